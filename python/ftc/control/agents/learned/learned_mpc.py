"""``learned-mpc``: model-predictive control on a model of the plant learned
from its observed steps alone, with no plant equations.

    python -m ftc.mpc --method learned-mpc --scenario scenarios/single.toml --out runs/learned

What it knows: the published levels, the valves the plant applied and the
engines' published deficit (what an aircraft's fuel system reports), and the
reward, which it computes itself. Not the tank model, not the parameters,
not the faults: the import contract in pyproject.toml keeps this module and
everything it imports away from the identification (:mod:`ftc.learning.identify`),
the C++ physics and the scenario's factors, and a test shows the contract
catches such an import.

* The model (:class:`ftc.learning.feature_model.FeatureModel`) is first fitted
  on nominal data (``learn_episodes`` episodes on the nominal plant, as the
  paper's world model), then updated after every step the plant takes, with
  older steps fading (``learn_forget``): it follows the degradation within
  the interval, not one interval late.
* The planner is the oracle's (``--planner``, ``--hold``, ``--horizon``),
  every candidate rolled out on the model; an episode ends in a rollout where
  the predicted fuel falls ``learn_terminal_band`` below the demand, which is
  estimated from what was burnt (level drop plus published deficit).
* Valves seen not to follow their command are planned as they will be, and
  commanded closed (:class:`ftc.learning.stuck.StuckValves`, shared with the
  controllers on the plant's equations).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ftc.common.cli import at_least, between, positive
from ftc.common.constants import EMPTY_VOLUME, NUM_TANKS, TANK_HEIGHT, TERMINAL_TOLERANCE
from ftc.common.errors import CheckpointError
from ftc.control.run.agent import Agent, StepContext, Transition
from ftc.control.agents.mpc_config import MPCConfig
from ftc.control.planning.planners import CEMPlanner, make_planner
from ftc.learning.feature_model import FeatureModel
from ftc.learning.stuck import StuckValves, charge_commanded
from ftc.learning.transitions import (Transitions, collect_nominal_dataset,
                                      collect_sparse_episodes)
from ftc.plant.link import CorePlant, PlantObservation
from ftc.plant.reward import AREAS, reward_moments

DEMAND_MEMORY = 0.8  # weight of the old estimate of the demand per step in each update


@dataclass
class LearnedMPCConfig(MPCConfig):
    """A learned-mpc run: the planner's options and the learned model's."""

    method: str = field(default="learned-mpc", metadata={"help": "the method"})
    learn_features: int = field(default=256, metadata={"check": at_least(1, 100_000), "help": (
        "random ReLU features of the learned model (beside a constant, the "
        "12 inputs and their 66 pairwise products)")})
    learn_forget: float = field(default=0.998, metadata={"check": between(0.5, 1.0), "help": (
        "weight a step keeps per later step in the model's fit (0.998: a "
        "half-life of 350 steps; 1: never forget)")})
    learn_ridge: float = field(default=0.01, metadata={"check": positive(1e6), "help": (
        "weight of the prior (the fit at the last interval's end) against the "
        "data, per feature direction")})
    learn_episodes: int = field(default=100, metadata={"check": at_least(1, 100_000), "help": (
        "nominal episodes the model is first fitted on: half the paper's "
        "random valves held up to 30 steps, half sparse openings (each valve open with a "
        "probability drawn from [0, 0.3], held up to 10 steps), where closed valves, the "
        "best policy's usual choice, are common")})
    learn_terminal_band: float = field(default=0.005, metadata={"check": between(0.0, 1.0), "help": (
        "a predicted step ends the episode only if it leaves this much less "
        "fuel (m^3) than the demand estimated from what was burnt; a model slightly wrong "
        "near the end otherwise plans on a reset that never comes (fuel stranded behind a "
        "dead pump: docs/controller.md)")})


class LearnedEvaluator:
    """Candidate valve sequences rolled out on the learned model, all in one batch
    per step; after a predicted terminal step the tanks are full again, as the
    plant resets them. Valves seen not to follow their command (``stuck``: valve
    -> the state it stays in) are planned as they will be, the activity charged
    for the commanded valves: a plan that opens a valve stuck closed would be
    rolled out on a transfer the model learned before the valve stuck."""

    def __init__(self, model: FeatureModel, demand: float, band: float,
                 stuck: dict[int, int] | None = None) -> None:
        self.model, self.end_volume = model, demand + TERMINAL_TOLERANCE - band
        self.stuck = stuck or {}

    def __call__(self, x0: np.ndarray, sequences: np.ndarray) -> np.ndarray:
        commanded = sequences
        if self.stuck:
            sequences = np.array(sequences, copy=True)
            for i, state in self.stuck.items():
                sequences[:, :, i] = state
        k, horizon, _ = sequences.shape
        x = np.broadcast_to(np.asarray(x0, np.float64), (k, NUM_TANKS))
        total = np.zeros(k)
        for t in range(horizon):
            nxt = self.model.predict(x, sequences[:, t])
            total += reward_moments(nxt, sequences[:, t])
            terminal = nxt @ AREAS < self.end_volume
            x = np.where(terminal[:, None], TANK_HEIGHT, nxt)
        return charge_commanded(total, commanded, sequences) if self.stuck else total


def fit_nominal(model: FeatureModel, episodes: int, seed: int) -> tuple[float, dict[str, Any]]:
    """Fit ``model`` on nominal data, as the paper's world model is pretrained:
    half the paper's random-valve episodes, half sparse openings
    (:func:`collect_sparse_episodes`), on the nominal plant. Returns the demand
    per step estimated from them and what was measured."""
    start = time.perf_counter()
    half = episodes // 2
    parts = [collect_nominal_dataset(half, seed=seed)] if half else []
    plant = CorePlant(None, seed + 1)  # the nominal plant
    try:
        parts.append(collect_sparse_episodes(plant, episodes - half, seed + 1))
    finally:
        plant.close()
    data = Transitions.concat(parts)
    model.fit(data.level, data.valves, data.next_level)
    demand = float(np.median((data.level - data.next_level).sum(axis=1)))  # engines served
    return demand, {"learn_pretrain_rows": len(data),
                    "learn_pretrain_seconds": time.perf_counter() - start}


def learn_step(model: FeatureModel, t: Transition, stuck: StuckValves,
               errors: list[np.ndarray], demand: float) -> float:
    """One plant step into what a learned controller keeps: valves seen not to
    follow their command into ``stuck``, the model's error on the step (before
    learning it) into ``errors``, the step into ``model``. Returns the demand
    per step estimated anew from what was burnt (level drop plus deficit)."""
    applied = t.next_obs.valves  # the plant publishes the valves it applied
    stuck.observe(t.valves, applied, t.obs.operating_steps)
    errors.append(model.add(t.obs.level, applied, t.next_obs.level))
    burnt = float(np.sum(t.obs.level - t.next_obs.level) + np.sum(t.next_obs.deficit))
    return DEMAND_MEMORY * demand + (1 - DEMAND_MEMORY) * burnt


def error_metrics(errors: list[np.ndarray]) -> dict[str, float | None]:
    """The model's one-step RMSE and largest error over ``errors``, m (None: no step)."""
    e = np.asarray(errors)
    if not len(e):
        return {"model_one_step_rmse": None, "model_max_step_error": None}
    return {"model_one_step_rmse": float(np.sqrt(np.mean(e ** 2))),
            "model_max_step_error": float(np.abs(e).max())}


