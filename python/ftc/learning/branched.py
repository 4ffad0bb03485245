"""Where the episodes of a simulated env start: full tanks, or (MBPO's
branched rollouts) a level actually observed on the plant, cut short. Shared
by the envs on a model of the plant (:class:`ftc.learning.physics_env.PhysicsEnv`,
``ppo-learned``'s env on its learned model)."""

from __future__ import annotations

import numpy as np
import torch

from ftc.common.constants import NUM_TANKS, TANK_HEIGHT


class BranchedStarts:
    """N envs' levels, step counts and step limits. An episode starts from full
    tanks (cut after ``max_episode_steps``) or, with probability
    ``branch_fraction``, from a level drawn from ``starts`` (N, 6) (cut after
    ``branch_steps``)."""

    def __init__(self, num_envs: int, *, max_episode_steps: int, starts: np.ndarray | None,
                 branch_fraction: float, branch_steps: int, seed: int) -> None:
        self.num_envs = num_envs
        self.max_episode_steps = max_episode_steps
        self.starts = None if starts is None or len(starts) == 0 else np.asarray(starts, float)
        self.branch_fraction = branch_fraction if self.starts is not None else 0.0
        self.branch_steps = branch_steps
        self.rng = np.random.default_rng(seed)
        self.level = np.full((num_envs, NUM_TANKS), TANK_HEIGHT)
        self.steps = np.zeros(num_envs, int)
        self.limit = np.full(num_envs, max_episode_steps)

    def _start(self, i: int) -> None:
        if self.branch_fraction and self.rng.random() < self.branch_fraction:
            self.level[i] = self.starts[self.rng.integers(len(self.starts))]
            self.limit[i] = self.branch_steps
        else:
            self.level[i] = TANK_HEIGHT
            self.limit[i] = self.max_episode_steps
        self.steps[i] = 0

    def reset(self) -> torch.Tensor:
        for i in range(self.num_envs):
            self._start(i)
        return torch.as_tensor(self.level, dtype=torch.float32).clone()
