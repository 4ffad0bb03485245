"""``ppo-learned``: the paper's scheme (PPO online on the plant, nominal
pretraining, an offline phase after every interval) made to hold up on a
model learned from data alone: guided PPO (:mod:`ftc.control.agents.learned.guided_ppo`,
DAgger with a planner as the expert, as ``ppo-robust``) whose planner and
rollouts run on ``learned-mpc``'s model (:class:`ftc.learning.feature_model.FeatureModel`),
updated after every step on the plant. No plant equations: the import
contract in pyproject.toml covers this module as it covers ``learned-mpc``.

    python -m ftc.controller --method ppo-learned --pretrain --offline-steps 0 --out runs/ppo-learned

The policy acts on the plant with one forward pass per step. Every
``--teacher-check-every`` steps the planner prices the policy's choice on the
model; a loss above ``--teacher-check-regret`` refits the policy at once from
the levels seen in the interval. After every interval the policy is fitted to
the planner's choices on the model (the levels observed on the plant, then
those the policy visits on the model), and, with ``--offline-steps``, trained
by PPO on the model (half of its episodes branched from observed levels).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import numpy as np
import torch

from ftc.common.constants import NUM_TANKS, TERMINAL_TOLERANCE, offline_seed
from ftc.common.errors import CheckpointError
from ftc.control.run.agent import Transition
from ftc.control.agents.learned.guided_ppo import GuidedConfig, GuidedPPOAgent
from ftc.control.agents.learned.learned_mpc import (LearnedEvaluator, LearnedMPCConfig,
                                                   error_metrics, fit_nominal, learn_step)
from ftc.learning.branched import BranchedStarts
from ftc.learning.feature_model import FeatureModel
from ftc.learning.ppo import PPOConfig
from ftc.learning.rollout import EnvStep, train_on_env
from ftc.learning.stuck import StuckValves
from ftc.plant.reward import AREAS, reward

# the learned model as learned-mpc's defaults configure it (ftc.mpc --help: --learn-*)
MODEL = LearnedMPCConfig()


class LearnedModelEnv(BranchedStarts):
    """N plants simulated on the learned model, stepped side by side (the step
    interface of :class:`ftc.learning.model_env.ModelEnv`). Episodes start from
    full tanks or, with probability ``branch_fraction``, from an observed level
    (``starts``), cut after ``branch_steps``; they end where the model's fuel
    falls ``band`` below the demand, or after ``max_episode_steps``."""

    def __init__(self, model: FeatureModel, demand: float, band: float, num_envs: int, *,
                 max_episode_steps: int, seed: int, starts: np.ndarray | None = None,
                 branch_fraction: float = 0.0, branch_steps: int = 64) -> None:
        super().__init__(num_envs, max_episode_steps=max_episode_steps, starts=starts,
                         branch_fraction=branch_fraction, branch_steps=branch_steps, seed=seed)
        self.model = model
        self.end_volume = demand + TERMINAL_TOLERANCE - band
        self.errors = 0  # nothing is refused on the model

    def step(self, actions: torch.Tensor) -> EnvStep:
        u = actions.numpy().astype(np.int64)
        final = self.model.predict(self.level, u)
        rew = reward(final, u)
        self.steps += 1
        term = final @ AREAS < self.end_volume
        trunc = ~term & (self.steps >= self.limit)
        self.level = final.copy()
        for i in np.flatnonzero(term | trunc):
            self._start(i)
        f = torch.float32
        return EnvStep(torch.as_tensor(self.level, dtype=f).clone(), torch.as_tensor(rew, dtype=f),
                       torch.as_tensor(term), torch.as_tensor(trunc),
                       torch.as_tensor(final, dtype=f))


class LearnedPPOAgent(GuidedPPOAgent):
    """Guided PPO on the model learned online; see the module docstring."""

    name = "ppo-learned"

    def __init__(self, cfg: GuidedConfig, ppo_config: PPOConfig) -> None:
        super().__init__(cfg, ppo_config)
        self.model = FeatureModel(MODEL.learn_features, MODEL.learn_forget, MODEL.learn_ridge,
                                  seed=cfg.seed)
        self.demand, self.added = 0.0, 0  # steps the model has learned from
        self.stuck = StuckValves()  # valves seen not to follow their command
        self._reset_interval()

    def _reset_interval(self) -> None:
        self.levels: list[np.ndarray] = []  # observed in the interval
        self.errors: list[np.ndarray] = []  # each step's prediction error before it was learned

    @property
    def teacher_eval(self) -> LearnedEvaluator:  # type: ignore[override]
        return LearnedEvaluator(self.model, self.demand, MODEL.learn_terminal_band,
                                self.stuck.stuck)

    def prepare(self) -> dict[str, Any]:
        info = super().prepare()  # the policy (--pretrain)
        self.demand, model_info = fit_nominal(self.model, MODEL.learn_episodes, self.cfg.seed)
        return {**info, **model_info}

    def _begin_interval(self, interval: int) -> None:
        super()._begin_interval(interval)
        self._reset_interval()

    def watch(self, t: Transition) -> bool:
        self.demand = learn_step(self.model, t, self.stuck, self.errors, self.demand)
        self.added += 1
        self.levels.append(np.asarray(t.next_obs.level, np.float64))
        return False  # the model follows the plant step by step; the checks catch a change

    def observed_levels(self) -> np.ndarray:
        return np.array(self.levels).reshape(-1, NUM_TANKS)

    def steps_seen(self) -> int:
        return len(self.levels)

    def plan_key(self) -> tuple[Any, Callable[[Any, Any], bool]]:
        self.model.solve()  # plan on every step seen
        return self.added, lambda a, b: a == b

    def rollout_env(self, seed: int) -> LearnedModelEnv:
        return LearnedModelEnv(self.model, self.demand, MODEL.learn_terminal_band, 1,
                               max_episode_steps=self.cfg.steps_per_interval, seed=seed)

    def end_model(self, interval: int) -> dict[str, Any]:
        self.model.settle()
        return {"model_one_step_rmse": error_metrics(self.errors)["model_one_step_rmse"],
                "detected_changes": 0, "mispredicted_steps": None, **self.stuck.metrics()}

    def offline(self, interval: int, observed: np.ndarray) -> tuple[float, int, int]:
        """PPO on the learned model (--offline-steps; half the episodes branched
        from observed levels, MBPO), on a stream of its own, restored after."""
        cfg = self.cfg
        if not cfg.offline_steps:
            return float("nan"), 0, 0
        seed = offline_seed(cfg.seed, interval)
        env = LearnedModelEnv(self.model, self.demand, MODEL.learn_terminal_band,
                              cfg.offline_envs, max_episode_steps=cfg.steps_per_interval,
                              seed=seed, starts=observed, branch_fraction=cfg.branch_fraction,
                              branch_steps=cfg.branch_steps)
        online_config, generator_state = self.ppo.config, self.ppo.generator.get_state()
        self.ppo.generator.manual_seed(seed)
        self.ppo.config = dataclasses.replace(online_config, minibatch_size=cfg.offline_minibatch)
        try:
            stats, rew, _ = train_on_env(self.ppo, env, cfg.offline_steps, cfg.offline_rollout)
        finally:
            self.ppo.config = online_config
            self.ppo.generator.set_state(generator_state)
        return rew, len(stats), 0

    def model_state(self) -> dict[str, Any]:
        return {"learned_model": self.model.state_dict(), "demand": self.demand,
                "added": self.added, "stuck": self.stuck.state_dict()["stuck"],
                "stuck_valves": self.stuck.state_dict()}

    def load_model_state(self, state: dict[str, Any]) -> None:
        missing = sorted({"learned_model", "demand", "added"} - set(state))
        if missing:
            raise CheckpointError(f"checkpoint lacks the agent's {', '.join(missing)}")
        self.model.load_state_dict(state["learned_model"])
        self.demand, self.added = float(state["demand"]), int(state["added"])
        self.stuck.load_state_dict(state.get("stuck_valves", {"stuck": state.get("stuck", {})}))
