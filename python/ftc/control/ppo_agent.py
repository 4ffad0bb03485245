"""The paper's adaptive controller (Algorithm 1) as an agent of the interval
runner: PPO online on the real plant, and after every interval a world model
refitted from that interval's real experience and PPO trained offline on it.

    python -m ftc.controller --scenario scenarios/single.toml --seed 0 --out runs/s0

Data flow of one interval k (t_online = 512 real steps):

    plant --levels--> policy --valves--> plant      x 512    (the runner's loop)
         |                                  ^
         +-- Transition ---> collector -----|-- PPO update every t_update = 128 steps
         |
         +-- deterministic evaluation episode (plant.evaluate(), age frozen)
         |
    end of interval (sequential, or in a background process):
         world model  <- refit from the interval's transitions (warm start), cache cleared
         PPO on ModelEnv(world model) for t_offline = 2048 model steps
         -> improved policy (swapped in when ready)

The plant degrades itself at every interval boundary; the controller is never
told the fault parameters (the model env's fuel demand is estimated from the
observed consumption). With --pretrain the policy is first trained on the
nominal plant in simulation and stopped while it still explores.
"""

from __future__ import annotations

import concurrent.futures
import copy
import dataclasses
import multiprocessing
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from ftc.common.cli import at_least, between, positive
from ftc.common.errors import CheckpointError
from ftc.common.constants import DEFAULT_LCM_URL
from ftc.control import checkpoint, registry
from ftc.control.agent import Agent, StepContext, Transition
from ftc.control.checkpoint import check_finite_state
from ftc.control.config import MAX_INTERVALS, MAX_STEPS_PER_INTERVAL, RunConfig
from ftc.control.metrics import PPO_COLUMNS, PPO_PROGRESS_KEYS
from ftc.control.ppo_online import OnlinePPO
from ftc.learning.offline import (ModelWindow, OfflineResult, OfflineSettings, offline_phase,
                                  pretrained_world_model)
from ftc.learning.ppo import PPO, PPOConfig
from ftc.learning.pretrain import PretrainSettings, code_fingerprint
from ftc.learning.transitions import Transitions
from ftc.learning.world_model import WorldModelConfig
from ftc.plant.lcm_link import check_loopback_url
from ftc.plant.link import PlantObservation

METHODS = registry.config_values("ftc.controller")  # the values of ControllerConfig.method
PPO_METHODS = registry.policy_methods()  # ppo, ppo-robust: the rest refuse PPO's options
OFFLINE_MODES = ("sequential", "background")


