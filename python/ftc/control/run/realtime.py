"""The interval runner's loop on a plant in real-time mode (``--realtime RATE``,
or ``--attach`` to a plant started with ``--mode realtime``).

The plant does not wait: it steps every 1/RATE s on the last command it
received. For every state it publishes the loop takes the newest one, asks
the agent for valves and sends them at once; the plant's step, the reward and
the agent's ``observe`` are then accounted for every plant step, including
steps the controller was too late for (their valves are the ones the plant
applied):

    tick k: state --> [observe the steps since the last decision] --> act --> command
                                                                 (before tick k+1)

Learning stays off this path: an agent sees ``background_learning = True``
and runs its updates, refits and offline phases on other threads or
processes, swapping the acting policy in between two steps (PPO: see
:class:`ftc.control.agents.ppo_online.OnlinePPO`). The next interval's first
decision is sent before the previous interval's bookkeeping (end_interval,
checkpoint, metrics.csv), so the plant never waits for it.

Deadlines are measured per interval (metrics.csv, TensorBoard):

    deadline_misses     plant steps taken without a command answering the state before them
    latency_*_ms        from a state's arrival to its command's send (p50, p99, max)
    watchdog_trips      times the plant's watchdog put the valves in the safe state
    plant_missed_ticks  the plant's own count: steps with no command newer than the state
                        before them (it counts between the run's phases too, and a late
                        answer it applied is a miss above but not here)
    lost_states         states that never arrived (their steps are not learned from)

and so is foreign traffic (a neighbour's messages on the run's channels):

    refused_*           states the link refused, by cause: bad_decode, other_session,
                        stale (no newer than the last), seq_jump (implausibly far ahead),
                        and with a key bad_signature, replay, old_timestamp
    plant_other_session the plant's count of commands of other sessions it refused
    foreign_commands    plant steps taken on a command of this session the run never
                        sent (someone holding the session id commands the plant)

A run that saw any of it says so in a warning at its end (:meth:`RealtimeLoop.foreign_note`).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ftc.common.errors import RunError
from ftc.control.run.agent import Agent, StepContext, Transition
from ftc.control.run.checkpoint import finite_observation
from ftc.control.run.telemetry import Telemetry
from ftc.plant.realtime_link import RealtimeLink, observation
from ftc.plant.reward import reward

# RealtimeLink.refused's keys
REFUSALS = ("bad decode", "other session", "stale", "seq jump", "bad signature", "replay",
            "old timestamp")
REALTIME_COLUMNS = ("deadline_misses", "latency_p50_ms", "latency_p99_ms", "latency_max_ms",
                    "watchdog_trips", "plant_missed_ticks", "lost_states",
                    *(f"refused_{r.replace(' ', '_')}" for r in REFUSALS),
                    "plant_other_session", "foreign_commands")
KEPT_COMMANDS = 256  # sent commands remembered to tell which one the plant applied


class RealtimeLoop:
    """Drives ``agent`` on a real-time ``link`` for the interval runner (see
    the module doc). One per run; its deadline counters restart with each
    interval's first decision."""

    def __init__(self, link: RealtimeLink, agent: Agent, telemetry: Telemetry) -> None:
        self.link, self.agent, self.telemetry = link, agent, telemetry
        self.commands: dict[int, np.ndarray] = {}  # sent seq -> valves
        self.awaited: int | None = None  # seq of the command answering self.msg, if sent
        self.msg: Any = None  # the newest state
        self.obs = None  # its observation
        self.opened = False  # the next interval's episode is open and acted on
        self.where = ""
        self.sent_max = 0  # the highest seq this run sent in its session
        self.foreign_total = 0  # steps on commands this run never sent
        self._run_refused = dict(link.refused)
        self._first_other: int | None = None  # the plant's refusal count when the run began
        self._first_rejected: int | None = None  # its rejected commands then
        self._restart_counts()

    # -- deadlines ----------------------------------------------------------------
    def _restart_counts(self) -> None:
        self.latencies_ns: list[int] = []
        self.misses = 0
        self.lost = 0  # states that never arrived (a gap in the plant's state counter)
        self.foreign = 0
        self._plant_counts = self._counts(self.msg)
        self._refused = dict(self.link.refused)

    @staticmethod
    def _counts(msg) -> tuple[int, int, int]:
        return (0, 0, 0) if msg is None else (int(msg.missed_ticks), int(msg.watchdog_trips),
                                              int(msg.other_session))

    def foreign_note(self) -> str:
        """'' or one line on the foreign traffic the whole run saw."""
        refused = {r: self.link.refused[r] - self._run_refused.get(r, 0) for r in REFUSALS}
        other = (0 if self.msg is None or self._first_other is None
                 else int(self.msg.other_session) - self._first_other)
        parts = [f"{n} {r}" for r, n in refused.items() if n]
        text = []
        if parts:
            text.append(f"the link refused states ({', '.join(parts)})")
        if other > 0:
            text.append(f"the plant refused {other} commands of other sessions")
        rejected = (0 if self.msg is None or self._first_rejected is None
                    else int(self.msg.rejected_commands) - self._first_rejected)
        if rejected > 0:  # this run sends neither a conflicting repeat nor invalid valves
            text.append(f"the plant rejected {rejected} commands of this run's session (a "
                        "repeat of an applied seq with other valves, or invalid: another "
                        "sender in the session)")
        if self.foreign_total:
            text.append(f"the plant took {self.foreign_total} steps on commands this run never "
                        "sent: results may differ from an undisturbed run")
        return ("foreign traffic on the run's channels: " + "; ".join(text)) if text else ""

    def deadline_row(self) -> dict[str, Any]:
        """The deadline and foreign-traffic columns of the interval so far."""
        missed, trips, other = np.subtract(self._counts(self.msg), self._plant_counts)
        refused = {f"refused_{r.replace(' ', '_')}": self.link.refused[r] - self._refused.get(r, 0)
                   for r in REFUSALS}
        lat = np.array(self.latencies_ns, dtype=np.float64) / 1e6
        p50, p99, worst = (np.percentile(lat, [50, 99]).tolist() + [float(lat.max())]
                           if len(lat) else (None, None, None))
        return {"deadline_misses": self.misses, "latency_p50_ms": p50, "latency_p99_ms": p99,
                "latency_max_ms": worst, "watchdog_trips": int(trips),
                "plant_missed_ticks": int(missed), "lost_states": self.lost, **refused,
                "plant_other_session": int(other), "foreign_commands": self.foreign}

    # -- decisions ----------------------------------------------------------------
    def _act(self, ctx: StepContext) -> None:
        u = np.asarray(self.agent.act(self.obs, ctx), dtype=np.int8)
        seq = self.link.send(u, self.msg.seq)
        sent = time.monotonic_ns()
        self.latencies_ns.append(sent - self.link.arrival_ns.get(self.msg.seq, sent))
        self.commands[seq] = u.copy()
        self.sent_max = max(self.sent_max, seq)
        if len(self.commands) > KEPT_COMMANDS:
            del self.commands[min(self.commands)]
        self.awaited = seq

    def _open(self, command: int, ctx: StepContext, operating_step: int = 0,
              new_interval: bool = False) -> None:
        """Open an episode (START / RESET / EVALUATE) and act on it at once;
        ``new_interval``: the deadline counts start from its state."""
        self.msg = self.link.control(command, operating_step)
        self.sent_max = max(self.sent_max, int(self.msg.command_seq))
        if self._first_other is None:
            self._first_other = int(self.msg.other_session)
            self._first_rejected = int(self.msg.rejected_commands)
        if new_interval:
            self._restart_counts()
        self.obs = finite_observation(observation(self.msg), self.where)
        self.awaited = None
        self.agent.start_episode(self.obs)
        self._act(ctx)

    def open_next(self, interval: int, steps: int) -> None:
        """Open interval ``interval``'s first episode and take its first decision
        now (the caller's bookkeeping follows while the plant steps on it)."""
        self.where = f"interval {interval}, step 0"
        self._open(self.link.RESET, StepContext(interval, 0, steps), new_interval=True)
        self.opened = True

    def _stepped(self, s) -> tuple[Any, np.ndarray]:
        """Account for one plant step: its observation and the valves applied."""
        if self.awaited is None or s.command_seq != self.awaited:
            self.misses += 1
        if s.command_seq > self.sent_max:  # a command of this session this run never sent
            self.foreign += 1
            self.foreign_total += 1
        u = self.commands.get(int(s.command_seq))
        if u is None or s.watchdog_tripped:
            u = np.array(s.valve, dtype=np.int8)  # the safe state, or held from before
        return finite_observation(observation(s), self.where), u

    # -- the interval ---------------------------------------------------------------
    def online(self, interval: int, steps: int, keep: bool) -> tuple[dict[str, Any], list]:
        """Operating steps of one interval; returns its metrics and observations
        (for Transitions, when ``keep``). The plant's own operating-step count
        says where the interval is: a state lost on the way (a gap in the state
        counter) costs its transition, not the run."""
        n, agent, first = steps, self.agent, interval * steps
        self.where = f"interval {interval}, step 0"
        if not self.opened:  # the run's first interval: start the plant at its age
            self._open(self.link.START, StepContext(interval, 0, n), operating_step=first,
                       new_interval=True)
        self.opened = False
        observations, rewards, episodes = [self.obs], [], 1
        ended = None  # a terminal step's (obs, valves, reward, next obs) until the next episode
        t = 0
        while t < n:
            for s in self.link.next_states():
                gap = s.seq != self.msg.seq + 1
                if s.step == 0:  # the plant opened the next episode after a terminal step
                    o = finite_observation(observation(s), self.where)
                    observations.append(o)
                    episodes += 1
                    if ended is not None and not gap:
                        agent.observe(Transition(*ended, o))
                    agent.start_episode(o)
                    ended = None
                    self.msg, self.obs, self.awaited = s, o, None
                    continue
                t = int(s.operating_steps) - first
                self.where = f"interval {interval}, step {t}"
                if s.evaluation or not 0 < t <= n:
                    raise RunError(f"plant at operating step {s.operating_steps}"
                                   f"{' in an evaluation episode' if s.evaluation else ''} "
                                   f"while the run is at {self.where} (another controller?)")
                o, u = self._stepped(s)
                r = float(reward(o.level, u))
                rewards.append(r)
                observations.append(o)
                self.telemetry.step(o.level, u)
                _check_boundary(o, t == n, self.where)
                if gap:
                    self.lost += int(s.seq - self.msg.seq - 1)
                elif o.terminal and t < n:
                    ended = (self.obs, u, r, o)
                else:
                    agent.observe(Transition(self.obs, u, r, o, o))
                self.msg, self.obs, self.awaited = s, o, None
                if t == n:
                    break
            if t < n and not self.obs.terminal:
                self._act(StepContext(interval, t, n - t))
        metrics = {"reward_per_step": float(np.mean(rewards)), "episodes": episodes,
                   **agent.end_online()}
        return metrics, (observations if keep else [])

    def evaluate(self, interval: int, limit: int) -> tuple[float, int]:
        """The evaluation episode, cut off after ``limit`` steps."""
        self.where = f"interval {interval}, evaluation step 0"
        self._open(self.link.EVALUATE, StepContext(interval, 0, None, evaluation=True))
        total, steps = 0.0, 0
        while True:
            for s in self.link.next_states():
                if s.step == 0:  # the plant's next evaluation episode: not ours
                    continue
                self.where = f"interval {interval}, evaluation step {steps + 1}"
                o, u = self._stepped(s)
                total += float(reward(o.level, u))
                steps += 1
                self.msg, self.obs, self.awaited = s, o, None
                if o.done or steps >= limit:
                    return total / steps, steps
            self._act(StepContext(interval, steps, None, evaluation=True))


def _check_boundary(o, last: bool, where: str) -> None:
    if last and not o.done:
        raise RunError(f"plant did not end the interval at {where} (is its steps_per_interval "
                       "the same as ours?)")
    if o.truncated and not last:
        raise RunError(f"plant truncated the episode at {where}, before the interval's end "
                       "(is its steps_per_interval the same as ours?)")
