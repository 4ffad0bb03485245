"""The C++ plant core (ftc._core) against the independent reference simulation.

reference_sim.py integrates plant-model.md with scipy and shares no code with
the plant. Here both integrate the same valve sequences on degraded
parameters chosen so that pumps are weak and valves slow: empty tanks then
receive conduit inflow (pinned at 0) and sinks catch up with the conduit
level (ties). The reference is instrumented to prove these cases occur.
Checked: one-step maps from common states, free-running trajectories,
whole multi-episode plant runs across interval boundaries (ages, truncation,
termination), and the reward (C++, ftc.reward, reference) - plus ftc.reward
on hand-computed cases, which needs no build.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import reference_sim as ref
from ftc.plant import reward as ftc_reward

try:
    from ftc import _core
except ImportError as exc:  # the build must exist (scripts/test.sh builds it first)
    _core = None
    _CORE_MISSING = f"ftc._core is not built ({exc}); run cmake --build build --target _core"
needs_core = pytest.mark.skipif(_core is None, reason=_core is None and _CORE_MISSING or "")

LEVEL_TOL = 1e-4       # m: required agreement of free-running trajectories
ONE_STEP_TOL = 1e-5    # m: one step from a common state. The core integrates at rtol 1e-8
                       # (per-step errors measured 1.5e-8 m; 5e-7 m with an earlier rtol 1e-7),
                       # the reference at 1e-10; a mishandled switch costs 1e-3 m or more.
INF = math.inf
PARAM_KEYS = ("g", "height", "area", "resistance", "pump", "demand")

# Degradation factors 5..30 at ages up to 9: pumps down to 0, valves up to 2.8x slower,
# engines up to 2.8x hungrier. (tank_factor, engine_factor, age)
FAULTS = [
    ([6.0, INF, 12.0, 8.0, INF, 5.0], [10.0, 25.0], 7),
    ([INF, 20.0, 20.0, INF, 20.0, 20.0], [20.0, INF], 9),
    ([30.0, 5.0, INF, 10.0, 15.0, INF], [INF, 6.0], 4),
    ([8.0, 8.0, 8.0, 8.0, 8.0, 8.0], [INF, INF], 9),
]


def sticky_valves(rng: np.random.Generator, n: int, flip: float = 0.15) -> np.ndarray:
    """(n, 6) valve commands, each valve flipping with probability `flip` per step, so that
    valves stay open long enough for tanks to empty and levels to meet."""
    u = rng.integers(0, 2, 6)
    out = np.empty((n, 6), dtype=int)
    for k in range(n):
        u = np.where(rng.uniform(size=6) < flip, 1 - u, u)
        out[k] = u
    return out


def make_scenario(tank_factor, engine_factor, steps_per_interval: int = 512):
    s = _core.Scenario()
    s.tank_factor = list(map(float, tank_factor))
    s.engine_factor = list(map(float, engine_factor))
    s.steps_per_interval = int(steps_per_interval)
    return s


def core_params(tank_factor, engine_factor, age: float) -> dict:
    return dict(_core.degraded_params(make_scenario(tank_factor, engine_factor), float(age)))


def as_ref_params(d: dict) -> ref.Params:
    return ref.Params(g=float(d["g"]), **{k: np.array(d[k], dtype=float) for k in PARAM_KEYS[1:]})


def core_step(x: np.ndarray, u: np.ndarray, params: dict, dt: float = 1.0) -> np.ndarray:
    out = _core.integrate_step(list(map(float, x)), list(map(int, u)), params, dt)
    if isinstance(out, dict):
        out = out["x"] if "x" in out else out["level"]
    return np.asarray(out, dtype=float)


def run_core_plant(scenario, seed: int, valves: np.ndarray) -> dict[str, np.ndarray]:
    plant = _core.Plant(scenario, seed)
    plant.reset()
    rows = [plant.step(list(map(int, u))) for u in valves]
    return {key: np.array([r[key] for r in rows]) for key in
            ("level", "age", "step", "episode", "terminal", "truncated", "deficit")}


# --------------------------------------------------------------------------- parameters


@needs_core
@pytest.mark.parametrize("tank_factor, engine_factor, age", FAULTS + [([INF] * 6, [INF] * 2, 0)])
def test_degraded_params_agree(tank_factor, engine_factor, age) -> None:
    c = core_params(tank_factor, engine_factor, age)
    r = ref.degraded_params(tank_factor, engine_factor, age)
    for key in PARAM_KEYS:
        np.testing.assert_allclose(c[key], getattr(r, key), rtol=1e-14, err_msg=key)


# --------------------------------------------------------------------------- integration


@needs_core
def test_random_valve_sequences_agree_and_exercise_ties_and_pinned_tanks() -> None:
    """Both sides run the same sticky random valve sequences from full tanks on degraded
    parameters, each from its own state (errors accumulate), restarting full at terminal;
    one-step maps are also compared from the reference's state."""
    stats = ref.EventStats()
    worst_traj = worst_step = 0.0
    for seed, (tf, ef, age) in enumerate(FAULTS):
        rng = np.random.default_rng(100 + seed)
        cp = core_params(tf, ef, age)
        rp = ref.degraded_params(tf, ef, age)
        xr = np.ones(6)
        xc = np.ones(6)
        for k, u in enumerate(sticky_valves(rng, 70)):
            x_prev = xr
            xr = ref.integrate_step(xr, u, rp, 1.0, stats).x
            one = core_step(x_prev, u, cp)
            xc = core_step(xc, u, cp)
            err_step = np.abs(one - xr).max()
            err_traj = np.abs(xc - xr).max()
            assert err_step < ONE_STEP_TOL, (
                f"fault {seed} step {k}: x0={x_prev.tolist()} u={u.tolist()} "
                f"core={one.tolist()} reference={xr.tolist()}")
            assert err_traj < LEVEL_TOL, f"fault {seed} step {k}: {xc} vs {xr}"
            worst_step, worst_traj = max(worst_step, err_step), max(worst_traj, err_traj)
            if ref.is_terminal(xr, rp):
                assert ref.is_terminal(xc, rp)
                xr, xc = np.ones(6), np.ones(6)
    print(f"max level error: one step {worst_step:.2e} m, trajectory {worst_traj:.2e} m; {stats}")
    # The sequences must reach the hard cases, or the comparison proves little.
    assert stats.ties_formed >= 1 and stats.group_time > 0, stats  # a sink met the conduit level
    assert stats.pinned_time > 0, stats  # an empty tank passed its inflow to its pump
    assert stats.counts["empty"] >= 4, stats