@dataclass
class ControllerConfig(RunConfig):
    """Everything a controller run depends on (with --ppo-* fields of :class:`PPOConfig`)."""

    #: options no longer offered (they measured worse: docs/controller.md), with the
    #: value that does what the controller does now: a stored config.json that
    #: holds that value resumes, any other is refused (control/cli.py)
    RETIRED_FIELDS: ClassVar[dict[str, Any]] = {"pretrain_deterministic_closed": False,
                                                "pretrain_sim": "core"}

    method: str = field(default="ppo", metadata={"choices": METHODS, "help": (
        "ppo: Algorithm 1 as its flags configure it; ppo-online (= ppo --no-offline), "
        "ppo-offline (= ppo --offline), ppo-pretrained (= ppo --offline --pretrain): its "
        "compared variants; closed / open / random: baselines (all valves closed, all open, "
        "each valve open with p=0.5) through the same loop and plant; balance: a rule that "
        "moves fuel to the light wing when |cg| > 0.1; ppo-robust: PPO online with an "
        "offline phase guided by a planner on the identified physics (docs/controller.md)")})
    update_every: int = field(default=128, metadata={"check": at_least(1, MAX_STEPS_PER_INTERVAL), "help": (
        "t_update: real steps between PPO updates (paper: 128)")})
    offline: bool = field(default=True, metadata={"help": (
        "after each online interval refit the world model and train PPO on it")})
    offline_mode: str = field(default="sequential", metadata={"choices": OFFLINE_MODES, "help": (
        "sequential: offline phase between intervals; background: in a separate "
        "process while online control continues with the current policy, the improved "
        "policy swapped in at the next update boundary after it is ready (not "
        "reproducible step for step: the swap point depends on timing)")})
    offline_steps: int = field(default=2048, metadata={"check": at_least(0, 100_000_000), "help": (
        "t_offline: model steps of offline PPO per interval (paper: 2048; ppo-robust: 0 "
        "keeps only the guided fit)")})
    offline_envs: int = field(default=16, metadata={"check": at_least(1, 100_000), "help": (
        "model rollouts run side by side (one batch through the world model)")})
    offline_rollout: int = field(default=64, metadata={"check": at_least(1, 1_000_000), "help": (
        "model steps per env between offline PPO updates (update batch = envs x rollout)")})
    offline_minibatch: int = field(default=64, metadata={"check": at_least(1, 1_000_000), "help": (
        "PPO minibatch size for offline updates (online uses --ppo-minibatch-size)")})
    model_window: int = field(default=1, metadata={"check": at_least(1, MAX_INTERVALS), "help": (
        "intervals of real data each refit trains on: 1 = only the interval just run "
        "(Algorithm 1: the cache is cleared after each refit); k > 1 keeps the last k")})
    model_engine: str = field(default="numpy", metadata={"choices": ("numpy", "torch"), "help": (
        "how the world model is trained: numpy (several times faster at this size) or "
        "torch (autograd); the same algorithm, minibatches and stopping rule, float32 "
        "rounding differs (docs/benchmarks.md)")})
    model_episodes: int = field(default=50, metadata={"check": at_least(1, 100_000), "help": (
        "nominal random-valve episodes for world-model pretraining (paper: 50)")})
    pretrain: bool = field(default=False, metadata={"help": (
        "pretrain the policy on the nominal plant in simulation (in-process core) "
        "before interval 0, stopped while it still explores (see --pretrain-open-fraction)")})
    pretrain_open_fraction: float = field(default=0.05, metadata={"check": between(0.0, 1.0), "help": (
        "pretraining stops once the mean valve-open probability over the last rollout "
        "falls to this (~5% keeps enough exploration to adapt; trained to convergence the "
        "policy barely adapts)")})
    pretrain_max_steps: int = field(default=200_000, metadata={"check": at_least(1, 1_000_000_000), "help": (
        "upper bound on pretraining simulation steps")})
    pretrain_envs: int = field(default=16, metadata={"check": at_least(1, 10_000), "help": "nominal plants simulated side by side"})
    pretrain_ent_coef: float = field(default=0.0, metadata={"check": between(0.0, 10.0), "help": (
        "entropy bonus while pretraining; 0: the stop rule, not the bonus, decides how "
        "much exploration is left (with 0.01 the open fraction stalls near 0.15)")})
    pretrain_lr: float | None = field(default=None, metadata={"check": positive(1.0), "help": (
        "Adam step size while pretraining (None: the PPO learning rate)")})
    pretrain_minibatch: int = field(default=256, metadata={"check": at_least(1, 1_000_000), "help": (
        "PPO minibatch size while pretraining (large batches of cheap simulated steps)")})
    pretrain_rollout: int = field(default=64, metadata={"check": at_least(1, 1_000_000), "help": "steps per plant between updates"})
    pretrain_cache: str = field(default="~/.cache/ftc/pretrain", metadata={
        "run_local": True, "help": (
        "directory of pretrained policies and world models, keyed by a hash of everything "
        "pretraining depends on (seed, pretrain, PPO and model settings, code); a hit skips "
        "pretraining with the same result ('' disables)")})
    fresh_optimizer: bool = field(default=True, metadata={"help": (
        "reset Adam's state when adaptation starts, after pretraining (narrows the spread "
        "across seeds)")})
    push_policy: str | None = field(default=None, metadata={"run_local": True, "help": (
        "after every interval, push the acting policy's weights (policy_t, the version "
        "the time in ms) to a policy node (build/policy_node) listening on this channel "
        "prefix at --push-url: learn here, fly there (docs/deploy.md). PPO methods only "
        "(None: no push)")})
    push_url: str = field(default=DEFAULT_LCM_URL, metadata={"run_local": True, "help": (
        "with --push-policy: the node's LCM URL (ttl=0)")})

    def ignored(self) -> dict[str, str]:
        """The pretraining options that have no effect on this run, each with why
        (the command line refuses them when given; a baseline refuses every PPO
        option, ppo its robust options)."""
        if self.pretrain or self.method not in PPO_METHODS:
            return {}
        return {f.name: "without --pretrain" for f in dataclasses.fields(self)
                if f.name.startswith("pretrain_") and f.name != "pretrain_cache"}

    def validate(self) -> None:
        super().validate()
        if self.push_policy is not None and not self.push_policy.strip():
            raise ValueError("--push-policy must name the node's channel prefix, got ''")
        try:
            check_loopback_url(self.push_url)
        except ValueError as e:
            raise ValueError(f"--push-url: {e}") from None
        if self.push_policy is None and self.push_url != DEFAULT_LCM_URL:
            raise ValueError("--push-url is where --push-policy sends the policy: give "
                             "--push-policy PREFIX with it")
        if self.method == "ppo" and self.offline and self.offline_steps < 1:
            raise ValueError("--offline-steps must be >= 1 with --method ppo --offline")
        if self.method in PPO_METHODS and self.steps_per_interval % self.update_every:
            raise ValueError("--steps-per-interval must be a multiple of --update-every")

    def pretrain_settings(self) -> PretrainSettings:
        return PretrainSettings(
            seed=self.seed, steps_per_interval=self.steps_per_interval, envs=self.pretrain_envs,
            rollout=self.pretrain_rollout, minibatch=self.pretrain_minibatch,
            max_steps=self.pretrain_max_steps, open_fraction=self.pretrain_open_fraction,
            ent_coef=self.pretrain_ent_coef, lr=self.pretrain_lr)

    def offline_settings(self) -> OfflineSettings:
        return OfflineSettings(seed=self.seed, steps=self.offline_steps, envs=self.offline_envs,
                               rollout=self.offline_rollout, minibatch=self.offline_minibatch,
                               max_episode_steps=self.steps_per_interval,
                               model_engine=self.model_engine)


