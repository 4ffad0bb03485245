"""Rollouts of valve sequences on a scenario's true physics, step by step: what
the episode planner (:mod:`ftc.control.planning.physics.episode_planner`) plans with. Each step
of a rollout runs under the parameters and stuck valves the scenario gives that
operating step (its events and continuous degradation included)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ftc.common.constants import NUM_TANKS


class TruePhysics:
    """Rollouts of valve sequences on a scenario's true physics, step by step.

    ``run(x0, sequences, step0, frozen)`` simulates candidate sequences (K, L, 6)
    from levels x0 (6,) m, step t under the parameters and stuck valves of
    operating step ``step0 + t`` (all of them ``step0``'s when ``frozen``: an
    evaluation episode). A candidate the integrator refuses (chattering, a
    SUNDIALS failure) earns -inf at every step and is counted in ``refused``."""

    def __init__(self, scenario: Any, rtol: float, atol: float, closed_form: bool) -> None:
        from ftc import _core  # native: the C++ physics

        self._core, self.scenario = _core, scenario
        self.rollout = _core.BatchRollout(rtol=rtol, atol=atol, exact_active_conduit=closed_form)
        self._events = np.array([e["at_step"] for e in scenario.events], np.int64)  # sorted
        self._params: dict[tuple[float, int], dict] = {}
        self._stuck: dict[int, tuple[np.ndarray, np.ndarray] | None] = {}
        self._schedules: dict[tuple[int, int], tuple[Any, Any]] = {}
        self.refused = 0
        self.simulated = 0  # candidate steps rolled out, for the planner's budget

    def events_within(self, step0: int, steps: int) -> bool:
        """Whether an event of the scenario takes effect after step0 and within the
        ``steps`` steps from it (an abrupt fault the interval's later episodes meet)."""
        return bool(((self._events > step0) & (self._events < step0 + steps)).any())

    def _key(self, step: int) -> tuple[float, int]:
        applied = int(np.searchsorted(self._events, step, side="right"))
        key = (float(self._core.age_at(self.scenario, step)), applied)
        if key not in self._params:
            self._params[key] = self._core.params_at_step(self.scenario, step)
        if applied not in self._stuck:
            mask, state = self._core.stuck_valves_at_step(self.scenario, step)
            self._stuck[applied] = (mask, state.astype(np.int64)) if mask.any() else None
        return key

    def schedule(self, step0: int, length: int) -> tuple[Any, Any, tuple]:
        """(params: one dict or a list of ``length``, stuck: None or (mask, state) of
        shape (length, 6), signature: a hashable summary of both) for the steps
        step0 .. step0 + length - 1."""
        cached = self._schedules.get((step0, length))
        if cached is not None:
            return cached
        if len(self._schedules) > 4096:  # a bounded memo: planning moves through the steps
            self._schedules.clear()
        keys = [self._key(step0 + t) for t in range(length)]
        params: Any = (self._params[keys[0]] if all(k == keys[0] for k in keys)
                       else [self._params[k] for k in keys])
        stuck = [self._stuck[k[1]] for k in keys]
        if all(s is None for s in stuck):
            stuck_arrays = None
        else:
            mask = np.stack([np.zeros(NUM_TANKS, bool) if s is None else s[0] for s in stuck])
            state = np.stack([np.zeros(NUM_TANKS, np.int64) if s is None else s[1]
                              for s in stuck])
            stuck_arrays = (mask, state)
        runs: list[list] = []  # the keys in force, run-length encoded
        for k in keys:
            if runs and runs[-1][0] == k:
                runs[-1][1] += 1
            else:
                runs.append([k, 1])
        # a constant schedule's signature is its one key, whatever its length
        out = (params, stuck_arrays, (runs[0][0],) if len(runs) == 1 else
               tuple((k, n) for k, n in runs))
        self._schedules[(step0, length)] = out
        return out

    def run(self, x0: np.ndarray, sequences: np.ndarray, step0: int, frozen: bool
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rewards (K, L), terminal (K, L) bool, levels after each step (K, L, 6))."""
        k, length, _ = sequences.shape
        params, stuck, _ = self.schedule(step0, 1 if frozen else length)
        if frozen and stuck is not None:
            stuck = (np.repeat(stuck[0], length, 0), np.repeat(stuck[1], length, 0))
        applied = sequences if stuck is None else np.where(stuck[0], stuck[1], sequences)
        x0 = np.asarray(x0, np.float64)
        self.simulated += k * length
        try:
            d = self.rollout.run(x0, applied, params, details=True)
            rewards, terminal, levels = d["rewards"], d["terminal"].astype(bool), d["levels"]
        except RuntimeError:  # one candidate at a time: a refused one earns -inf
            rewards = np.full((k, length), -np.inf)
            terminal = np.zeros((k, length), bool)
            levels = np.full((k, length, NUM_TANKS), np.nan)
            for i in range(k):
                try:
                    d = self.rollout.run(x0, applied[i:i + 1], params, details=True)
                except RuntimeError:
                    self.refused += 1
                    continue
                rewards[i], terminal[i], levels[i] = d["rewards"][0], d["terminal"][0], \
                    d["levels"][0]
        if stuck is not None:  # r = shape(x') - mean(u): charge the commanded valves
            rewards = rewards + applied.mean(-1) - sequences.mean(-1)
        return rewards, terminal, levels