@needs_core
@pytest.mark.parametrize("case", [
    # (x0, open tanks, dt, what): the hand-solved cases of test_reference_sim.py
    ([1, 1, 0.0137, 1, 1, 1], (), 1.0, "tank 3 empties after 0.274 s"),
    ([1, 0.99, 1, 1, 1, 1], (2, 4), 1.0, "sink catches up with a pumping source"),
    ([1, 1, 1, 1, 1, 0], (2, 4, 6), 8.0, "persistent tie, member leaves at 3.73 s"),
    ([0.4, 1, 0, 1, 1, 1], (1, 3), 2.0, "empty tank pinned by inflow"),
    ([0.6, 1, 0, 1, 1, 1], (1, 3), 6.0, "empty tank refills, empties, is pinned"),
    ([0.7] * 6, (1, 2, 5, 6), 1.0, "equal open levels"),
    ([0.25, 0.25, 0, 0, 0.25, 0.25], (1, 2, 3, 4, 5, 6), 3.0, "symmetric simultaneous leaves"),
])
def test_hand_cases_agree(case) -> None:
    x0, open_tanks, dt, what = case
    u = [1 if i + 1 in open_tanks else 0 for i in range(6)]
    c = core_step(np.array(x0, float), np.array(u), core_params([INF] * 6, [INF] * 2, 0), dt)
    r = ref.integrate_step(x0, u, ref.Params(), dt).x
    np.testing.assert_allclose(c, r, atol=ONE_STEP_TOL, err_msg=what)