class PPOAgent(Agent):
    """Algorithm 1: PPO online (an update every t_update real steps: its
    :class:`OnlinePPO`) and, after each interval, the offline phase on the
    refitted world model."""

    name = "ppo"
    extra_columns = PPO_COLUMNS
    progress_keys = PPO_PROGRESS_KEYS

    def __init__(self, cfg: ControllerConfig, ppo_config: PPOConfig) -> None:
        self.cfg, self.ppo_config = cfg, ppo_config
        self.ppo = PPO(ppo_config, seed=cfg.seed)
        self.online = OnlinePPO(self.ppo, cfg.update_every)
        self.model_state: dict | None = None
        self.model_fits = 0
        self.window = ModelWindow(cfg.model_window)
        # background offline phase
        self.executor: concurrent.futures.ProcessPoolExecutor | None = None
        self.pending: tuple[concurrent.futures.Future, int] | None = None
        self.pending_data: tuple[int, Transitions] | None = None
        self.queued: int | None = None  # background learning: the next phase's interval
        self.swaps = 0
        self._swaps_before = 0
        self._late: list[tuple[int, dict[str, Any]]] = []

    @classmethod
    def from_configs(cls, configs: dict[str, Any]) -> "PPOAgent":
        return cls(configs["controller"], configs["ppo"])

    # -- setup ------------------------------------------------------------------
    def prepare(self) -> dict[str, Any]:
        """Pretrain the world model (offline on) and the policy (--pretrain)."""
        cfg, info = self.cfg, {}
        if cfg.offline:
            model, _demand, info = pretrained_world_model(cfg.model_episodes, cfg.seed,
                                                          cfg.pretrain_cache, cfg.model_engine)
            self.model_state, self.model_fits = model.state_dict(), model.fits
        if cfg.pretrain:
            info.update(self.online.pretrain(cfg.pretrain_settings(), cfg.pretrain_cache,
                                             cfg.fresh_optimizer))
        return info

    def wants_data(self) -> bool:
        return self.cfg.offline

    def exported_policy(self) -> Any:
        return self.ppo.policy

    def config_doc(self) -> dict[str, Any]:
        doc: dict[str, Any] = {}
        if self.cfg.offline:
            doc["world_model"] = dataclasses.asdict(
                WorldModelConfig(seed=self.cfg.seed, engine=self.cfg.model_engine))
        if self.cfg.pretrain:  # what the pretraining cache key covers
            doc["pretrain_code"] = code_fingerprint()
        return doc

    # -- online -----------------------------------------------------------------
    def begin_interval(self, interval: int) -> None:
        self.online.begin_interval(self.background_learning)
        self._swaps_before = self.swaps

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        return self.online.act(obs, ctx)

    def observe(self, t: Transition) -> None:
        stats = self.online.observe(t)
        if stats is not None:  # an update boundary: where a finished offline phase swaps in
            self.telemetry.update(stats._asdict())
            if self.pending is not None and self.pending[0].done() and not self.online.updating:
                self._take_pending()
            if self.pending is None and self.queued is not None:
                self._submit(self._offline_inputs(self.queued))
                self.queued = None

    def end_online(self) -> dict[str, Any]:
        return self.online.end_online()

    # -- offline ----------------------------------------------------------------
    def end_interval(self, interval: int, data: Transitions | None) -> dict[str, Any]:
        metrics: dict[str, Any] = {}
        if self.cfg.offline:
            self.window.add(data)
            if self.cfg.offline_mode == "sequential" and not self.background_learning:
                metrics = self._apply(offline_phase(*self._offline_inputs(interval)), interval)
            elif self.background_learning and self.pending is not None:
                # the control loop does not wait: it starts once the phase in flight
                # has swapped in (observe), as its model is this refit's start
                self.queued = interval
            else:
                self._wait_pending()  # the previous phase's model is the next refit's start
                self._submit(self._offline_inputs(interval))
        metrics["policy_swaps"] = self.swaps - self._swaps_before
        return metrics

    def _offline_inputs(self, interval: int, data: Transitions | None = None) -> tuple:
        data = self.window.take() if data is None else data
        # copies: pickling a tensor for the background worker moves its storage into
        # shared memory, which would move the live policy's weights under the actor
        return (copy.deepcopy(self.ppo.state_dict()), self.ppo_config, self.model_state,
                self.model_fits, data, self.cfg.offline_settings(), interval)

    def _apply(self, result: OfflineResult, interval: int) -> dict[str, Any]:
        what = f"the offline phase of interval {interval}"
        check_finite_state(result.ppo_state["policy"], f"policy weights after {what}")
        check_finite_state(result.model_state, f"world-model weights after {what}")
        self.ppo.load_state_dict(result.ppo_state)
        self.model_state, self.model_fits = result.model_state, result.model_fits
        return result.metrics

    def _submit(self, inputs: tuple) -> None:
        """Start an offline phase in the background worker."""
        interval, data = inputs[-1], inputs[4]
        if self.executor is None:
            self.executor = concurrent.futures.ProcessPoolExecutor(
                1, mp_context=multiprocessing.get_context("spawn"))
        generator_state = self.ppo.generator.get_state()
        self.pending = (self.executor.submit(offline_phase, *inputs), interval)
        self.pending_data = (interval, data)
        self.ppo.generator.set_state(generator_state)

    def _take_pending(self) -> None:
        future, interval = self.pending
        self.pending, self.pending_data = None, None
        result = future.result()
        # the online generator keeps its own stream; only weights and Adam state swap in
        generator_state = self.ppo.generator.get_state()
        self._late.append((interval, self._apply(result, interval)))
        self.ppo.generator.set_state(generator_state)
        self.swaps += 1

    def _wait_pending(self) -> None:
        if self.pending is not None:
            self._take_pending()

    def late_metrics(self) -> list[tuple[int, dict[str, Any]]]:
        late, self._late = self._late, []
        return late

    def finish(self) -> None:
        self.online.finish()
        self._wait_pending()
        if self.queued is not None:
            self._submit(self._offline_inputs(self.queued))
            self.queued = None
            self._wait_pending()

    def close(self) -> None:
        self.online.close()
        if self.executor is not None:
            self.executor.shutdown(cancel_futures=True)
            self.executor = None

    # -- persistence ------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {"ppo": self.online.state_dict(), "model": self.model_state,
                "model_fits": self.model_fits,
                "window": [checkpoint.transitions_state(w) for w in self.window.parts],
                # a background offline phase in flight: its data, to start it again on resume
                "pending": None if self.pending_data is None else {
                    "interval": self.pending_data[0],
                    "data": checkpoint.transitions_state(self.pending_data[1])},
                # real time: the phase waiting for that one (its data is the window's)
                "queued": self.queued}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        missing = sorted({"ppo", "model", "model_fits", "window", "pending"} - set(state))
        if missing:
            raise CheckpointError(f"checkpoint lacks the agent's {', '.join(missing)}")
        if state["model"] is not None:
            try:
                check_finite_state(state["model"], "world-model weights in the checkpoint")
            except Exception as e:  # NonFiniteError: a checkpoint that cannot be resumed
                raise CheckpointError(str(e)) from None
        self.online.load_state_dict(state["ppo"])
        self.model_state, self.model_fits = state["model"], state["model_fits"]
        self.window.parts = [checkpoint.transitions_from_state(w) for w in state["window"]]
        if state["pending"] is not None:  # restart the phase that was in flight
            p = state["pending"]
            self._submit(self._offline_inputs(p["interval"],
                                              checkpoint.transitions_from_state(p["data"])))
        self.queued = state.get("queued")  # started once the one above has swapped in
