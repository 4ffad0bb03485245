"""The one rollout collector: how PPO turns environment steps into updates,
for the real plant (N = 1, stepped by the interval runner) and for batched
simulated envs (nominal core plants, world-model rollouts).

Every stored step carries the truncation bootstrap: where an episode was cut
off (interval boundary, model rollout cut short) the critic's value of the
final observation; a termination (fuel exhausted) is not bootstrapped.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import torch

from ftc.learning.buffer import RolloutBuffer
from ftc.learning.ppo import PPO, UpdateStats


class EnvStep(NamedTuple):
    """One batched step of a simulated env (N = num_envs).

    obs:       (N, 6) levels to act on next, m: after auto-reset for envs that finished
    reward:    (N,) reward of the step
    terminal:  (N,) bool, fuel exhausted (do not bootstrap)
    truncated: (N,) bool, cut off and not terminal (bootstrap)
    final_obs: (N, 6) levels after the step before any reset, m (bootstrap from these)
    """

    obs: torch.Tensor
    reward: torch.Tensor
    terminal: torch.Tensor
    truncated: torch.Tensor
    final_obs: torch.Tensor


class RolloutCollector:
    """Stores what ``ppo`` did in ``num_envs`` envs for ``num_steps`` steps,
    then updates it. Use: ``act`` -> step the envs -> ``add`` -> when ``full``,
    ``update(next_obs)``."""

    def __init__(self, ppo: PPO, num_steps: int, num_envs: int) -> None:
        self.ppo = ppo
        self.buffer = RolloutBuffer(num_steps, num_envs)

    @property
    def full(self) -> bool:
        return self.buffer.full

    def act(self, obs: torch.Tensor, deterministic: bool = False
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return self.ppo.act(obs, deterministic)

    def add(self, obs: torch.Tensor, actions: torch.Tensor, logprobs: torch.Tensor,
            values: torch.Tensor, reward: torch.Tensor, terminal: torch.Tensor,
            truncated: torch.Tensor, final_obs: torch.Tensor) -> None:
        """One step of every env; ``truncated`` must exclude terminal steps."""
        bootstrap = (torch.where(truncated, self.ppo.value(final_obs), 0.0)
                     if bool(truncated.any()) else None)
        self.buffer.add(obs, actions, logprobs, values, reward, terminal, truncated, bootstrap)

    def update(self, next_obs: torch.Tensor) -> UpdateStats:
        """GAE (bootstrapped from the value of ``next_obs``, the observations the
        envs act on next) and the PPO update; empties the buffer."""
        return self.ppo.update(self.buffer, self.ppo.value(next_obs))


def train_on_env(ppo: PPO, env: Any, total_steps: int, rollout: int,
                 stop: Callable[[UpdateStats, torch.Tensor], bool] | None = None
                 ) -> tuple[list[UpdateStats], float, int]:
    """PPO on a batched env (reset() -> (N, 6); step(a) -> :class:`EnvStep`) for
    up to ``total_steps`` env steps, updating every ``rollout`` steps per env;
    stops early when ``stop(stats, obs)`` is true (obs: (rollout, N, 6) the
    observations of the update's rollout).

    Returns the update stats, the mean reward per step and the steps taken.
    """
    n = env.num_envs
    collector = RolloutCollector(ppo, rollout, n)
    obs = env.reset()
    stats: list[UpdateStats] = []
    reward_sum, steps = 0.0, 0
    while steps + rollout * n <= max(total_steps, rollout * n):
        for _ in range(rollout):
            actions, logprobs, values = collector.act(obs)
            s = env.step(actions)
            collector.add(obs, actions, logprobs, values, s.reward, s.terminal, s.truncated,
                          s.final_obs)
            reward_sum += float(s.reward.sum())
            obs = s.obs
        steps += rollout * n
        rollout_obs = collector.buffer.obs
        stats.append(collector.update(obs))
        if stop is not None and stop(stats[-1], rollout_obs):
            break
        if steps >= total_steps:
            break
    return stats, reward_sum / max(steps, 1), steps
