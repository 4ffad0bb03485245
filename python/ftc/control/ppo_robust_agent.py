"""``ppo-robust``: the paper's scheme (PPO online on the plant, offline on a
model refitted after every interval, nominal pretraining) with the changes
that made it hold up on faults it was never tuned on (docs/controller.md):

* the offline model is the plant's physics with its parameters identified
  from the interval's data (:mod:`ftc.learning.identify`; it assumes the
  plant's structure), extrapolated one interval ahead, so the offline phase
  trains for the plant the next interval will meet, not the one just left;
* guided offline training: the oracle's planner, run on the identified
  physics, labels levels the policy will meet (a sample of those observed on
  the plant, and those the current policy visits on the model from full
  tanks, as in DAgger), and the policy is first fitted to those decisions
  (:mod:`ftc.learning.distill`), then trained by PPO on the identified physics,
  half of its episodes short branches from observed levels (MBPO).

    python -m ftc.controller --method ppo-robust --pretrain --offline-steps 16384 ...
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np
import torch

from ftc.common.constants import offline_seed
from ftc.control.agent import Transition
from ftc.control.checkpoint import check_finite_state
from ftc.control.planners import HoldPlanner, ParamsEvaluator
from ftc.control.ppo_agent import ControllerConfig, PPOAgent
from ftc.learning.distill import distill
from ftc.learning.identify import Identifier, PlantParameters
from ftc.learning.physics_env import PhysicsEnv
from ftc.learning.ppo import PPOConfig
from ftc.learning.pretrain import pretrain_cached
from ftc.learning.rollout import train_on_env
from ftc.learning.transitions import Transitions


class RobustPPOAgent(PPOAgent):
    name = "ppo-robust"

    def __init__(self, cfg: ControllerConfig, ppo_config: PPOConfig) -> None:
        from ftc import _core  # native: the plant's integrator for the teacher's rollouts

        super().__init__(cfg, ppo_config)
        self.identifier = Identifier(seed=cfg.seed)
        self.history: list[PlantParameters] = []
        self.prior = PlantParameters.nominal()
        self.rows: list[tuple[np.ndarray, ...]] = []
        self.teacher = HoldPlanner(3, 10)  # the oracle MPC's planner (H = 3, L = 10)
        self.teacher_eval = ParamsEvaluator(_core.BatchRollout(rtol=1e-6, atol=1e-8))

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
        # guided: the planner on the identified physics labels states the policy will meet
        self.teacher_eval.params = ahead.as_core()
        states = self._teacher_states(next_level, interval)
        labels = np.stack([self.teacher.plan(self.teacher_eval, x)[0] for x in states])
        metrics = distill(self.ppo, torch.as_tensor(states, dtype=torch.float32),
                          torch.as_tensor(labels, dtype=torch.float32),
                          seed=offline_seed(cfg.seed, interval))
        teach_seconds = time.perf_counter() - start - refit_seconds
        rew, updates, errors = float("nan"), 0, 0
        if cfg.offline_steps:  # then PPO on the identified physics (also fits the critic)
            env = PhysicsEnv(ahead.as_core(), cfg.offline_envs,
                             max_episode_steps=cfg.steps_per_interval, starts=next_level,
                             branch_fraction=cfg.branch_fraction, branch_steps=cfg.branch_steps,
                             seed=offline_seed(cfg.seed, interval))
            online_config = self.ppo.config
            generator_state = self.ppo.generator.get_state()
            self.ppo.generator.manual_seed(offline_seed(cfg.seed, interval))
            self.ppo.config = dataclasses.replace(online_config,
                                                  minibatch_size=cfg.offline_minibatch)
            try:
                stats, rew, _ = train_on_env(self.ppo, env, cfg.offline_steps,
                                             cfg.offline_rollout)
            finally:
                self.ppo.config = online_config
                self.ppo.generator.set_state(generator_state)
            updates, errors = len(stats), env.errors
        check_finite_state(self.ppo.policy.state_dict(),
                           f"policy weights after the offline phase of interval {interval}")
        return {**metrics, "model_one_step_rmse": rms, "offline_reward_per_step": rew,
                "offline_updates": updates, "refit_seconds": refit_seconds,
                "teach_seconds": teach_seconds, "teacher_labels": len(states),
                "offline_seconds": time.perf_counter() - start, "policy_swaps": 0,
                "offline_model_errors": errors}

    def _teacher_states(self, observed: np.ndarray, interval: int) -> np.ndarray:
        """Levels to label: a sample of those observed on the plant, and those the
        current policy visits on the identified physics from full tanks (so the
        policy learns what to do where it goes, as in DAgger)."""
        rng = np.random.default_rng(offline_seed(self.cfg.seed, interval))
        n = self.cfg.teacher_states
        picked = observed[rng.choice(len(observed), min(n // 2, len(observed)), replace=False)]
        env = PhysicsEnv(self.teacher_eval.params, 1, max_episode_steps=self.cfg.steps_per_interval,
                         seed=offline_seed(self.cfg.seed, interval))
        obs, visited = env.reset(), []
        with torch.no_grad():
            while len(visited) < n - len(picked):
                visited.append(obs[0].numpy().astype(np.float64))
                actions, _, _ = self.ppo.act(obs, deterministic=True)
                obs = env.step(actions).obs
        return np.concatenate([picked, np.array(visited)]) if visited else picked

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "history": [p.vector().tolist() for p in self.history],
                "identifier_rng": self.identifier.rng.bit_generator.state}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.identifier.rng.bit_generator.state = state["identifier_rng"]
        self.history = [PlantParameters.from_vector(np.array(v)) for v in state["history"]]