@needs_core
def test_instantaneous_flows_agree_at_ties_and_empty_tanks() -> None:
    """compute_flows (mode classified at x) against the reference's flows, on random states
    with deliberate ties (an open tank copied to another's level, or within 1e-10 m of it)
    and empty open tanks."""
    rng = np.random.default_rng(21)
    for n in range(300):
        tf, ef, age = FAULTS[n % len(FAULTS)]
        cp, rp = core_params(tf, ef, age), ref.degraded_params(tf, ef, age)
        x = rng.uniform(0, 1, 6) * (rng.uniform(size=6) > 0.3)
        u = rng.integers(0, 2, 6)
        i, j = rng.choice(6, 2, replace=False)
        x[j] = x[i] + rng.choice([0.0, 5e-10, -5e-10])
        x = np.clip(x, 0, 1)
        c = _core.compute_flows(x, u, cp)
        f = ref.flows(x, ref.classify(x, u, rp), rp)
        conduit = np.multiply(f.dx, rp.area) + f.s
        where = f"x={x.tolist()} u={u.tolist()} fault={n % len(FAULTS)}"
        np.testing.assert_allclose(c["supply"], f.s, atol=1e-12, err_msg=where)
        np.testing.assert_allclose(c["deficit"], f.deficit, atol=1e-12, err_msg=where)
        np.testing.assert_allclose(c["conduit"], conduit, atol=1e-9, err_msg=where)


@needs_core
def test_core_step_conserves_fuel() -> None:
    rng = np.random.default_rng(4)
    for n in range(100):
        tf, ef, age = FAULTS[n % len(FAULTS)]
        cp = core_params(tf, ef, age)
        x = rng.uniform(0, 1, 6) * (rng.uniform(size=6) > 0.3)
        out = _core.integrate_step(x, rng.integers(0, 2, 6), cp, 1.0)
        assert x.sum() - out["x"].sum() == pytest.approx(out["supplied"].sum(), abs=1e-9)
        wing = [out["supplied"][:3].sum(), out["supplied"][3:].sum()]
        np.testing.assert_allclose(np.add(wing, out["deficit"]), cp["demand"], atol=1e-9)


@needs_core
def test_empty_tank_whose_inflow_exactly_equals_its_draw_is_pinned() -> None:
    """Tank 3 empty (exactly 0) and open, tank 1 full and open, E1 demand 0.1 = pump capacity:
    the inflow g x1 / R = 0.1 equals tank 3's draw at t = 0 and then falls below it, so tank 3
    stays pinned at 0 (plant-model.md: it stays at 0 while the inflow is smaller). By hand:
    x1 = exp(-0.1 t), tank 2 supplies 0.1 - 0.1 x1, so after 1 s x1 = e^-0.1 and
    x2 = 0.9 - (0.1 - (1 - e^-0.1)). The plant reaches this state itself (engine factor 2 at
    age 2, valves closed until both inner tanks are empty), see the second half."""
    params = core_params([INF] * 6, [2.0, 2.0], 2)
    assert list(params["demand"]) == [0.1, 0.1]
    x0 = np.array([1.0, 0.9, 0.0, 0.0, 0.9, 1.0])
    u = np.array([1, 0, 1, 0, 0, 0])
    x1 = math.exp(-0.1)
    expected = [x1, 0.9 - (0.1 - (1 - x1)), 0.0, 0.0, 0.8, 1.0]
    r = ref.integrate_step(x0, u, ref.degraded_params([INF] * 6, [2.0, 2.0], 2))
    np.testing.assert_allclose(r.x, expected, atol=1e-9)
    c = _core.integrate_step(x0, u, params, 1.0)
    assert x0.sum() - c["x"].sum() == pytest.approx(c["supplied"].sum(), abs=1e-9), (
        f"fuel not conserved: volume drop {x0.sum() - c['x'].sum()}, supplied "
        f"{c['supplied'].sum()}; core {c['x'].tolist()}")
    np.testing.assert_allclose(c["x"], expected, atol=ONE_STEP_TOL)

    # The same state reached by the plant: 30-step intervals, episode at age 2 from step 60.
    valves = np.zeros((73, 6), dtype=int)
    valves[71:, [0, 2]] = 1
    core = run_core_plant(make_scenario([INF] * 6, [2.0, 2.0], 30), 0, valves)
    traj = ref.simulate({"engine_factor": [2.0, 2.0]}, valves, steps_per_interval=30)
    np.testing.assert_allclose(core["level"][70], x0, atol=1e-12)
    np.testing.assert_allclose(traj.levels[71], expected, atol=1e-9)
    np.testing.assert_allclose(core["level"], traj.levels, atol=LEVEL_TOL)


