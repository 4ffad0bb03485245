"""N in-process nominal plants (the C++ core, no LCM) as one batched env, for
nominal pretraining: the same step interface as
:class:`ftc.learning.model_env.ModelEnv`."""

from __future__ import annotations

import numpy as np
import torch

from ftc.common.constants import NUM_TANKS
from ftc.learning.rollout import EnvStep
from ftc.plant.link import CorePlant
from ftc.plant.reward import reward


class VecCorePlant:
    """reset() -> obs (N, 6); step(actions (N, 6)) -> EnvStep, finished envs reset
    automatically. Episodes are the plant's own (terminal when the fuel is out,
    truncated at its interval boundary)."""

    def __init__(self, num_envs: int, seed: int, scenario: str | None = None) -> None:
        self.plants = [CorePlant(scenario, seed + i) for i in range(num_envs)]
        self.num_envs = num_envs
        self.levels = [np.ones(NUM_TANKS)] * num_envs
        self.errors = 0  # steps the core refused (see step)

    def reset(self) -> torch.Tensor:
        self.levels = [p.reset().level for p in self.plants]
        return torch.tensor(np.stack(self.levels), dtype=torch.float32)

    def step(self, actions: torch.Tensor) -> EnvStep:
        """A step the core refuses (it raises, e.g. on chattering) is counted in
        ``errors`` and ends that episode as a truncation at the last good state
        (reward 0): one bad simulated step must not end a pretraining run, and
        the count is reported so it cannot go unnoticed."""
        u = actions.numpy().astype(np.int8)
        obs, final, rew, term, trunc = [], [], [], [], []
        for i, (plant, a) in enumerate(zip(self.plants, u)):
            try:
                o = plant.step(a)
                level, r, t, tr = o.level, float(reward(o.level, a)), o.terminal, o.truncated
            except RuntimeError:
                self.errors += 1
                level, r, t, tr = self.levels[i], 0.0, False, True
            final.append(level)
            rew.append(r)
            term.append(t)
            trunc.append(tr and not t)
            self.levels[i] = plant.reset().level if (t or tr) else level
            obs.append(self.levels[i])

        def stack(x: list) -> torch.Tensor:
            return torch.tensor(np.stack(x), dtype=torch.float32)

        return EnvStep(stack(obs), torch.tensor(rew), torch.tensor(term), torch.tensor(trunc),
                       stack(final))
