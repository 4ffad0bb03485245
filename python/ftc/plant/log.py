"""Recorded plant runs: read an LCM log (lcm-logger's format) of one plant's
traffic back into a :class:`Trajectory`.

Only ``<prefix>STATE`` messages are used: they carry the levels, the valves
applied and the episode bookkeeping, so the trajectory, the episodes and the
rewards (recomputed with :mod:`ftc.plant.reward` from the published levels, as
the controller computed them) follow from the log alone. A plant re-sends its
last state when a command is retried or a HELLO arrives; such repeats are
counted and dropped, keyed by (episode, step). A truncated or corrupt log is a
:class:`LogError` naming the file and the byte offset where reading stopped. A
well-framed event on the STATE channel that is not a plant state (another
process's traffic on the bus, hostile lengths included) is checked before
decoding (:mod:`ftc.plant.wire`), counted and skipped: ``undecodable`` and
``first_undecodable`` say which. A signed state (a plant with a bus key) is
read without its trailer (:mod:`ftc.plant.signing`; not verified: no key).
"""

from __future__ import annotations

import os
import struct
import sys
import tempfile
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ftc.common.atomic import atomic_write_csv
from ftc.common.constants import NUM_ENGINES, NUM_TANKS
from ftc.plant import trajectory as schema
from ftc.plant.reward import reward
from ftc.plant.signing import TRAILER_BYTES
from ftc.plant.wire import decode_state

STATE_SUFFIX = "STATE"
class LogError(RuntimeError):
    """The log cannot be read as a plant log (truncated, corrupt, or no plant states)."""


@dataclass
class Trajectory:
    """One row per plant step (states with step > 0), in the order the plant took them.

    episode, step: (n,) int; age: (n,) float, intervals; operating_steps: (n,) int
    level, true_level: (n, 6) m, after the step (level as published, noise included)
    valves: (n, 6) int8, applied during the step; deficit: (n, 2) m^3
    terminal, truncated, evaluation: (n,) bool
    utime: (n,) int, plant publication time, microseconds since the epoch
    reward: (n,) recomputed with ftc.plant.reward from (level, valves)
    initial_level: episode -> (6,) published level of its initial state (step 0)
    """

    episode: np.ndarray
    step: np.ndarray
    age: np.ndarray
    operating_steps: np.ndarray
    level: np.ndarray
    true_level: np.ndarray
    valves: np.ndarray
    deficit: np.ndarray
    terminal: np.ndarray
    truncated: np.ndarray
    evaluation: np.ndarray
    utime: np.ndarray
    reward: np.ndarray
    initial_level: dict[int, np.ndarray] = field(default_factory=dict)
    channel: str = ""
    events: int = 0
    repeats: int = 0
    missing: int = 0
    undecodable: int = 0
    first_undecodable: str = ""

    def __len__(self) -> int:
        return len(self.step)

    def episodes(self, evaluation: bool | None = None) -> list[int]:
        """Episode numbers present, optionally only (non-)evaluation ones."""
        keep = np.ones(len(self), bool) if evaluation is None else self.evaluation == evaluation
        return sorted(set(self.episode[keep].tolist()))

    def select(self, mask: np.ndarray) -> "Trajectory":
        """The rows where mask (n,) is true."""
        arrays = {k: getattr(self, k)[mask] for k in _ARRAY_FIELDS}
        return Trajectory(**arrays, initial_level=self.initial_level, channel=self.channel,
                          events=self.events, repeats=self.repeats, missing=self.missing,
                          undecodable=self.undecodable, first_undecodable=self.first_undecodable)

    def episode_rows(self, episode: int) -> "Trajectory":
        rows = self.select(self.episode == episode)
        if len(rows) == 0:
            raise LogError(f"episode {episode} has no steps in the log "
                           f"(episodes present: {_ranges(self.episodes())})")
        return rows

    def interval(self) -> np.ndarray:
        """(n,) degradation interval of each step: the integer part of its age."""
        return np.floor(self.age + 1e-9).astype(int)

    def reward_per_interval(self, evaluation: bool = False) -> dict[int, float]:
        """Mean reward per step of each interval, over its operating (or evaluation) steps.

        Evaluation episodes are frozen at the age of the last operating step, so
        they fall into the interval they evaluate.
        """
        keep = self.evaluation == evaluation
        out: dict[int, float] = {}
        for k in sorted(set(self.interval()[keep].tolist())):
            out[k] = float(np.mean(self.reward[keep & (self.interval() == k)]))
        return out