class LearnedMPCAgent(Agent):
    """MPC on the model learned online; see the module docstring."""

    name = "learned-mpc"
    extra_columns = ("model_one_step_rmse", "model_max_step_error", "demand_estimate",
                     "open_fraction", "decisions_per_second", "stuck_valves", "stuck_detected")
    progress_keys = (("model_one_step_rmse", "model rmse"),)
    Config = LearnedMPCConfig

    def __init__(self, cfg: LearnedMPCConfig) -> None:
        self.cfg = cfg
        self.rng = np.random.default_rng(cfg.seed)
        self.planner = make_planner(cfg, self.rng)
        self.model = FeatureModel(cfg.learn_features, cfg.learn_forget, cfg.learn_ridge,
                                  seed=cfg.seed)
        self.demand = 0.0
        self.stuck = StuckValves()
        self._reset_interval()

    @classmethod
    def from_configs(cls, configs: dict[str, Any]) -> "LearnedMPCAgent":
        return cls(configs["mpc"])

    def _reset_interval(self) -> None:
        self.errors: list[np.ndarray] = []  # each step's prediction error (6,), m
        self.decisions, self.plan_seconds, self.opened = 0, 0.0, 0

    def prepare(self) -> dict[str, Any]:
        self.demand, info = fit_nominal(self.model, self.cfg.learn_episodes, self.cfg.seed)
        return info

    def begin_interval(self, interval: int) -> None:
        self._reset_interval()

    def start_episode(self, obs: PlantObservation) -> None:
        if isinstance(self.planner, CEMPlanner):
            self.planner.reset()  # full tanks again: forget the warm start

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        horizon = self.cfg.horizon
        if ctx.steps_left is not None and self.cfg.truncate_at_interval:
            horizon = max(1, min(horizon, ctx.steps_left))
        evaluate = LearnedEvaluator(self.model, self.demand, self.cfg.learn_terminal_band,
                                    self.stuck.stuck)
        t0 = time.perf_counter()
        u, _, _ = self.planner.plan(evaluate, obs.level, horizon)
        self.plan_seconds += time.perf_counter() - t0
        self.decisions += 1
        u = self.stuck.command(u.astype(np.int8))
        if not ctx.evaluation:
            self.opened += int(u.sum())
        return u

    def observe(self, t: Transition) -> None:
        self.demand = learn_step(self.model, t, self.stuck, self.errors, self.demand)

    def end_online(self) -> dict[str, Any]:
        return {**error_metrics(self.errors),
                "open_fraction": self.opened / (self.cfg.steps_per_interval * NUM_TANKS),
                "decisions_per_second": (self.decisions / self.plan_seconds
                                         if self.plan_seconds else None)}

    def end_interval(self, interval: int, data: Transitions | None) -> dict[str, Any]:
        self.model.settle()
        return {"demand_estimate": self.demand, **self.stuck.metrics()}

    # -- persistence ---------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {"np_rng": self.rng.bit_generator.state, "demand": self.demand,
                "stuck": self.stuck.state_dict()["stuck"],  # as older checkpoints had it
                "stuck_valves": self.stuck.state_dict(),
                "learned_model": self.model.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        missing = sorted({"np_rng", "demand", "stuck", "learned_model"} - set(state))
        if missing:
            raise CheckpointError(f"checkpoint lacks the agent's {', '.join(missing)}")
        self.rng.bit_generator.state = state["np_rng"]
        self.demand = float(state["demand"])
        self.stuck.load_state_dict(state.get("stuck_valves", {"stuck": state["stuck"]}))
        self.model.load_state_dict(state["learned_model"])