@needs_core
def test_group_member_whose_pump_equals_the_group_rate_stays() -> None:
    """Tanks 1 and 6 full and open (a tie), tank 3 at 0.75 open, tank 2 empty; E1 demand 0.125
    (engine factor 4 at age 6): tank 3 pumps 0.1, tank 1 the other 0.025. Tank 3's inflow
    q = 0.1 (1 - 0.75) = 0.025, so the group falls at rho = (q + 0.025) / 2 = 0.025: tank 1's
    own rate equals rho and it stays (plant-model.md: leaves only if s_i/c_i > rho). Then the
    gap G = x_group - x3 obeys G' = 0.0875 - 0.15 G, G = 7/12 - (1/3) exp(-0.15 t), grows, so
    rho grows and the tie holds: 2 x_group + x3 = 2.75 - 0.125 t."""
    tf, ef, age = [INF] * 6, [4.0, INF], 6
    x0 = np.array([1.0, 0.0, 0.75, 0.75, 0.1, 1.0])
    u = np.array([1, 0, 1, 0, 0, 1])
    dt = 3.0
    gap = 7 / 12 - math.exp(-0.15 * dt) / 3
    xg = (2.75 - 0.125 * dt + gap) / 3
    expected = [xg, 0.0, xg - gap, 0.75 - 0.05 * dt, 0.1, xg]
    r = ref.integrate_step(x0, u, ref.degraded_params(tf, ef, age), dt)
    np.testing.assert_allclose(r.x, expected, atol=1e-9)
    c = _core.integrate_step(x0, u, core_params(tf, ef, age), dt)
    np.testing.assert_allclose(c["x"], expected, atol=ONE_STEP_TOL,
                               err_msg="tanks 1 and 6 must stay tied")


@needs_core
@pytest.mark.parametrize("off, rise", [(1e-4, 8e-5), (1e-4, 9e-5), (3e-4, 2.3e-4),
                                       (3e-4, 2.4e-4), (1e-3, 7.5e-4), (1e-3, 7.6e-4)])
def test_a_member_that_leaves_a_tie_it_just_reached_rejoins_it(off, rise) -> None:
    """Tank 5 (drawing 0.02 after tank 4's 0.03) falls `off` onto tank 1, tank 2 a sink
    0.2 - rise below: at the tie tank 5 leaves (its draw outruns the pair while
    q2 < 0.02), and q2, growing, passes 0.02 within ~1 ms: tank 5 rejoins and ends the
    step tied with tank 1 (tests/cpp/test_integrator.cpp scans the family and explains
    it). From these states the plant once missed the rejoin (tank 5 ended 4e-4 m above
    tank 1) or refused the step as chattering."""
    pump = np.array([0.1, 0.1, 0.1, 0.03, 0.1, 0.1])
    x0 = np.array([0.5, 0.3 + rise, 0.0, 0.8, 0.5 + off, 0.8])
    u = np.array([1, 1, 0, 0, 1, 0])
    r = ref.integrate_step(x0, u, ref.Params(pump=pump), 1.0).x
    assert abs(r[4] - r[0]) < 1e-12
    params = dict(g=10.0, height=np.ones(6), area=np.ones(6), resistance=np.full(6, 100.0),
                  pump=pump, demand=np.full(2, 0.05))
    c = _core.integrate_step(x0, u, params, 1.0)
    np.testing.assert_allclose(c["x"], r, atol=ONE_STEP_TOL)


# --------------------------------------------------------------------------- whole plant runs