_ARRAY_FIELDS = ("episode", "step", "age", "operating_steps", "level", "true_level", "valves",
                 "deficit", "terminal", "truncated", "evaluation", "utime", "reward")


def _ranges(values: list[int]) -> str:
    if not values:
        return "none"
    return f"{values[0]}..{values[-1]} ({len(values)})" if len(values) > 3 else str(values)


# fd 2 is one per process: captures from several threads (the experiments read
# finished runs' logs in worker threads) must not interleave, or one restores
# the other's temporary file as fd 2 for good
_FD2_LOCK = threading.Lock()


class _CStderr:
    """Captures what C code prints on file descriptor 2 (liblcm reports a bad
    event header there), so an error stays one line; ``text`` is it joined.
    One capture at a time per process (other threads' fd-2 output during one
    lands in it too: keep the captured block short)."""

    def __init__(self) -> None:
        self.text = ""
        self._saved: int | None = None

    def __enter__(self) -> "_CStderr":
        _FD2_LOCK.acquire()
        try:
            sys.stderr.flush()
            self._file = tempfile.TemporaryFile()
            self._saved = os.dup(2)
            os.dup2(self._file.fileno(), 2)
        except BaseException:
            _FD2_LOCK.release()
            raise
        return self

    def __exit__(self, *exc) -> None:
        if self._saved is None:
            return
        try:
            sys.stderr.flush()
            os.dup2(self._saved, 2)
            os.close(self._saved)
        finally:
            self._saved = None
            _FD2_LOCK.release()
        self._file.seek(0)
        self.text = "; ".join(line.strip() for line in
                              self._file.read().decode(errors="replace").splitlines()
                              if line.strip())
        self._file.close()


def read_log(path: str | os.PathLike, channel: str | None = None) -> Trajectory:
    """Rebuild the trajectory from the plant states in an LCM log.

    channel: the STATE channel to read; default: the one channel ending in
    'STATE' (an error if the log holds several, e.g. two plants' traffic).
    Raises LogError on a truncated or corrupt log, with the file and byte offset.
    """
    import lcm  # native: liblcm's Python binding


    path = Path(path)
    if not path.is_file():
        raise LogError(f"{path}: no such file")
    size = path.stat().st_size
    try:
        log = lcm.EventLog(str(path), "r")
    except (OSError, ValueError) as e:
        raise LogError(f"{path}: cannot open as an LCM log: {e}") from None
    states: dict[str, list] = {}
    bad: dict[str, list[str]] = {}  # channel -> where and why each undecodable event
    events = 0
    offset = 0
    lcm_said = _CStderr()  # liblcm prints its own complaints; they go into our one line
    try:
        lcm_said.__enter__()
        while True:
            offset = log.tell()
            try:
                event = log.read_next_event()
            except (OSError, ValueError) as e:
                raise LogError(f"{path}: corrupt event at byte offset {offset}: {e}") from None
            if event is None:
                break
            if event.eventnum != events:
                raise LogError(f"{path}: corrupt log at byte offset {offset}: event number "
                               f"{event.eventnum} where {events} was expected")
            events += 1
            if event.channel.endswith(STATE_SUFFIX) and (channel is None or event.channel == channel):
                msg, why = decode_state(event.data)
                if msg is None and len(event.data) > TRAILER_BYTES:
                    # a keyed plant's state carries a signature trailer: the log
                    # is a record (the MAC was checked live, if at all)
                    msg, _ = decode_state(event.data[:-TRAILER_BYTES])
                if msg is None:
                    bad.setdefault(event.channel, []).append(
                        f"event {event.eventnum} at byte offset {offset}: {why}")
                    continue
                states.setdefault(event.channel, []).append(msg)
    finally:
        log.close()
        lcm_said.__exit__()
    if offset != size:
        raise LogError(f"{path}: truncated or corrupt log: reading stopped at byte offset "
                       f"{offset} of {size} (after {events} events)"
                       + (f" (lcm: {lcm_said.text})" if lcm_said.text else ""))
    if not states:
        skipped = sum(len(v) for v in bad.values())
        raise LogError(f"{path}: no plant_state_t messages"
                       + (f" ({skipped} undecodable, the first {next(iter(bad.values()))[0]})"
                          if skipped else "")
                       + (f" on channel {channel}" if channel else " on any *STATE channel")
                       + f" among {events} events")
    if len(states) > 1:
        raise LogError(f"{path}: several STATE channels ({', '.join(sorted(states))}); "
                       "choose one with --channel")
    (name, msgs), = states.items()
    traj = _trajectory(msgs, name, events)
    traj.undecodable = len(bad.get(name, []))
    traj.first_undecodable = bad[name][0] if traj.undecodable else ""
    return traj


