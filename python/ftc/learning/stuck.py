"""Valves stuck open or closed: detected once, shared by every controller that
plans or is guided (``identified-mpc``, ``ppo-robust``'s teacher and its
distillation, ``learned-mpc``, ``ppo-learned``).

A valve is stuck when the plant's answer shows it in another state than the
one commanded: the plant publishes the valves it applied (the flows it let
through), and a valve applied otherwise than commanded is stuck in the
applied state. A valve stuck in the state it is commanded to cannot be told
from a healthy one until it is commanded otherwise; since stuck valves are
commanded closed (below), one stuck open is found at the first step its
controller wants it closed.

A stuck valve stays stuck (no scenario frees one). It is planned as it will
be, and commanded closed: the reward charges the commanded valves (the
activity term), so opening a valve stuck open pays for nothing, and a valve
stuck closed does nothing when opened. Pure numpy, no plant equations: the
learned controllers use it too (the import contract in pyproject.toml).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ftc.common.constants import NUM_VALVES

STATES = ("closed", "open")


def against_command(commanded: np.ndarray, applied: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rule: valves (..., 6) the plant ``applied`` otherwise than
    ``commanded``, as (stuck closed, stuck open) bool arrays: commanded open
    and applied closed, commanded closed and applied open."""
    commanded = np.asarray(commanded) != 0
    applied = np.asarray(applied) != 0
    return commanded & ~applied, ~commanded & applied


class StuckMemory:
    """N plants' valves seen stuck, kept as a learned policy reads them.

    ``stuck`` (N, 12) float32 of 0/1: per valve whether it was last seen stuck
    closed, for valves 1-6, then whether last seen stuck open. ``see`` feeds
    it a step's commanded and applied valves; ``forget`` clears the rows of
    plants that are new; ``features`` is the memory as inputs, 2 x - 1."""

    def __init__(self, num_envs: int) -> None:
        self.stuck = np.zeros((num_envs, 2 * NUM_VALVES), np.float32)

    def see(self, commanded: np.ndarray, applied: np.ndarray) -> None:
        """A step where the plants ``applied`` (N, 6) on ``commanded`` (N, 6)."""
        closed, opened = against_command(commanded, applied)
        seen = closed | opened
        self.stuck[:, :NUM_VALVES][seen] = closed[seen]
        self.stuck[:, NUM_VALVES:][seen] = opened[seen]

    def forget(self, which: np.ndarray | None = None) -> None:
        """Clear the memory of plants ``which`` (bool (N,), default all)."""
        self.stuck[slice(None) if which is None else np.asarray(which, bool)] = 0.0

    def features(self) -> np.ndarray:
        return 2.0 * self.stuck - 1.0


class StuckValves:
    """The valves seen stuck, and when each was detected.

    ``stuck``: valve index (0-based) -> the state it stays in (0 closed,
    1 open); ``detections``: (valve, state, operating step) in the order found.
    """

    def __init__(self) -> None:
        self.stuck: dict[int, int] = {}
        self.detections: list[tuple[int, int, int]] = []
        self._reported = 0  # detections already returned by take_new()

    def observe(self, commanded: np.ndarray, applied: np.ndarray, step: int) -> bool:
        """One plant step: ``commanded`` and ``applied`` valves (6,) and the
        operating step it was taken at. Returns True when a valve not known
        stuck before (or known stuck in the other state) was found stuck."""
        closed, opened = against_command(commanded, applied)
        found = False
        for i in np.flatnonzero(closed | opened):
            found |= self._add(int(i), int(opened[i]), step)
        return found

    def _add(self, valve: int, state: int, step: int) -> bool:
        if self.stuck.get(valve) == state:
            return False
        self.stuck[valve] = state
        self.detections.append((valve, state, int(step)))
        return True

    def applied(self, valves: np.ndarray) -> np.ndarray:
        """What the plant will apply for commands ``valves`` (..., 6): the stuck
        ones replaced by their state (a copy)."""
        out = np.array(valves, copy=True)
        for i, state in self.stuck.items():
            out[..., i] = state
        return out

    def command(self, valves: np.ndarray) -> np.ndarray:
        """The command to send for a plan ``valves`` (6,): the stuck ones closed
        (they do what they do whatever is commanded; closed costs nothing)."""
        out = np.array(valves, copy=True)
        for i in self.stuck:
            out[i] = 0
        return out

    def take_new(self) -> list[tuple[int, int, int]]:
        """The detections since the last call."""
        new, self._reported = self.detections[self._reported:], len(self.detections)
        return new

    def metrics(self) -> dict[str, Any]:
        """metrics.csv's columns: how many valves are known stuck and the
        detections of the interval (since the last call), as 'valve N
        open|closed at step S' (valves 1-based, as scenario files number them)."""
        new = self.take_new()
        return {"stuck_valves": len(self.stuck),
                "stuck_detected": "; ".join(f"valve {v + 1} {STATES[s]} at step {at}"
                                            for v, s, at in new)}

    def state_dict(self) -> dict[str, Any]:
        return {"stuck": {str(k): v for k, v in self.stuck.items()},
                "detections": [list(d) for d in self.detections], "reported": self._reported}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.stuck.clear()  # in place: evaluators hold this dict
        self.stuck.update({int(k): int(v) for k, v in state.get("stuck", {}).items()})
        self.detections = [tuple(int(x) for x in d) for d in state.get("detections", [])]
        self._reported = int(state.get("reported", len(self.detections)))


def charge_commanded(totals: np.ndarray, commanded: np.ndarray, applied: np.ndarray
                     ) -> np.ndarray:
    """Summed rewards (K,) of rollouts that charged the ``applied`` valves
    (K, L, 6), corrected to charge the ``commanded`` ones instead, as the
    runner's reward does (r = shape(x') - mean(u), u commanded)."""
    return totals + (np.asarray(applied).mean(-1) - np.asarray(commanded).mean(-1)).sum(-1)