@needs_core
@pytest.mark.parametrize("tank_factor, engine_factor, policy, spi", [
    ([INF, INF, INF, INF, 5.0, 5.0], [1.5, 2.5], "random", 40),
    ([6.0, INF, 12.0, 8.0, INF, 5.0], [1.0, 3.0], "random", 40),
    ([INF] * 6, [1.0, 2.0], "open", 40),
    ([INF] * 6, [INF] * 2, "closed", 70),  # nominal: 59-step episodes, then a cut one
])
def test_multi_episode_trajectories_with_interval_truncation(tank_factor, engine_factor, policy,
                                                             spi) -> None:
    # Short intervals: 200 steps cross several ages, each interval cutting an episode, and
    # engines degrading fast (D_E 1..3) end episodes (terminal) inside the intervals.
    n = 200
    rng = np.random.default_rng(7)
    valves = {"random": sticky_valves(rng, n), "open": np.ones((n, 6), dtype=int),
              "closed": np.zeros((n, 6), dtype=int)}[policy]
    core = run_core_plant(make_scenario(tank_factor, engine_factor, spi), 3, valves)
    traj = ref.simulate({"tank_factor": tank_factor, "engine_factor": engine_factor}, valves,
                        steps_per_interval=spi)
    np.testing.assert_array_equal(core["age"], traj.age)
    np.testing.assert_array_equal(core["step"], traj.step)
    np.testing.assert_array_equal(core["episode"] - core["episode"][0], traj.episode)
    np.testing.assert_array_equal(core["terminal"], traj.terminal)
    np.testing.assert_array_equal(core["truncated"], traj.truncated)
    err = np.abs(core["level"] - traj.levels).max()
    print(f"max level error {err:.2e} m; {traj.terminal.sum()} terminal, "
          f"{traj.truncated.sum()} truncated episodes")
    assert err < LEVEL_TOL, f"max level error {err:.2e} m"
    assert traj.truncated.sum() >= 2 and traj.terminal.sum() >= 2
    assert traj.age.max() == (n - 1) // spi
    # The reward the controller computes from these levels agrees on both sides.
    np.testing.assert_allclose(ftc_reward.reward(core["level"], valves), traj.reward, atol=1e-3)


@needs_core
def test_continuous_degradation_mode() -> None:
    # age = operating steps / steps per interval, changing every step.
    spi, n = 40, 100
    valves = sticky_valves(np.random.default_rng(8), n)
    scenario = make_scenario([10.0, INF, INF, INF, INF, 4.0], [2.0, INF], spi)
    scenario.mode = "continuous"
    core = run_core_plant(scenario, 0, valves)
    traj = ref.simulate({"tank_factor": [10.0, INF, INF, INF, INF, 4.0],
                         "engine_factor": [2.0, INF], "mode": "continuous"}, valves,
                        steps_per_interval=spi)
    np.testing.assert_allclose(core["age"], np.arange(n) / spi, rtol=1e-15)
    np.testing.assert_array_equal(core["terminal"], traj.terminal)
    np.testing.assert_array_equal(core["truncated"], traj.truncated)
    assert np.abs(core["level"] - traj.levels).max() < LEVEL_TOL


# --------------------------------------------------------------------------- reward


