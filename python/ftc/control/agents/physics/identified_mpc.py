"""The project's recommended controller (method ``identified-mpc``): model-predictive
control on the plant's own physics with its parameters identified online
from what the plant publishes.

    python -m ftc.mpc --method identified-mpc --scenario scenarios/single.toml --out runs/identified

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

from dataclasses import dataclass, field
from typing import Any

import numpy as np


from ftc.common.cli import at_least, between
from ftc.common.errors import CheckpointError
from ftc.control.run.agent import StepContext, Transition
from ftc.control.agents.physics.mpc import MPCAgent, PhysicsConfig
from ftc.control.planning.physics.evaluators import ParamsEvaluator
from ftc.control.planning.planners import Evaluator
from ftc.learning.identify import Identifier, OnlineIdentification
from ftc.learning.stuck import StuckValves
from ftc.learning.transitions import Transitions
from ftc.plant.link import PlantObservation


@dataclass
class IdentifiedConfig(PhysicsConfig):
    """An identified-mpc run: the physics MPC's options and the identification's."""

    method: str = field(default="identified-mpc", metadata={"help": "the method"})
    identify_every: int = field(default=64, metadata={"check": at_least(0, 1_000_000), "help": (
        "re-identify the parameters every N steps of an interval from its data "
        "so far (0: only at interval ends)")})
    identify_trigger: float = field(default=1e-4, metadata={"check": between(0.0, 1.0), "help": (
        "a one-step prediction error above this (m) means the plant changed: the "
        "parameters are re-identified from the data since then at once, not at the next "
        "scheduled refit (0: off, relearn on the schedule only)")})


class IdentifiedAgent(MPCAgent):
    """MPC on identified physics; see the module docstring."""

    Config = IdentifiedConfig

    # (refused_rollouts: one of MPCAgent's columns)
    extra_columns = (*MPCAgent.extra_columns, "identify_seconds", "identified_pump_min",
                     "identified_demand_max", "detected_changes", "mispredicted_steps",
                     "stuck_valves", "stuck_detected")

    def __init__(self, cfg: IdentifiedConfig) -> None:
        super().__init__(cfg)
        from ftc import _core  # native: the plant's integrator for the rollouts

        self.online_id = OnlineIdentification(
            Identifier(cfg.rollout_rtol, cfg.rollout_atol, seed=cfg.seed),
            trigger=cfg.identify_trigger, every=cfg.identify_every)
        self.evaluator_ = ParamsEvaluator(_core.BatchRollout(
            rtol=cfg.rollout_rtol, atol=cfg.rollout_atol,
            exact_active_conduit=cfg.rollout_closed_form))
        self.stuck = StuckValves()
        self.evaluator_.stuck = self.stuck.stuck  # planned as they will be

    def prepare(self) -> dict[str, Any]:
        return {}

    def evaluator(self, o: PlantObservation) -> Evaluator:
        self.evaluator_.params = self.online_id.params.as_core()
        return self.evaluator_

    def begin_interval(self, interval: int) -> None:
        super().begin_interval(interval)
        self.online_id.begin()

    def observe(self, t: Transition) -> None:
        applied = t.next_obs.valves  # the plant publishes the valves it applied
        self.stuck.observe(t.valves, applied, t.obs.operating_steps)
        self.online_id.add(t.obs.level, applied, t.next_obs.level, t.next_obs.deficit)

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        return self.stuck.command(super().act(obs, ctx))

    def wants_data(self) -> bool:
        return False

    def end_interval(self, interval: int, data: Transitions | None) -> dict[str, Any]:
        ident = self.online_id
        if not ident.rows:
            return self.stuck.metrics()
        params, rms = ident.end()
        refused, self.evaluator_.refused = self.evaluator_.refused, 0
        return {"model_one_step_rmse": rms, "identify_seconds": ident.seconds,
                "refused_rollouts": refused, "detected_changes": ident.changes,
                "mispredicted_steps": ident.mispredicted,
                "identified_pump_min": float(params.pump.min()),
                "identified_demand_max": float(params.demand.max()), **self.stuck.metrics()}

    def config_doc(self) -> dict[str, Any]:
        return {}

    def state_dict(self) -> dict[str, Any]:
        return {"np_rng": self.rng.bit_generator.state,
                "identification": self.online_id.state_dict(), "stuck": self.stuck.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        missing = sorted({"np_rng", "identification"} - set(state))
        if missing:
            raise CheckpointError(f"checkpoint lacks the agent's {', '.join(missing)}")
        self.rng.bit_generator.state = state["np_rng"]
        self.online_id.load_state_dict(state["identification"])
        self.stuck.load_state_dict(state.get("stuck", {}))  # none in older checkpoints
