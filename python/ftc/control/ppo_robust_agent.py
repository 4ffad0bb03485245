"""``ppo-robust``: the paper's scheme (PPO online on the plant, offline on a
model refitted after every interval, nominal pretraining) with the changes
that made it hold up on faults it was never tuned on (docs/controller.md):

* the offline model is the plant's physics with its parameters identified
  from the interval's data (:mod:`ftc.learning.identify`; it assumes the
  plant's structure), extrapolated one interval ahead, so the offline phase
  trains for the plant the next interval will meet, not the one just left;
* offline phases far longer than the paper's 2048 model steps (model steps
  are cheap), half of their episodes short branches from levels observed on
  the real plant (MBPO) and half full-tank episodes.

    python -m ftc.controller --method ppo-robust --pretrain --offline-steps 16384 ...
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from ftc.common.constants import offline_seed
from ftc.control.agent import Transition
from ftc.control.checkpoint import check_finite_state
from ftc.control.ppo_agent import ControllerConfig, PPOAgent
from ftc.learning.identify import Identifier, PlantParameters
from ftc.learning.physics_env import PhysicsEnv
from ftc.learning.ppo import PPOConfig
from ftc.learning.pretrain import pretrain_cached
from ftc.learning.rollout import train_on_env
from ftc.learning.transitions import Transitions


class RobustPPOAgent(PPOAgent):
    name = "ppo-robust"

    def __init__(self, cfg: ControllerConfig, ppo_config: PPOConfig) -> None:
        super().__init__(cfg, ppo_config)
        self.identifier = Identifier(seed=cfg.seed)
        self.history: list[PlantParameters] = []
        self.prior = PlantParameters.nominal()
        self.rows: list[tuple[np.ndarray, ...]] = []

    def prepare(self) -> dict[str, Any]:
        info: dict[str, Any] = {}
        if self.cfg.pretrain:
            info.update(pretrain_cached(self.ppo, self.cfg.pretrain_settings(),
                                        self.cfg.pretrain_cache))
            if self.cfg.fresh_optimizer:
                self.ppo.reset_optimizer()
        return info

    def wants_data(self) -> bool:
        return False

    def config_doc(self) -> dict[str, Any]:
        return {}

    def begin_interval(self, interval: int) -> None:
        super().begin_interval(interval)
        self.rows = []
        if len(self.history) >= 2:
            self.prior = self.history[-1].extrapolate(self.history[-2])
        elif self.history:
            self.prior = self.history[-1]

    def observe(self, t: Transition) -> None:
        self.rows.append((t.obs.level, t.valves, t.next_obs.level, t.next_obs.deficit))
        super().observe(t)

    def end_interval(self, interval: int, data: Transitions | None) -> dict[str, Any]:
        cfg, start = self.cfg, time.perf_counter()
        level, valves, next_level, deficit = (np.array(c) for c in zip(*self.rows))
        params, rms = self.identifier.fit(level, valves, next_level, deficit, self.prior)
        self.history.append(params)
        ahead = params.extrapolate(self.history[-2]) if len(self.history) >= 2 else params
        refit_seconds = time.perf_counter() - start
        env = PhysicsEnv(ahead.as_core(), cfg.offline_envs, max_episode_steps=cfg.steps_per_interval,
                         starts=next_level, branch_fraction=cfg.branch_fraction,
                         branch_steps=cfg.branch_steps, seed=offline_seed(cfg.seed, interval))
        online_config = self.ppo.config
        generator_state = self.ppo.generator.get_state()
        self.ppo.generator.manual_seed(offline_seed(cfg.seed, interval))
        self.ppo.config = dataclasses.replace(online_config, minibatch_size=cfg.offline_minibatch)
        try:
            stats, rew, _ = train_on_env(self.ppo, env, cfg.offline_steps, cfg.offline_rollout)
        finally:
            self.ppo.config = online_config
            self.ppo.generator.set_state(generator_state)
        check_finite_state(self.ppo.policy.state_dict(),
                           f"policy weights after the offline phase of interval {interval}")
        return {"model_one_step_rmse": rms, "offline_reward_per_step": rew,
                "offline_updates": len(stats), "refit_seconds": refit_seconds,
                "offline_seconds": time.perf_counter() - start, "policy_swaps": 0,
                "offline_model_errors": env.errors}

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "history": [p.vector().tolist() for p in self.history],
                "identifier_rng": self.identifier.rng.bit_generator.state}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.identifier.rng.bit_generator.state = state["identifier_rng"]
        self.history = [PlantParameters.from_vector(np.array(v)) for v in state["history"]]
