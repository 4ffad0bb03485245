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

from ftc.common.errors import CheckpointError
from ftc.control.run import checkpoint
from ftc.control.run.agent import Agent, StepContext, Transition
from ftc.control.run.checkpoint import check_finite_state
from ftc.control.agents import world_model_options
from ftc.control.run.metrics import PPO_COLUMNS, PPO_PROGRESS_KEYS
from ftc.control.agents.ppo_online import OnlinePPO, PolicyConfig
from ftc.learning.offline import (ModelWindow, OfflineResult, OfflineSettings, offline_phase,
                                  pretrained_world_model)
from ftc.learning.ppo import PPO, PPOConfig
from ftc.learning.pretrain import code_fingerprint
from ftc.learning.transitions import Transitions
from ftc.learning.world_model import WorldModelConfig
from ftc.plant.link import PlantObservation

OFFLINE_MODES = ("sequential", "background")


@dataclass
class ControllerConfig(PolicyConfig):
    """A run of Algorithm 1 (``--method ppo`` and its variants ppo-online,
    ppo-offline, ppo-pretrained): the options of every PPO method and those of
    its offline phase on the world model."""

    NEEDS: ClassVar[dict[str, Any]] = {
        **{name: ("offline", True) for name in (
            "offline_mode", "offline_steps", "offline_envs", "offline_rollout",
            "offline_minibatch", "model_window", "model_engine", "model_episodes")},
        # the cache holds pretrained world models and policies
        "pretrain_cache": [("offline", True), ("pretrain", True)]}

    offline: bool = field(default=True, metadata={"help": (
        "after each online interval refit the world model and train PPO on it")})
    offline_mode: str = field(default="sequential", metadata={"choices": OFFLINE_MODES, "help": (
        "sequential: offline phase between intervals; background: in a separate "
        "process while online control continues with the current policy, the improved "
        "policy swapped in at the next update boundary after it is ready (not "
        "reproducible step for step: the swap point depends on timing)")})
    model_window: int = world_model_options.model_window()
    model_engine: str = world_model_options.model_engine()
    model_episodes: int = world_model_options.model_episodes()

    def validate(self) -> None:
        super().validate()
        if self.offline and self.offline_steps < 1:
            raise ValueError("--offline-steps must be >= 1 with --offline")

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
    Config = ControllerConfig
    parts = {"ppo": (PPOConfig, "ppo-")}

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
