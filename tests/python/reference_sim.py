"""Independent reference simulation of ../shared/design/plant-model.md, for the tests.

It shares no code with the plant (C++ core, ftc.plant, ftc.reward): the
tests compare the plant against it, so a shared mistake would go unseen.

Equations. Levels x (m) of six tanks, valves u held over a step:

    dx_i/dt = (q_in_i - q_out_i - s_i) / c_i

* pumps, innermost first per engine: s_i = min(p_i, remaining demand) for a
  tank with fuel; an empty tank receiving conduit inflow q supplies
  min(p_i, remaining, q) and stays at 0 ("pinned") while q is the smaller;
* conduit: V = g * (highest open level); open tanks within 1e-9 m of it form
  the source group G, the other open tanks are sinks with q_k = (V - g x_k)/R_k;
  G falls together at rho = (Q + sum_G s_i) / sum_G c_i, a member with
  s_i/c_i > rho leaves G (becomes a sink); repeated until none leaves.

Solver. Between two switches the right-hand side is smooth (affine in x, up
to a continuous min() kink when a pinned tank feeds the pump walk), so an
explicit Runge-Kutta method is right: the plant is not stiff (slowest time
constant R c / g = 10 s, fastest about R c / (6 g) ~ 1.7 s at nominal, longer
when valves degrade). We use scipy's DOP853 with rtol = 1e-10 and atol = 1e-12
m: levels are O(1) m and the tests compare to 1e-4 m over a few hundred steps,
so the relative error per step (~1e-10) leaves six orders of margin after
accumulation; atol = 1e-12 m keeps near-empty tanks (levels -> 0, where rtol
alone would allow sloppy steps) resolved well below the 1e-9 m tie tolerance
and the 1e-6 m^3 termination tolerance, so neither classification can be
flipped by integration error. Every switch of the hybrid system is a terminal
event located by root finding (scipy uses Brent's method to ~4 machine
epsilons in time); integration restarts from there under the new mode:

* a tank with a falling level reaching 0               (x_i -> 0, falling)
* a sink reaching the conduit level                    (x_lead - x_k -> 0)
* a pinned empty tank's inflow exceeding its pump draw (draw - q_k -> 0)
* a group member whose pump outpaces the group         (rho - s_i/c_i -> 0)

scipy checks the sign of each root only at the ends of accepted steps, so a root that
dips below zero and comes back within one step is missed (seen: a sink crossing the
conduit level, the wrong mode then carrying it back, within one 0.7 s step). Steps are
therefore capped at 0.05 s: a dip shorter than that is a near-tangent touch whose
effect on the levels is far below the test tolerances.

After an event the mode is recomputed; the switch that fired is applied
explicitly (the tank set to exactly 0, the member forced out, the pinned tank
released) so that a root sitting at zero cannot re-fire forever.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.integrate import solve_ivp

N_TANKS = 6
ARMS = (-3.0, -2.0, -1.0, 1.0, 2.0, 3.0)
PUMP_ORDER = ((2, 1, 0), (3, 4, 5))  # engine 1 from tanks 3,2,1; engine 2 from 4,5,6 (0-based)
TIE_TOL = 1e-9          # m: open tanks this close to the highest open level are sources
TERMINAL_TOL = 1e-6     # m^3: episode ends when volume < demand * dt + this
EMPTY_VOLUME = 1e-6     # m^3: below this the reward's cg and spread are 0
RTOL = 1e-10
ATOL = 1e-12            # m
MAX_STEP = 0.05         # s: see the header (roots are only checked at step ends)
SIMULTANEOUS = 1e-12    # s: events closer than this in time are applied together
ROOT_OFFSET = 1e-15     # added to every root: scipy fires a root that sits at exactly 0
                        # (two open tanks at one level, a tank filling from 0 at rate 0), and
                        # each condition it encodes is strict (leave when s/c > rho, ...)
MAX_EVENTS = 1000       # per step; more means chattering, which the spec rules out

FUEL, PINNED, EMPTY = 0, 1, 2  # tank status within a mode


@dataclass
class Params:
    """Physical parameters in force during a step (plant-model.md, "Nominal parameters")."""

    g: float = 10.0
    height: np.ndarray = field(default_factory=lambda: np.ones(N_TANKS))           # m
    area: np.ndarray = field(default_factory=lambda: np.ones(N_TANKS))             # m^2
    resistance: np.ndarray = field(default_factory=lambda: np.full(N_TANKS, 100.0))
    pump: np.ndarray = field(default_factory=lambda: np.full(N_TANKS, 0.1))        # m^3/s
    demand: np.ndarray = field(default_factory=lambda: np.full(2, 0.05))           # m^3/s

    def copy(self, **changes) -> "Params":
        values = {k: np.array(getattr(self, k), dtype=float) if k != "g" else self.g
                  for k in ("g", "height", "area", "resistance", "pump", "demand")}
        for k, v in changes.items():
            values[k] = v if k == "g" else np.array(v, dtype=float)
        return Params(**values)


def degraded_params(tank_factor: Sequence[float], engine_factor: Sequence[float], age: float,
                    nominal: Params | None = None) -> Params:
    """Parameters at `age` intervals: p0 max(0, 1 - a/D_T), R0 (1 + a/D_T), d0 (1 + a/D_E);
    a factor D = inf is healthy."""
    nominal = nominal or Params()
    ft = np.array([age / float(d) for d in tank_factor])  # a / inf = 0
    fe = np.array([age / float(d) for d in engine_factor])
    return nominal.copy(pump=nominal.pump * np.maximum(0.0, 1.0 - ft),
                        resistance=nominal.resistance * (1.0 + ft),
                        demand=nominal.demand * (1.0 + fe))


# --------------------------------------------------------------------------- modes


@dataclass
class Mode:
    """Discrete state fixed between two events."""

    status: list[int]        # FUEL / PINNED / EMPTY per tank
    group: list[int]         # source group (open tanks at the conduit level)
    sinks: list[int]         # open tanks below it
    lead: int                # group member setting V (-1: no conduit flow)


@dataclass
class Flows:
    q: list[float]           # conduit inflow of each sink, m^3/s (0 elsewhere)
    s: list[float]           # pump supply of each tank, m^3/s
    rem: list[float]         # demand still unmet when the walk reaches each tank, m^3/s
    deficit: list[float]     # per engine, m^3/s
    rho: float               # group fall rate, m/s
    dx: list[float]          # m/s


def flows(x: Sequence[float], mode: Mode, p: Params) -> Flows:
    """Flows at levels x under a fixed mode (smooth in x apart from min() kinks)."""
    q = [0.0] * N_TANKS
    if mode.lead >= 0:
        v = p.g * x[mode.lead]
        for k in mode.sinks:
            q[k] = (v - p.g * x[k]) / p.resistance[k]
    s = [0.0] * N_TANKS
    rem_at = [0.0] * N_TANKS
    deficit = [0.0, 0.0]
    for j, order in enumerate(PUMP_ORDER):
        rem = float(p.demand[j])
        for i in order:
            rem_at[i] = rem
            if mode.status[i] == FUEL:
                si = min(p.pump[i], rem)
            elif mode.status[i] == PINNED:
                si = min(p.pump[i], rem, q[i])
            else:
                si = 0.0
            s[i] = si
            rem -= si
        deficit[j] = rem
    dx = [-s[i] / p.area[i] for i in range(N_TANKS)]
    rho = 0.0
    if mode.lead >= 0:
        total_q = 0.0
        for k in mode.sinks:
            total_q += q[k]
        draw = area = 0.0
        for i in mode.group:
            draw += s[i]
            area += p.area[i]
        rho = (total_q + draw) / area
        for i in mode.group:
            dx[i] = -rho
        for k in mode.sinks:
            dx[k] = (q[k] - s[k]) / p.area[k]
    return Flows(q, s, rem_at, deficit, rho, dx)


def classify(x: Sequence[float], u: Sequence[int], p: Params, force_leave: set[int] = frozenset(),
             force_rise: set[int] = frozenset()) -> Mode:
    """The mode in force from levels x onwards (x already clamped to [0, h])."""
    open_ = [i for i in range(N_TANKS) if u[i]]
    top = max((x[i] for i in open_), default=0.0)
    if top > 0.0:
        group = [i for i in open_ if x[i] >= top - TIE_TOL]
        sinks = [i for i in open_ if i not in group]
    else:  # no valve open, or every open tank empty: nothing flows
        group, sinks = [], []

    # Pump walk: decides which empty sinks are pinned (inflow below their draw).
    status = [EMPTY] * N_TANKS
    for j, order in enumerate(PUMP_ORDER):
        rem = float(p.demand[j])
        for i in order:
            if x[i] > 0.0:
                status[i] = FUEL
                rem -= min(p.pump[i], rem)
            elif i in sinks:
                inflow = p.g * top / p.resistance[i]
                draw = min(p.pump[i], rem)
                if i in force_rise or inflow >= draw:
                    status[i] = FUEL  # fills from 0 while pumping its full draw
                    rem -= draw
                else:
                    status[i] = PINNED
                    rem -= inflow

    # Group: members whose own pump outpaces the group's fall leave it.
    while len(group) > 0:
        lead = max(group, key=lambda i: x[i])
        f = flows(x, Mode(status, group, sinks, lead), p)
        leave = [i for i in group
                 if i in force_leave or f.s[i] / p.area[i] > f.rho]
        if not leave or len(leave) == len(group):
            break  # all leaving is impossible for rho is a weighted mean plus Q >= 0
        group = [i for i in group if i not in leave]
        sinks = sorted(sinks + leave)
    lead = max(group, key=lambda i: x[i]) if group else -1
    return Mode(status, group, sinks, lead)


def _roots(mode: Mode, p: Params) -> list[tuple[str, int, Callable[[np.ndarray], float]]]:
    """Root functions that end `mode`, as (kind, tank, g(x)); each fires falling through 0."""
    roots = []
    for i in range(N_TANKS):
        if mode.status[i] == FUEL:
            roots.append(("empty", i, lambda x, i=i: x[i]))
    if mode.lead >= 0:
        for k in mode.sinks:
            if mode.status[k] == FUEL:
                roots.append(("join", k, lambda x, k=k: x[mode.lead] - x[k]))
            elif mode.status[k] == PINNED:
                def unpin(x, k=k):
                    f = flows(x, mode, p)
                    return min(p.pump[k], f.rem[k]) - f.q[k]
                roots.append(("unpin", k, unpin))
        if len(mode.group) > 1:
            for i in mode.group:
                def leave(x, i=i):
                    f = flows(x, mode, p)
                    return f.rho - f.s[i] / p.area[i]
                roots.append(("leave", i, leave))
    return roots


# --------------------------------------------------------------------------- one step


@dataclass
class EventStats:
    """Instrumentation: what the hybrid integration went through."""

    counts: dict[str, int] = field(default_factory=lambda: {"empty": 0, "join": 0, "leave": 0,
                                                            "unpin": 0})
    group_time: float = 0.0    # s spent with a source group of 2+ tanks
    pinned_time: float = 0.0   # s spent with an empty tank pinned at 0 by its inflow
    refill_time: float = 0.0   # s spent with an empty open tank filling from 0
    ties_formed: int = 0       # join events after which 2+ tanks fall together

    def merge(self, other: "EventStats") -> None:
        for k, v in other.counts.items():
            self.counts[k] += v
        self.group_time += other.group_time
        self.pinned_time += other.pinned_time
        self.refill_time += other.refill_time
        self.ties_formed += other.ties_formed


@dataclass
class StepResult:
    x: np.ndarray          # levels after the step, m
    supplied: np.ndarray   # fuel pumped from each tank, m^3
    deficit: np.ndarray    # unmet demand per engine, m^3
    events: int            # switches located


def _as_lists(p: Params) -> Params:
    """The same parameters held in Python lists: element access in the right-hand side is
    several times faster than on numpy arrays."""
    return Params(g=float(p.g), height=list(map(float, p.height)), area=list(map(float, p.area)),
                  resistance=list(map(float, p.resistance)), pump=list(map(float, p.pump)),
                  demand=list(map(float, p.demand)))


def integrate_step(x0: Sequence[float], u: Sequence[int], p: Params, dt: float = 1.0,
                   stats: EventStats | None = None) -> StepResult:
    """Integrates one step of dt seconds from levels x0 (6,) m with valves u (6,) held."""
    h = np.asarray(p.height, dtype=float)
    p = _as_lists(p)
    x = np.clip(np.asarray(x0, dtype=float), 0.0, h)
    u = [int(v) for v in u]
    supplied = np.zeros(N_TANKS)
    deficit = np.zeros(2)
    t = 0.0
    events = 0
    force_leave: set[int] = set()
    force_rise: set[int] = set()
    while t < dt:
        mode = classify(x, u, p, force_leave, force_rise)
        roots = _roots(mode, p)

        def rhs(_t, y, mode=mode):
            f = flows(y[:N_TANKS].tolist(), mode, p)
            return [*f.dx, *f.s, *f.deficit]

        evs = []
        for _kind, _i, g in roots:
            ev = (lambda _t, y, g=g: g(y[:N_TANKS].tolist()) + ROOT_OFFSET)
            ev.terminal = True
            ev.direction = -1
            evs.append(ev)
        y0 = np.concatenate([x, np.zeros(N_TANKS + 2)])
        sol = solve_ivp(rhs, (t, dt), y0, method="DOP853", rtol=RTOL, atol=ATOL,
                        max_step=MAX_STEP, events=evs or None)
        if sol.status < 0:
            raise RuntimeError(f"solve_ivp failed: {sol.message}")
        t_new = float(sol.t[-1])
        y = sol.y[:, -1]
        span = t_new - t
        if stats is not None:
            if len(mode.group) > 1:
                stats.group_time += span
            if any(st == PINNED for st in mode.status):
                stats.pinned_time += span
            if any(mode.status[k] == FUEL and x[k] == 0.0 for k in mode.sinks):
                stats.refill_time += span
        supplied += y[N_TANKS:2 * N_TANKS]
        deficit += y[2 * N_TANKS:]
        x = np.clip(y[:N_TANKS], 0.0, h)
        t = t_new
        if span > SIMULTANEOUS:
            # Forced switches hold only until time moves on; simultaneous events (common in
            # this symmetric plant: both wings switch at once) accumulate them instead, or
            # the first switch would be undone when the second one is applied.
            force_leave, force_rise = set(), set()
        if sol.status == 1:  # an event ended the mode
            fired = [r for r, te in zip(roots, sol.t_events) if len(te) and te[-1] >= t_new - 1e-15]
            for kind, i, _g in fired:
                events += 1
                if stats is not None:
                    stats.counts[kind] += 1
                if kind == "empty":
                    x[i] = 0.0
                elif kind == "leave":
                    force_leave.add(i)
                elif kind == "unpin":
                    force_rise.add(i)
            if stats is not None and any(k == "join" for k, _i, _g in fired):
                after = classify(x, u, p, force_leave, force_rise)
                stats.ties_formed += int(len(after.group) > 1)
            if events > MAX_EVENTS:
                raise RuntimeError(f"more than {MAX_EVENTS} events in one step (chattering)")
        else:
            t = dt
    return StepResult(x, supplied, deficit, events)


# --------------------------------------------------------------------------- reward


def reward(x_next: Sequence[float], valves: Sequence[int],
           area: Sequence[float] = (1.0,) * N_TANKS) -> dict[str, float]:
    """Reward of plant-model.md, "Reward", written out term by term for one step."""
    w = [area[i] * max(float(x_next[i]), 0.0) for i in range(N_TANKS)]
    total = sum(w)
    if total < EMPTY_VOLUME:
        cg = spread = 0.0
    else:
        cg = sum(w[i] * ARMS[i] for i in range(N_TANKS)) / total
        spread = math.sqrt(sum(w[i] * (ARMS[i] - cg) ** 2 for i in range(N_TANKS)) / total)
    activity = sum(int(v) for v in valves) / N_TANKS
    r = (1.0 - abs(cg) / max(abs(a) for a in ARMS)) * spread - activity
    return {"reward": r, "cg": cg, "spread": spread, "activity": activity}


def is_terminal(x: Sequence[float], p: Params, dt: float = 1.0) -> bool:
    volume = float(np.dot(p.area, x))
    return volume < float(np.sum(p.demand)) * dt + TERMINAL_TOL


# --------------------------------------------------------------------------- episodes

ValveSource = Sequence[int] | np.ndarray | Callable[[int, np.ndarray], Sequence[int]]


@dataclass
class Episode:
    levels: np.ndarray     # (n, 6) levels after each step, m
    valves: np.ndarray     # (n, 6)
    rewards: np.ndarray    # (n,)
    deficit: np.ndarray    # (n, 2) m^3
    terminal: bool


def _valves_at(source: ValveSource, k: int, x: np.ndarray) -> np.ndarray | None:
    if callable(source):
        return np.asarray(source(k, x), dtype=int)
    arr = np.asarray(source, dtype=int)
    if arr.ndim == 1:
        return arr
    return arr[k] if k < len(arr) else None


def episode(params: Params, valve_sequence: ValveSource, max_steps: int = 10_000,
            x0: Sequence[float] | None = None, stats: EventStats | None = None) -> Episode:
    """One episode at fixed parameters from full tanks (or x0) until terminal, or until the
    valve sequence ((6,) constant, (n, 6), or f(step_index, x) -> (6,)) or max_steps runs out."""
    x = np.array(params.height if x0 is None else x0, dtype=float)
    levels, valves, rewards, deficits = [], [], [], []
    terminal = False
    for k in range(max_steps):
        u = _valves_at(valve_sequence, k, x)
        if u is None:
            break
        res = integrate_step(x, u, params, 1.0, stats)
        x = res.x
        levels.append(x.copy())
        valves.append(u.copy())
        rewards.append(reward(x, u, params.area)["reward"])
        deficits.append(res.deficit)
        if is_terminal(x, params):
            terminal = True
            break
    return Episode(np.array(levels).reshape(-1, N_TANKS), np.array(valves).reshape(-1, N_TANKS),
                   np.array(rewards), np.array(deficits).reshape(-1, 2), terminal)


@dataclass
class Trajectory:
    """One row per control step, as in the trajectory export (ftc.simulate)."""

    episode: np.ndarray    # (n,) int, episode index
    step: np.ndarray       # (n,) int, step within the episode, from 1
    age: np.ndarray        # (n,) float, intervals in force during the step
    valves: np.ndarray     # (n, 6) int
    levels: np.ndarray     # (n, 6) m, after the step
    terminal: np.ndarray   # (n,) bool
    truncated: np.ndarray  # (n,) bool
    reward: np.ndarray     # (n,)

    def rows(self) -> list[list]:
        """episode,step,age,u1..u6,x1..x6 rows."""
        return [[int(self.episode[k]), int(self.step[k]), float(self.age[k]),
                 *map(int, self.valves[k]), *map(float, self.levels[k])]
                for k in range(len(self.step))]


def simulate(scenario: dict, valves_per_step: np.ndarray, steps_per_interval: int = 512,
             first_episode: int = 0, nominal: Params | None = None,
             stats: EventStats | None = None) -> Trajectory:
    """Runs the plant over len(valves_per_step) operating steps from age 0.

    scenario: {"tank_factor": 6 floats, "engine_factor": 2 floats (inf healthy),
    "mode": "stepwise" | "continuous"}. Each episode starts full; after a terminal
    step, or after the last step of an interval (then truncated), a new one starts.
    """
    nominal = nominal or Params()
    tank_factor = scenario.get("tank_factor", [math.inf] * N_TANKS)
    engine_factor = scenario.get("engine_factor", [math.inf] * 2)
    continuous = scenario.get("mode", "stepwise") == "continuous"
    valves_per_step = np.asarray(valves_per_step, dtype=int)
    n = len(valves_per_step)
    out = {k: [] for k in ("episode", "step", "age", "terminal", "truncated", "reward")}
    levels = np.zeros((n, N_TANKS))
    ep, step = first_episode, 0
    x = np.array(nominal.height, dtype=float)
    for k in range(n):
        age = k / steps_per_interval if continuous else float(k // steps_per_interval)
        p = degraded_params(tank_factor, engine_factor, age, nominal)
        u = valves_per_step[k]
        x = integrate_step(x, u, p, 1.0, stats).x
        step += 1
        terminal = is_terminal(x, p)
        truncated = (not terminal) and (k + 1) % steps_per_interval == 0
        levels[k] = x
        for key, val in (("episode", ep), ("step", step), ("age", age), ("terminal", terminal),
                         ("truncated", truncated), ("reward", reward(x, u, p.area)["reward"])):
            out[key].append(val)
        if terminal or truncated:
            ep, step = ep + 1, 0
            x = np.array(nominal.height, dtype=float)
    return Trajectory(np.array(out["episode"], dtype=int), np.array(out["step"], dtype=int),
                      np.array(out["age"], dtype=float), valves_per_step.copy(), levels,
                      np.array(out["terminal"], dtype=bool), np.array(out["truncated"], dtype=bool),
                      np.array(out["reward"], dtype=float))
