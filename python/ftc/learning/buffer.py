"""Preallocated rollout storage for PPO, with GAE advantages computed
backwards (truncations bootstrapped from the critic, terminations not)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from ftc.common.constants import NUM_TANKS, NUM_VALVES  # noqa: F401 (NUM_VALVES: read from here)

OBS_DIM = NUM_TANKS     # the six published levels


class RolloutBatch(NamedTuple):
    """Flattened rollout, B = T * N samples."""

    obs: torch.Tensor         # (B, 6) levels, m
    actions: torch.Tensor     # (B, 6) valves in {0, 1}
    logprobs: torch.Tensor    # (B,) log-prob under the behaviour policy
    values: torch.Tensor      # (B,) critic value when acting (scaled units)
    advantages: torch.Tensor  # (B,) GAE advantages
    returns: torch.Tensor     # (B,) critic targets = advantages + values


class RolloutBuffer:
    """Preallocated storage for T steps of N environments, (T, N, ...) tensors.

    Per step t: the observation acted on, the action, its log-prob, the critic
    value, the (unscaled) reward received, whether the step ended the episode by
    termination or truncation, and for truncated steps the critic value of the
    final observation (the bootstrap). After T steps, call
    :meth:`compute_returns_and_advantages` with the value of the observation
    that follows the last step.
    """

    def __init__(self, num_steps: int, num_envs: int) -> None:
        self.num_steps, self.num_envs = num_steps, num_envs
        shape = (num_steps, num_envs)
        self.obs = torch.zeros(shape + (OBS_DIM,))
        self.actions = torch.zeros(shape + (NUM_VALVES,))
        self.logprobs = torch.zeros(shape)
        self.values = torch.zeros(shape)
        self.rewards = torch.zeros(shape)
        self.terminals = torch.zeros(shape, dtype=torch.bool)
        self.truncations = torch.zeros(shape, dtype=torch.bool)
        self.truncation_values = torch.zeros(shape)
        self.advantages = torch.zeros(shape)
        self.returns = torch.zeros(shape)
        self.pos = 0

    @property
    def full(self) -> bool:
        return self.pos == self.num_steps

    def reset(self) -> None:
        self.pos = 0

    def add(self, obs: torch.Tensor, actions: torch.Tensor, logprobs: torch.Tensor,
            values: torch.Tensor, rewards: torch.Tensor, terminals: torch.Tensor,
            truncations: torch.Tensor, truncation_values: torch.Tensor | None = None) -> None:
        """Store one step of all N envs: obs (N, 6), actions (N, 6), the rest (N,).

        truncation_values: critic value of the final observation of envs whose
        episode was truncated at this step (ignored elsewhere); None: zeros.
        """
        if self.full:
            raise IndexError("rollout buffer is full")
        t = self.pos
        self.obs[t] = obs
        self.actions[t] = actions
        self.logprobs[t] = logprobs
        self.values[t] = values
        self.rewards[t] = torch.as_tensor(rewards, dtype=torch.float32)
        self.terminals[t] = torch.as_tensor(terminals, dtype=torch.bool)
        self.truncations[t] = torch.as_tensor(truncations, dtype=torch.bool)
        self.truncation_values[t] = (0.0 if truncation_values is None
                                     else torch.as_tensor(truncation_values, dtype=torch.float32))
        self.pos += 1

    def compute_returns_and_advantages(self, last_values: torch.Tensor, gamma: float,
                                       gae_lambda: float, reward_scale: float = 1.0) -> None:
        """GAE backwards over the stored steps.

        last_values (N,): critic value of the observation after the last stored
        step (used only where that step did not end the episode).

        delta_t = s * r_t + gamma * V_next_t - V_t, with V_next_t = 0 after a
        termination, the final observation's value after a truncation, else the
        value of the next stored observation; the GAE recursion is cut at every
        episode end. returns = advantages + values.
        """
        T = self.pos
        # in NumPy on views of the tensors (the same float32 operations, one at
        # a time as torch ran them, so the same bits; no per-op dispatch)
        values, rewards = self.values.numpy(), self.rewards.numpy()
        terminals, truncations = self.terminals.numpy(), self.truncations.numpy()
        truncation_values, advantages = self.truncation_values.numpy(), self.advantages.numpy()
        last = np.asarray(last_values.detach().numpy(), dtype=np.float32)
        last_gae = np.zeros(self.num_envs, np.float32)
        for t in reversed(range(T)):
            next_values = last if t == T - 1 else values[t + 1]
            next_values = np.where(truncations[t], truncation_values[t], next_values)
            next_values = np.where(terminals[t], np.float32(0.0), next_values)
            continues = (~(terminals[t] | truncations[t])).astype(np.float32)
            delta = reward_scale * rewards[t] + gamma * next_values - values[t]
            last_gae = delta + gamma * gae_lambda * continues * last_gae
            advantages[t] = last_gae
        self.returns[:T] = self.advantages[:T] + self.values[:T]

    def batch(self) -> RolloutBatch:
        """The stored steps flattened to (T * N, ...)."""
        T = self.pos
        return RolloutBatch(
            obs=self.obs[:T].reshape(-1, OBS_DIM),
            actions=self.actions[:T].reshape(-1, NUM_VALVES),
            logprobs=self.logprobs[:T].reshape(-1),
            values=self.values[:T].reshape(-1),
            advantages=self.advantages[:T].reshape(-1),
            returns=self.returns[:T].reshape(-1))