def _trajectory(msgs: list, channel: str, events: int) -> Trajectory:
    seen: set[tuple[int, int]] = set()
    rows = []
    initial: dict[int, np.ndarray] = {}
    repeats = 0
    # The plant numbers every state it publishes 1, 2, ...; a gap is a message
    # the recorder did not receive (or a log that starts late).
    seqs = np.array(sorted({int(m.seq) for m in msgs}), dtype=np.int64)
    missing = int(seqs[-1] - seqs[0] + 1 - len(seqs)) + int(seqs[0] - 1) if len(seqs) else 0
    for m in msgs:
        key = (m.episode, m.step)
        if key in seen:
            repeats += 1
            continue
        seen.add(key)
        if m.step == 0:
            initial[int(m.episode)] = np.array(m.level, dtype=np.float64)
        else:
            rows.append(m)
    n = len(rows)
    level = np.array([m.level for m in rows], dtype=np.float64).reshape(n, NUM_TANKS)
    valves = np.array([m.valve for m in rows], dtype=np.int8).reshape(n, NUM_TANKS)
    return Trajectory(
        episode=np.array([m.episode for m in rows], dtype=np.int64),
        step=np.array([m.step for m in rows], dtype=np.int64),
        age=np.array([m.age for m in rows], dtype=np.float64),
        operating_steps=np.array([m.operating_steps for m in rows], dtype=np.int64),
        level=level,
        true_level=np.array([m.true_level for m in rows], dtype=np.float64).reshape(n, NUM_TANKS),
        valves=valves,
        deficit=np.array([m.deficit for m in rows], dtype=np.float64).reshape(n, NUM_ENGINES),
        terminal=np.array([m.terminal for m in rows], dtype=bool),
        truncated=np.array([m.truncated for m in rows], dtype=bool),
        evaluation=np.array([m.evaluation for m in rows], dtype=bool),
        utime=np.array([m.utime for m in rows], dtype=np.int64),
        reward=np.array([float(reward(level[i], valves[i])) for i in range(n)], dtype=np.float64),
        initial_level=initial, channel=channel, events=events, repeats=repeats, missing=missing)


def control_episode(traj: Trajectory) -> int:
    """The episode that best shows control at the highest degradation in the log.

    The last complete (terminal) evaluation episode, as it shows the
    deterministic policy; failing that the last terminal operating episode at
    the highest age; failing that the longest episode at the highest age.
    """
    top = traj.interval().max()
    at_top = traj.interval() == top
    for evaluation in (True, False):
        done = traj.terminal & at_top & (traj.evaluation == evaluation)
        if done.any():
            return int(traj.episode[done][-1])
    eps, counts = np.unique(traj.episode[at_top], return_counts=True)
    return int(eps[np.argmax(counts)])


def write_trajectory_csv(rows: Trajectory, out: Path) -> None:
    """Write rows as CSV (:mod:`ftc.plant.trajectory`, with flags and reward),
    atomically. A single episode starts with its initial state (step 0, valves
    closed, no reward) when the log has it."""
    lines = []
    episodes = set(rows.episode.tolist())
    if len(episodes) == 1 and (ep := episodes.pop()) in rows.initial_level and rows.step[0] == 1:
        lines.append(schema.row(ep, 0, rows.age[0], [0] * NUM_TANKS, rows.initial_level[ep],
                                flags=(rows.evaluation[0], 0, 0), reward=""))
    lines += [schema.row(rows.episode[i], rows.step[i], rows.age[i], rows.valves[i],
                         rows.level[i], reward=rows.reward[i],
                         flags=(rows.evaluation[i], rows.terminal[i], rows.truncated[i]))
              for i in range(len(rows))]
    atomic_write_csv(out, schema.header(flags=True, reward=True), lines)
