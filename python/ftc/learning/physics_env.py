"""N plants simulated by the C++ core with given (identified) physical
parameters, stepped side by side: the offline env of ``ppo-robust``. The same
step interface as :class:`ftc.learning.model_env.ModelEnv`.

Episodes start from full tanks or, with probability ``branch_fraction``, from
a level actually observed on the plant (``starts``), cut after
``branch_steps`` steps: short branched rollouts from real states (MBPO), so
the policy trains where the plant is, not only on the full-tank episodes.
Full-tank episodes end by the plant's rule (terminal when the volume is below
one step of demand + 1e-6 m^3) or are cut after ``max_episode_steps``.
Valves known stuck (``stuck``: valve -> state) move fuel as they are stuck,
whatever the action; the reward charges the action (the commanded valves), as
the plant's runner does.
"""

from __future__ import annotations

import numpy as np
import torch

from ftc.common.constants import NUM_TANKS, TERMINAL_TOLERANCE
from ftc.learning.branched import BranchedStarts
from ftc.learning.rollout import EnvStep
from ftc.plant.reward import AREAS, reward


class PhysicsEnv(BranchedStarts):
    def __init__(self, params: dict, num_envs: int, *, max_episode_steps: int = 512,
                 starts: np.ndarray | None = None, branch_fraction: float = 0.0,
                 branch_steps: int = 64, seed: int = 0, rtol: float = 1e-6,
                 atol: float = 1e-8, stuck: dict[int, int] | None = None) -> None:
        from ftc import _core  # native: the plant's integrator

        self.rollout = _core.BatchRollout(rtol=rtol, atol=atol)
        self.params = params
        self.stuck = dict(stuck or {})
        super().__init__(num_envs, max_episode_steps=max_episode_steps, starts=starts,
                         branch_fraction=branch_fraction, branch_steps=branch_steps, seed=seed)
        self.demand = float(np.sum(params["demand"]))
        self.errors = 0  # steps the integrator refused (ended as truncations)

    def step(self, actions: torch.Tensor) -> EnvStep:
        u = actions.numpy().astype(np.int64)
        applied = u.copy()
        for k, state in self.stuck.items():
            applied[:, k] = state
        final = np.empty_like(self.level)
        rew = np.zeros(self.num_envs)
        term = np.zeros(self.num_envs, bool)
        trunc = np.zeros(self.num_envs, bool)
        for i in range(self.num_envs):
            try:
                r = self.rollout.run(self.level[i], applied[i].reshape(1, 1, NUM_TANKS),
                                     self.params, details=True)
                nxt = r["levels"][0, 0]
            except RuntimeError:  # ill-posed under these parameters: end the episode here
                self.errors += 1
                final[i], trunc[i] = self.level[i], True
                self._start(i)
                continue
            final[i] = nxt
            rew[i] = float(reward(nxt, u[i]))
            self.steps[i] += 1
            term[i] = float(AREAS @ nxt) < self.demand + TERMINAL_TOLERANCE
            trunc[i] = not term[i] and self.steps[i] >= self.limit[i]
            if term[i] or trunc[i]:
                self._start(i)
            else:
                self.level[i] = nxt
        f = torch.float32
        return EnvStep(torch.as_tensor(self.level, dtype=f).clone(), torch.as_tensor(rew, dtype=f),
                       torch.as_tensor(term), torch.as_tensor(trunc),
                       torch.as_tensor(final, dtype=f))
