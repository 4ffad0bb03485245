"""PPO for six binary valves: the update and the algorithm (config and
actor-critic: :mod:`ftc.learning.ppo_policy`; buffer: :mod:`ftc.learning.buffer`).

Responsibilities are split as in Stable-Baselines3, and each part reads top to
bottom as in CleanRL:

* :class:`PPOConfig`     every hyperparameter, with help text and the source of its
                         default (ppo_policy.py)
* :class:`ActorCritic`   the networks and the Bernoulli-per-valve distribution
                         (ppo_policy.py)
* :class:`RolloutBuffer` preallocated (T, N, ...) storage; GAE and returns (buffer.py)
* :func:`ppo_update`     epochs x minibatches of the clipped-surrogate update
* :class:`PPO`           the algorithm: owns policy, optimiser and generator;
                         acts, fills a buffer, updates

The same code drives the real plant (N = 1 environment) and batched rollouts
on the learned world model (N environments at once).

Episode ends follow the plant: *termination* (fuel exhausted) is not
bootstrapped; *truncation* (interval boundary, model rollout cut short) is
bootstrapped from the critic's value of the final observation.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import nn

from ftc.learning.buffer import RolloutBatch, RolloutBuffer
from ftc.learning.ppo_numpy import NumpyActor, numpy_ppo_update
from ftc.learning.ppo_policy import ActorCritic, PPOConfig, UpdateStats

__all__ = ["PPO", "ActorCritic", "PPOConfig", "UpdateStats", "clipped_surrogate_loss",
           "explained_variance", "ppo_update"]


# --------------------------------------------------------------------------
# The update
# --------------------------------------------------------------------------

def clipped_surrogate_loss(new_logprob: torch.Tensor, old_logprob: torch.Tensor,
                           advantages: torch.Tensor, clip_coef: float) -> torch.Tensor:
    """PPO's clipped surrogate, as a loss to minimise (scalar):
    mean(max(-A r, -A clip(r, 1 - eps, 1 + eps))), r = exp(new - old)."""
    ratio = (new_logprob - old_logprob).exp()
    return torch.max(-advantages * ratio,
                     -advantages * ratio.clamp(1.0 - clip_coef, 1.0 + clip_coef)).mean()


def explained_variance(pred: torch.Tensor, target: torch.Tensor) -> float:
    """1 - Var(target - pred) / Var(target); nan when the target is constant."""
    var = target.var(unbiased=False)
    return float("nan") if var == 0 else float(1.0 - (target - pred).var(unbiased=False) / var)


def ppo_update(policy: ActorCritic, optimizer: torch.optim.Optimizer, batch: RolloutBatch,
               config: PPOConfig, generator: torch.Generator | None = None) -> UpdateStats:
    """config.update_epochs passes over the batch in shuffled minibatches of
    config.minibatch_size; stops early when approx-KL exceeds config.target_kl."""
    B = batch.obs.shape[0]
    mb = min(config.minibatch_size, B)
    kls, clipfracs, steps = [], [], 0
    pg_loss = v_loss = entropy_mean = torch.zeros(())
    for _epoch in range(config.update_epochs):
        order = torch.randperm(B, generator=generator)
        for start in range(0, B, mb):
            idx = order[start:start + mb]
            logprob, entropy, value = policy.evaluate_actions(batch.obs[idx], batch.actions[idx])
            log_ratio = logprob - batch.logprobs[idx]
            with torch.no_grad():
                ratio = log_ratio.exp()
                kls.append(float(((ratio - 1.0) - log_ratio).mean()))
                clipfracs.append(float(((ratio - 1.0).abs() > config.clip_coef).float().mean()))

            adv = batch.advantages[idx]
            if config.norm_adv and adv.numel() > 1:
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            pg_loss = clipped_surrogate_loss(logprob, batch.logprobs[idx], adv, config.clip_coef)

            target = batch.returns[idx]
            if config.clip_vloss:
                clipped = batch.values[idx] + (value - batch.values[idx]).clamp(
                    -config.clip_coef, config.clip_coef)
                v_loss = 0.5 * torch.max((value - target) ** 2, (clipped - target) ** 2).mean()
            else:
                v_loss = 0.5 * ((value - target) ** 2).mean()
            entropy_mean = entropy.mean()
            loss = pg_loss - config.ent_coef * entropy_mean + config.vf_coef * v_loss

            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(policy.parameters(), config.max_grad_norm)
            optimizer.step()
            steps += 1
        if config.target_kl is not None and np.mean(kls[-math.ceil(B / mb):]) > config.target_kl:
            break

    with torch.no_grad():
        logits, values = policy(batch.obs)
        open_fraction = float(torch.sigmoid(logits).mean())
        _, entropy_all = policy.log_prob_entropy(logits, batch.actions)
    return UpdateStats(
        policy_loss=float(pg_loss.detach()), value_loss=float(v_loss.detach()),
        entropy=float(entropy_all.mean()), approx_kl=float(np.mean(kls)),
        clipfrac=float(np.mean(clipfracs)),
        explained_variance=explained_variance(batch.values, batch.returns),
        open_fraction=open_fraction, gradient_steps=steps)


# --------------------------------------------------------------------------
# The algorithm
# --------------------------------------------------------------------------

class PPO:
    """Owns the policy, its optimiser and the torch generator used for sampling
    actions and shuffling minibatches, so a run is reproducible from its seed and
    resumable from :meth:`state_dict`."""

    def __init__(self, config: PPOConfig = PPOConfig(), seed: int = 0) -> None:
        self.config = config
        torch.manual_seed(seed)  # network initialisation
        self.policy = ActorCritic(config.trunk_sizes, config.head_sizes)
        self.generator = torch.Generator().manual_seed(seed)
        self.optimizer = self.new_optimizer()
        self._actor: NumpyActor | None = None  # NumPy views of self.policy (engine numpy)
        self._actor_of: ActorCritic | None = None

    def new_optimizer(self) -> torch.optim.Adam:
        return torch.optim.Adam(self.policy.parameters(), lr=self.config.learning_rate, eps=1e-5)

    def reset_optimizer(self) -> None:
        """A fresh optimiser state (at the start of adaptation: it narrows the spread
        across seeds)."""
        self.optimizer = self.new_optimizer()

    def act(self, obs: torch.Tensor, deterministic: bool = False
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Actions (N, 6), log-probs (N,), values (N,) for obs (N, 6)."""
        if self.config.engine == "numpy" and not obs.requires_grad:
            if self._actor is None or self._actor_of is not self.policy or self._actor.stale():
                self._actor, self._actor_of = NumpyActor(self.policy), self.policy
            return self._actor.act(obs, self.generator, deterministic)
        return self.policy.act(obs, self.generator, deterministic)

    @torch.no_grad()
    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.policy.value(obs)

    def update(self, buffer: RolloutBuffer, last_values: torch.Tensor) -> UpdateStats:
        """GAE on the buffer, then the PPO update; leaves the buffer emptied."""
        c = self.config
        buffer.compute_returns_and_advantages(last_values, c.gamma, c.gae_lambda, c.reward_scale)
        if c.engine == "numpy" and not c.clip_vloss:
            stats = numpy_ppo_update(self.policy, self.optimizer, buffer.batch(), c,
                                     self.generator, UpdateStats)
        else:
            stats = ppo_update(self.policy, self.optimizer, buffer.batch(), c, self.generator)
        buffer.reset()
        return stats

    def state_dict(self) -> dict[str, Any]:
        """Tensors and plain containers only (loadable with weights_only=True)."""
        return {"policy": self.policy.state_dict(), "optimizer": self.optimizer.state_dict(),
                "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.policy.load_state_dict(state["policy"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
