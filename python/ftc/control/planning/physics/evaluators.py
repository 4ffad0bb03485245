"""Evaluators that simulate the candidates on the plant's own physics (the C++
core's batch rollouts): the true degraded physics of the scenario (the
oracle) or physics with given parameters (identified ones). The planners
(:mod:`ftc.control.planning.planners`) plan on any evaluator; the controllers that
learn the plant never import this module (the import contract in
pyproject.toml)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ftc.learning.stuck import charge_commanded


def guarded_rollout(rollout: Any, x0: np.ndarray, sequences: np.ndarray, params: Any
                    ) -> tuple[np.ndarray, int]:
    """Summed rewards (K,) of candidate valve sequences (K, L, 6) from levels x0
    (6,) m on ``rollout`` (a ``_core.BatchRollout``) under ``params``, and how
    many candidates the integrator refused.

    The integrator refuses a step it cannot integrate (RuntimeError: more mode
    switches than its limit, i.e. chattering, or a SUNDIALS failure). The batch
    is then rolled out again one candidate at a time: a refused candidate
    scores -inf (a plan whose rollout did not happen is never chosen) and the
    others are planned on, instead of the run ending."""
    try:
        return rollout.run(x0, sequences, params), 0
    except RuntimeError:
        totals, refused = np.full(len(sequences), -np.inf), 0
        for k in range(len(sequences)):
            try:
                totals[k] = rollout.run(x0, sequences[k:k + 1], params)[0]
            except RuntimeError:
                refused += 1
        return totals, refused


class OracleEvaluator:
    """The true physics in force at an operating step (C++ batch rollouts).

    ``set_step`` (the scenario's abrupt faults included) or ``set_age`` (the
    linear degradation only) chooses the parameters every candidate is rolled
    out with. Valves stuck at that step replace the candidates' entries before
    the rollout, as the plant replaces the command's; the activity term is then
    charged for the commanded valves, as the runner's reward is. Events later
    than the step are not anticipated within the horizon. A candidate whose
    rollout the integrator refuses scores -inf (:func:`guarded_rollout`);
    ``refused`` counts them.
    """

    def __init__(self, scenario: Any, rtol: float = 1e-6, atol: float = 1e-8,
                 closed_form: bool = False) -> None:
        """closed_form: steps with the conduit active in closed form
        (``_core.BatchRollout``'s exact_active_conduit)."""
        from ftc import _core  # native: the C++ physics

        self._core, self.scenario = _core, scenario
        self.rollout = _core.BatchRollout(rtol=rtol, atol=atol, exact_active_conduit=closed_form)
        self._params: dict[Any, dict] = {}
        self.params: dict | None = None
        self._event_steps = np.array([e["at_step"] for e in scenario.events], np.int64)  # sorted
        self._stuck: dict[int, tuple[np.ndarray, np.ndarray] | None] = {}
        self.stuck: tuple[np.ndarray, np.ndarray] | None = None  # (mask (6,) bool, state (6,))
        self.refused = 0  # candidates whose rollout the integrator refused

    def set_age(self, age: float) -> None:
        """Plan at an age (intervals) with the scenario's own factors, no events."""
        if age not in self._params:
            self._params[age] = self._core.degraded_params(self.scenario, float(age))
        self.params, self.stuck = self._params[age], None

    def set_step(self, operating_steps: int, evaluation: bool = False) -> None:
        """Plan for the plant's next step, given the observation's operating_steps:
        operating, the step after them; in an evaluation episode, the last
        operating step's parameters and stuck valves (frozen, as the plant does)."""
        step = max(0, int(operating_steps) - 1) if evaluation else int(operating_steps)
        applied = int(np.searchsorted(self._event_steps, step, side="right"))  # events in force
        key = (self.age_at(step), applied)
        if key not in self._params:
            self._params[key] = self._core.params_at_step(self.scenario, step)
        if applied not in self._stuck:
            mask, state = self._core.stuck_valves_at_step(self.scenario, step)
            self._stuck[applied] = (mask, state.astype(np.int64)) if mask.any() else None
        self.params, self.stuck = self._params[key], self._stuck[applied]

    def age_at(self, operating_steps: int) -> float:
        return float(self._core.age_at(self.scenario, int(operating_steps)))

    def __call__(self, x0: np.ndarray, sequences: np.ndarray) -> np.ndarray:
        x0 = np.asarray(x0, np.float64)
        if self.stuck is None:
            totals, refused = guarded_rollout(self.rollout, x0, sequences, self.params)
            self.refused += refused
            return totals
        mask, state = self.stuck
        applied = np.where(mask, state, sequences)
        totals, refused = guarded_rollout(self.rollout, x0, applied, self.params)
        self.refused += refused
        # r = shape(x') - mean(u): the rollout charged the applied valves.
        return charge_commanded(totals, sequences, applied)


class ParamsEvaluator:
    """Candidate sequences simulated with given physical parameters (C++ batch rollouts).

    Estimated parameters can make a candidate's rollout ill-posed where the true
    ones are not (the integrator refuses a step that would switch modes without
    end: chattering); such a candidate scores -inf and the others are planned
    on (:func:`guarded_rollout`). ``refused`` counts them. Valves known stuck
    (``stuck``, a :class:`ftc.learning.stuck.StuckValves`' dict) are rolled out as
    they will be, and the activity term charged for the commanded valves, as the
    runner's reward is (the oracle's rule)."""

    def __init__(self, rollout: Any) -> None:
        self.rollout = rollout
        self.params: dict | None = None
        self.refused = 0
        # valves seen not to follow their commands: index -> the state they stay in
        self.stuck: dict[int, int] = {}

    def __call__(self, x0: np.ndarray, sequences: np.ndarray) -> np.ndarray:
        x0 = np.asarray(x0, np.float64)
        applied = sequences
        if self.stuck:  # plan with the valves as they will be, not as commanded
            applied = np.array(sequences, copy=True)
            for i, state in self.stuck.items():
                applied[:, :, i] = state
        totals, refused = guarded_rollout(self.rollout, x0, applied, self.params)
        self.refused += refused
        return charge_commanded(totals, sequences, applied) if self.stuck else totals
