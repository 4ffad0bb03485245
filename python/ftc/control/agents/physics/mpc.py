"""Model-predictive control of the fuel plant: the reference controllers.

    python -m ftc.mpc --method oracle-mpc --scenario scenarios/single.toml --seed 0 --out runs/oracle
    python -m ftc.mpc --method model-mpc  --scenario scenarios/single.toml --seed 0 --out runs/mpc

* ``oracle-mpc``: knows the faults. It reads the same scenario file as the plant
  and plans on the true physics degraded to the age in force (the C++ core's
  batch rollouts, ``_core.BatchRollout``): an upper reference for every
  controller that is not told the faults.
* ``model-mpc``: plans on the controller's learned world model (batched torch
  rollouts), pretrained on the nominal data set and refitted after every
  interval from that interval's real transitions exactly as PPO's offline
  phase does; never told the faults (the termination rule uses the demand
  estimated from observed consumption).

Planner (both): receding horizon. ``hold``: each of the 64 valve settings held
for H steps, then all valves closed up to a horizon of L steps; rollouts reset
to full tanks after a terminal step, as the plant does; the best summed reward
wins, its first step is applied, and the plan is redone every step. ``cem``:
a cross-entropy search over per-step valve-open probabilities (L x 6), for
longer horizons, seeded with the best hold plan. ``two-stage``: each of the 64
settings held H1 steps, then each of the 64 held to the horizon (4,096 plans,
optionally pruned to the best first settings), together with the hold plans,
the better of the two families winning (``reference`` is ``oracle-mpc`` with it).

Both are agents of the interval runner (:mod:`ftc.control.run.runner`), so they
drive the plant through the same :class:`ftc.plant.PlantLink` as every
controller and write the controller's outputs into --out: config.json,
metrics.csv (the controller's columns, one row per interval, rewritten
atomically), checkpoint.pt (--resume continues), done.json.

Bad input is refused before anything is written (exit 2, one line naming the
option, or the scenario file and key); the options ftc.experiments passes to
every method's controller that only mean something to PPO are accepted and
ignored, with a note.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from ftc.common.cli import at_least, positive
from ftc.common.constants import NUM_TANKS
from ftc.common.errors import CheckpointError
from ftc.control.run import checkpoint
from ftc.control.run.agent import Agent, StepContext
from ftc.control.run.metrics import MODEL_COLUMNS
from ftc.control.agents.mpc_config import PLANNERS, MPCConfig
from ftc.control.agents import world_model_options
from ftc.control.planning.physics.episode_planner import EpisodePlanner
from ftc.control.planning.physics.true_physics import TruePhysics
from ftc.control.planning.physics.evaluators import OracleEvaluator
from ftc.control.planning.planners import CEMPlanner, Evaluator, ModelEvaluator, make_planner
from ftc.learning.offline import ModelWindow, pretrained_world_model, refit
from ftc.learning.transitions import Transitions
from ftc.learning.world_model import WorldModel, WorldModelConfig
from ftc.plant.link import PlantObservation

# refused_rollouts: candidates whose rollout the integrator refused (scored -inf),
# for the MPCs that plan on the C++ physics (oracle-mpc, identified-mpc); blank for model-mpc
# episode_plans: plans the episode planner made in the interval (reference; blank for
# the others): one at the interval's start and one for its evaluation episode, more
# where the plant departed from a plan
MPC_COLUMNS = ("decisions_per_second", "plan_open_fraction", "model_fit_epochs",
               "refused_rollouts", "episode_plans")


@dataclass
class PhysicsConfig(MPCConfig):
    """An MPC run on the plant's equations (oracle-mpc, identified-mpc): the
    planner's options and the rollouts' integrator."""

    rollout_closed_form: bool = field(default=False, metadata={"help": (
        "step the rollouts with two or more valves open in closed "
        "form (_core.BatchRollout's exact_active_conduit; CVODE only where a tank is pinned): "
        "within CVODE's tolerances of it and several times faster")})
    rollout_rtol: float = field(default=1e-6, metadata={"check": positive(1.0), "help": (
        "CVODE relative tolerance of the rollouts (measured: 1e-6 moves summed "
        "10-step rewards by < 2e-5 against 1e-12, never the chosen action in the bench, "
        "and is 1.6x faster than the plant's 1e-8)")})
    rollout_atol: float = field(default=1e-8, metadata={"check": positive(1.0), "help": "CVODE absolute tolerance, m"})


@dataclass
class OracleConfig(PhysicsConfig):
    """An oracle-mpc run: it may also plan whole episodes (--planner episode)."""

    NEEDS: ClassVar[dict[str, tuple[str, Any]]] = {"episode_sweeps": ("planner", "episode"),
                                                   "episode_tolerance": ("planner", "episode")}

    planner: str = field(default="hold", metadata={"choices": (*PLANNERS, "episode"), "help": (
        "hold: the 64 settings each held --hold steps then all closed; cem: "
        "cross-entropy search over per-step valve probabilities; two-stage: each setting "
        "held --two-stage-hold steps then each setting to the horizon (4,096 plans), and "
        "the hold plans; episode: whole episodes optimised on the true physics and played, "
        "never below the hold planner's closed loop "
        "(ftc.control.planning.physics.episode_planner)")})
    episode_sweeps: int = field(default=6, metadata={"check": at_least(1, 1000), "help": (
        "episode: coordinate-ascent sweeps over an episode's steps at most (each tries every "
        "setting held 1, 2, 4 and 8 steps at every step)")})
    episode_tolerance: float = field(default=1e-6, metadata={"check": positive(1.0), "help": (
        "episode: the plan is remade where an observed level differs from its prediction "
        "by more than this (plus 6 times the scenario's sensor-noise std), m")})


@dataclass
class ModelMPCConfig(MPCConfig):
    """A model-mpc run: the planner's options and the world model's."""

    method: str = field(default="model-mpc", metadata={"help": "the method"})
    model_window: int = world_model_options.model_window()
    model_engine: str = world_model_options.model_engine()
    model_episodes: int = world_model_options.model_episodes()
    pretrain_cache: str = field(default="~/.cache/ftc/pretrain", metadata={"run_local": True, "help": (
        "directory of pretrained world models keyed by a hash of everything "
        "pretraining depends on (episodes, seed, model config, code); a hit skips the "
        "pretraining with the same weights ('' disables)")})


class MPCAgent(Agent):
    """Receding-horizon control: every step, plan on the evaluator and apply the
    first valves of the best sequence."""

    extra_columns = (*MODEL_COLUMNS, "open_fraction", "offline_seconds", *MPC_COLUMNS)
    progress_keys = (("decisions_per_second", "decisions/s"),)

    def __init__(self, cfg: MPCConfig) -> None:
        self.cfg = cfg
        self.name = cfg.method
        self.evaluates = cfg.evaluate
        self.rng = np.random.default_rng(cfg.seed)
        self.planner = make_planner(cfg, self.rng)
        self.oracle: OracleEvaluator | None = None
        self.episode: EpisodePlanner | None = None
        self.model = None
        self.demand = 0.0
        self.window = ModelWindow(cfg.model_window if isinstance(cfg, ModelMPCConfig) else 1)
        self.decisions, self.plan_seconds, self.opened = 0, 0.0, 0
        self._interval_start = (0, 0.0, 0)
        if isinstance(cfg, OracleConfig):
            from ftc import _core  # native: the plant's scenario parser and physics

            scenario = _core.load_scenario(cfg.scenario) if cfg.scenario else _core.Scenario()
            scenario.steps_per_interval = cfg.steps_per_interval  # as the plant is told
            self.oracle = OracleEvaluator(scenario, cfg.rollout_rtol, cfg.rollout_atol,
                                          cfg.rollout_closed_form)
            if cfg.planner == "episode":
                self.episode = EpisodePlanner(
                    TruePhysics(scenario, cfg.rollout_rtol, cfg.rollout_atol,
                                cfg.rollout_closed_form),
                    # sensor noise is on the published levels, not on the state the plan
                    # follows: deviations within 6 std of it are not the plant departing
                    sweeps=cfg.episode_sweeps,
                    tolerance=cfg.episode_tolerance + 6 * scenario.noise_std,
                    hold=cfg.hold, horizon=cfg.horizon)

    @classmethod
    def from_configs(cls, configs: dict[str, Any]) -> "MPCAgent":
        return cls(configs["mpc"])

    def prepare(self) -> dict[str, Any]:
        if self.oracle is not None:
            return {}
        self.model, self.demand, info = pretrained_world_model(
            self.cfg.model_episodes, self.cfg.seed, self.cfg.pretrain_cache,
            self.cfg.model_engine)
        return {"model_pretrain_r2": info["model_pretrain_r2"], "demand_estimate": self.demand,
                "model_pretrain_seconds": info["model_pretrain_seconds"],
                "model_pretrain_cached": info["model_pretrain_cached"]}

    def wants_data(self) -> bool:
        return isinstance(self.cfg, ModelMPCConfig)

    def config_doc(self) -> dict[str, Any]:
        if not isinstance(self.cfg, ModelMPCConfig):
            return {}
        return {"world_model": dataclasses.asdict(
            WorldModelConfig(seed=self.cfg.seed, engine=self.cfg.model_engine))}

    # -- planning ----------------------------------------------------------------
    def evaluator(self, o: PlantObservation) -> Evaluator:
        if self.oracle is not None:
            # the next step's parameters and stuck valves (abrupt faults included);
            # an evaluation episode's are frozen at the last operating step's
            self.oracle.set_step(o.operating_steps, o.evaluation)
            return self.oracle
        return ModelEvaluator(self.model, self.demand)

    def start_episode(self, obs: PlantObservation) -> None:
        if isinstance(self.planner, CEMPlanner):
            self.planner.reset()  # forget the warm start: full tanks again

    def begin_interval(self, interval: int) -> None:
        self._interval_start = (self.decisions, self.plan_seconds, self.opened)

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        horizon = self.cfg.horizon
        if ctx.steps_left is not None and self.cfg.truncate_at_interval:
            horizon = max(1, min(horizon, ctx.steps_left))
        t0 = time.perf_counter()
        if self.episode is not None:
            u = self.episode.decide(obs.level, obs.operating_steps, ctx.steps_left,
                                    ctx.evaluation, self.cfg.steps_per_interval)
        else:
            u, _, _ = self.planner.plan(self.evaluator(obs), obs.level, horizon)
        self.plan_seconds += time.perf_counter() - t0
        self.decisions += 1
        if not ctx.evaluation:
            self.opened += int(u.sum())
        return u.astype(np.int8)

    def end_online(self) -> dict[str, Any]:
        decisions0, plan0, opened0 = self._interval_start
        fraction = (self.opened - opened0) / (self.cfg.steps_per_interval * NUM_TANKS)
        plan = self.plan_seconds - plan0
        return {"open_fraction": fraction, "plan_open_fraction": fraction,
                "decisions_per_second": (self.decisions - decisions0) / plan if plan else None}

    def end_interval(self, interval: int, data: Transitions | None) -> dict[str, Any]:
        """The model MPC refits its world model as PPO's offline phase does; the
        oracle reports the candidates whose rollout was refused in the interval."""
        if self.oracle is not None:
            refused, self.oracle.refused = self.oracle.refused, 0
            if self.episode is None:
                return {"refused_rollouts": refused}
            refused, self.episode.physics.refused = refused + self.episode.physics.refused, 0
            plans, self.episode.replans = self.episode.replans, 0
            return {"refused_rollouts": refused, "episode_plans": plans}
        if self.model is None:
            return {}
        start = time.perf_counter()
        self.window.add(data)
        self.demand, metrics = refit(self.model, self.window.take())
        return {**metrics, "offline_seconds": time.perf_counter() - start}

    # -- persistence ---------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {"np_rng": self.rng.bit_generator.state, "demand": self.demand,
                "model": None if self.model is None else self.model.state_dict(),
                "model_fits": 0 if self.model is None else self.model.fits,
                "window": [checkpoint.transitions_state(w) for w in self.window.parts]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        missing = sorted({"np_rng", "demand", "model", "model_fits", "window"} - set(state))
        if missing:
            raise CheckpointError(f"checkpoint lacks the agent's {', '.join(missing)}")
        self.rng.bit_generator.state = state["np_rng"]
        self.demand = float(state["demand"])
        if (state["model"] is None) != (not isinstance(self.cfg, ModelMPCConfig)):
            raise CheckpointError("checkpoint of another MPC method")
        if state["model"] is not None:
            self.model = WorldModel(WorldModelConfig(seed=self.cfg.seed,
                                                     engine=self.cfg.model_engine))
            checkpoint.check_network_shapes_of(self.model.state_dict(), state["model"],
                                               "world-model")
            self.model.load_state_dict(state["model"])
            self.model.fits = int(state["model_fits"])
        self.window.parts = [checkpoint.transitions_from_state(w) for w in state["window"]]


class OracleMPCAgent(MPCAgent):
    """oracle-mpc (and reference, its episode planner): MPC on the true physics."""

    Config = OracleConfig


class ModelMPCAgent(MPCAgent):
    """model-mpc: MPC on the world model refitted every interval."""

    Config = ModelMPCConfig
