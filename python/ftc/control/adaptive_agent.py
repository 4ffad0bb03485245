"""The project's recommended controller (method ``adaptive``): model-predictive
control on the plant's own physics with its parameters identified online
from what the plant publishes.

    python -m ftc.mpc --method adaptive --scenario scenarios/single.toml --out runs/adaptive

It plans exactly as the oracle MPC does (the same planner, the same C++ batch
rollouts), but with pump capacities, valve resistances and engine demands
*estimated* by :class:`ftc.learning.identify.Identifier` instead of read from
the scenario file: it is never told the faults. It does assume the plant's
structure (the tank model of plant-model.md), which the learned world model
does not; that is the price of its accuracy, said plainly.

Per interval k:

* at its start, the parameters are extrapolated from the estimates of
  intervals k-1 and k-2 (the degradation of the spec is linear in age), or
  kept from k-1 when there is only one;
* every ``identify_every`` steps they are re-identified from the interval's
  transitions so far (the plant degraded at the boundary, so only this
  interval's rows describe it), the extrapolation as the prior;
* at its end, a final fit on the whole interval is kept for the next
  extrapolation;
* after every step it compares the level it predicted with the one the plant
  published; an error above ``identify_trigger`` means the plant has changed
  (an abrupt fault, or the interval boundary's degradation): the rows before
  it no longer describe the plant, and the parameters are re-identified from
  the rows since, as soon as there are ``TRIGGER_ROWS`` of them, instead of
  waiting for the next scheduled refit (the paper's future work: relearning
  when the plant changes).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ftc.common.errors import CheckpointError
from ftc.control.agent import Transition
from ftc.control.mpc_agent import MPCAgent, MPCConfig
from ftc.control.planners import Evaluator, ParamsEvaluator
from ftc.learning.identify import Identifier, PlantParameters
from ftc.learning.transitions import Transitions
from ftc.plant.link import PlantObservation


TRIGGER_ROWS = 8  # rows since a detected change before re-identifying from them


class AdaptiveAgent(MPCAgent):
    """MPC on identified physics; see the module docstring."""

    extra_columns = (*MPCAgent.extra_columns, "identify_seconds", "identified_pump_min",
                     "identified_demand_max", "refused_rollouts", "detected_changes")

    def __init__(self, cfg: MPCConfig) -> None:
        super().__init__(cfg)
        self.name = "adaptive"
        from ftc import _core  # native: the plant's integrator for the rollouts

        self.identifier = Identifier(cfg.rollout_rtol, cfg.rollout_atol, seed=cfg.seed)
        self.evaluator_ = ParamsEvaluator(_core.BatchRollout(rtol=cfg.rollout_rtol,
                                                             atol=cfg.rollout_atol))
        self.history: list[PlantParameters] = []
        self.params = self.prior = PlantParameters.nominal()
        self.rows: list[tuple[np.ndarray, ...]] = []
        self.identify_seconds = 0.0
        self.change_at = 0          # first row that describes the plant as it is now
        self.pending_change = False  # a change was seen; re-identify once enough rows
        self.changes = 0

    def prepare(self) -> dict[str, Any]:
        return {}

    def evaluator(self, o: PlantObservation) -> Evaluator:
        self.evaluator_.params = self.params.as_core()
        return self.evaluator_

    def begin_interval(self, interval: int) -> None:
        super().begin_interval(interval)
        self.rows = []
        self.identify_seconds = 0.0
        self.change_at, self.pending_change, self.changes = 0, False, 0
        if len(self.history) >= 2:
            self.prior = self.history[-1].extrapolate(self.history[-2])
        elif self.history:
            self.prior = self.history[-1]
        self.params = self.prior

    def observe(self, t: Transition) -> None:
        self.rows.append((t.obs.level, t.valves, t.next_obs.level, t.next_obs.deficit))
        trigger = self.cfg.identify_trigger
        if trigger:
            predicted = self.identifier.predict(self.params, t.obs.level[None], t.valves[None])[0]
            wrong = not np.all(np.abs(predicted - t.next_obs.level) <= trigger)  # NaN: wrong
            if wrong and not self.pending_change:  # a change: the rows before it are stale
                self.change_at, self.pending_change = len(self.rows) - 1, True
                self.changes += 1
        every = self.cfg.identify_every
        if self.pending_change and len(self.rows) - self.change_at >= TRIGGER_ROWS:
            self.params, _ = self._identify()
            self.pending_change = False
        elif every and len(self.rows) % every == 0:
            self.params, _ = self._identify()

    def _identify(self) -> tuple[PlantParameters, float]:
        start = time.perf_counter()
        rows = self.rows[self.change_at:] if len(self.rows) - self.change_at >= TRIGGER_ROWS \
            else self.rows
        level, valves, next_level, deficit = (np.array(c) for c in zip(*rows))
        params, rms = self.identifier.fit(level, valves, next_level, deficit, self.prior)
        self.identify_seconds += time.perf_counter() - start
        return params, rms

    def wants_data(self) -> bool:
        return False

    def end_interval(self, interval: int, data: Transitions | None) -> dict[str, Any]:
        if not self.rows:
            return {}
        self.params, rms = self._identify()
        self.history.append(self.params)
        refused, self.evaluator_.refused = self.evaluator_.refused, 0
        return {"model_one_step_rmse": rms, "identify_seconds": self.identify_seconds,
                "refused_rollouts": refused, "detected_changes": self.changes,
                "identified_pump_min": float(self.params.pump.min()),
                "identified_demand_max": float(self.params.demand.max())}

    def config_doc(self) -> dict[str, Any]:
        return {}

    def state_dict(self) -> dict[str, Any]:
        return {"np_rng": self.rng.bit_generator.state,
                "history": [p.vector().tolist() for p in self.history],
                "identifier_rng": self.identifier.rng.bit_generator.state}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        missing = sorted({"np_rng", "history", "identifier_rng"} - set(state))
        if missing:
            raise CheckpointError(f"checkpoint lacks the agent's {', '.join(missing)}")
        self.rng.bit_generator.state = state["np_rng"]
        self.identifier.rng.bit_generator.state = state["identifier_rng"]
        self.history = [PlantParameters.from_vector(np.array(v)) for v in state["history"]]
        if self.history:
            self.params = self.prior = self.history[-1]