def reward_cases(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    x = rng.uniform(0, 1, (n, 6)) * (rng.uniform(size=(n, 6)) > 0.3)
    x[0] = 0.0                      # empty plant
    x[1] = [0, 0, 0, 0, 0, 5e-7]    # below the empty threshold
    x[2] = [0, 0, 0, 0, 0, 0.3]     # all the fuel at one arm: sigma = 0
    x[3] = 1.0
    return x, rng.integers(0, 2, (n, 6))


@needs_core
def test_core_reward_matches_ftc_reward_and_reference() -> None:
    x, u = reward_cases(np.random.default_rng(5), 200)
    py = ftc_reward.reward_terms(x, u)
    for k in range(len(x)):
        c = dict(_core.reward(list(map(float, x[k])), list(map(int, u[k]))))
        r = ref.reward(x[k], u[k])
        for key, field in (("reward", "reward"), ("cg", "cg"), ("spread", "spread"),
                           ("activity", "activity")):
            assert c[key] == pytest.approx(r[key], abs=1e-12), (key, x[k], u[k])
            assert getattr(py, field)[k] == pytest.approx(r[key], abs=1e-12), (key, x[k], u[k])


@needs_core
def test_every_form_of_the_reward_is_the_definition() -> None:
    """The reward's forms (plant/reward.py's module doc) against its definition,
    reward_terms, on the same levels: empty, nearly empty, one-arm and negative
    (sensor noise) plants among random ones. NumPy's form is the definition
    itself; torch's runs the same expression (float64: equal to rounding);
    the moments form and C++ sum in another order (only rounding differs)."""
    torch = pytest.importorskip("torch")
    x, u = reward_cases(np.random.default_rng(7), 640)
    x[4:8] -= 0.01  # negative levels count as empty tanks
    x[8:12] = 1e-8
    defined = ftc_reward.reward_terms(x, u)
    np.testing.assert_array_equal(defined.reward, defined.balance - defined.activity)
    np.testing.assert_allclose(ftc_reward.reward_moments(x, u), defined.reward, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ftc_reward.reward_torch(torch.tensor(x), torch.tensor(u)).numpy(),
                               defined.reward, rtol=0, atol=1e-12)
    core = [dict(_core.reward(list(map(float, x[k])), list(map(int, u[k]))))
            for k in range(len(x))]
    for key in ("reward", "cg", "spread", "activity"):
        np.testing.assert_allclose([c[key] for c in core], getattr(defined, key),
                                   rtol=0, atol=1e-12, err_msg=key)


def test_ftc_reward_matches_reference_without_core() -> None:
    x, u = reward_cases(np.random.default_rng(6), 200)
    py = ftc_reward.reward(x, u)
    np.testing.assert_allclose(py, [ref.reward(x[k], u[k])["reward"] for k in range(len(x))],
                               atol=1e-12)


def test_ftc_reward_full_balanced_plant() -> None:
    terms = ftc_reward.reward_terms(np.ones(6), np.zeros(6))
    assert terms.cg == 0.0
    assert terms.spread == pytest.approx(math.sqrt(14 / 3))
    assert float(terms.reward) == pytest.approx(2.160, abs=5e-4)
    assert float(ftc_reward.reward(np.ones(6), np.ones(6))) == pytest.approx(math.sqrt(14 / 3) - 1)


def test_ftc_reward_unbalanced_by_hand() -> None:
    # Tanks 1..6 at (1, 0.5, 0, 0, 0, 0.5), valves 1 and 2 open.
    # w = (1, .5, 0, 0, 0, .5), W = 2, cg = (-3 - 1 + 1.5) / 2 = -1.25.
    # var = (1 * 1.75^2 + .5 * 0.75^2 + .5 * 4.25^2) / 2 = (3.0625 + .28125 + 9.03125) / 2 = 6.1875
    # r = (1 - 1.25/3) * sqrt(6.1875) - 2/6
    terms = ftc_reward.reward_terms(np.array([1, 0.5, 0, 0, 0, 0.5]), np.array([1, 1, 0, 0, 0, 0]))
    assert float(terms.cg) == pytest.approx(-1.25)
    assert float(terms.spread) == pytest.approx(math.sqrt(6.1875))
    assert float(terms.activity) == pytest.approx(1 / 3)
    assert float(terms.reward) == pytest.approx((1 - 1.25 / 3) * math.sqrt(6.1875) - 1 / 3)


def test_ftc_reward_empty_plant_is_minus_activity() -> None:
    u = np.array([1, 0, 1, 0, 1, 1])
    assert float(ftc_reward.reward(np.zeros(6), u)) == pytest.approx(-4 / 6)
    assert float(ftc_reward.reward(np.full(6, 1e-8), u)) == pytest.approx(-4 / 6)  # W < 1e-6
    # Negative levels (sensor noise) count as empty tanks.
    assert float(ftc_reward.reward(np.array([-0.1, 0, 0, 0, 0, 0]), np.zeros(6))) == 0.0


def test_ftc_reward_batch_shapes() -> None:
    rng = np.random.default_rng(0)
    x, u = rng.uniform(0, 1, (4, 5, 6)), rng.integers(0, 2, (4, 5, 6))
    r = ftc_reward.reward(x, u)
    assert r.shape == (4, 5)
    assert ftc_reward.reward_terms(x, u).cg.shape == (4, 5)
    assert np.ndim(ftc_reward.reward(x[0, 0], u[0, 0])) == 0
    np.testing.assert_allclose(r[2, 3], ftc_reward.reward(x[2, 3], u[2, 3]))


def test_reward_torch_equals_reward() -> None:
    torch = pytest.importorskip("torch")
    x, u = reward_cases(np.random.default_rng(1), 64)
    expected = ftc_reward.reward(x, u)
    got = ftc_reward.reward_torch(torch.tensor(x), torch.tensor(u))
    assert got.dtype == torch.float64 and got.shape == (64,)
    np.testing.assert_allclose(got.numpy(), expected, atol=1e-12)
    got32 = ftc_reward.reward_torch(torch.tensor(x, dtype=torch.float32), torch.tensor(u))
    np.testing.assert_allclose(got32.numpy(), expected, atol=1e-5)
    batch = ftc_reward.reward_torch(torch.tensor(x.reshape(8, 8, 6)),
                                    torch.tensor(u.reshape(8, 8, 6)))
    np.testing.assert_allclose(batch.numpy(), expected.reshape(8, 8), atol=1e-12)
