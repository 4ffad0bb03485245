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
* :class:`TorchEngine`   acting, that update and behaviour cloning in torch: the
                         reference engine (the fast one: ppo_native.py)
* :class:`PPO`           the algorithm: owns policy, optimiser and generator;
                         acts, fills a buffer, updates, through its config's engine

The same code drives the real plant (N = 1 environment) and batched rollouts
on the learned world model (N environments at once).

Episode ends follow the plant: *termination* (fuel exhausted) is not
bootstrapped; *truncation* (interval boundary, model rollout cut short) is
bootstrapped from the critic's value of the final observation.
"""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
import torch
from torch import nn

from ftc.learning.buffer import RolloutBatch, RolloutBuffer
from ftc.learning.ppo_native import NativeEngine
from ftc.learning.ppo_policy import (ActorCritic, PPOConfig, PPOEngine, UpdateStats,
                                     explained_variance)

__all__ = ["PPO", "ActorCritic", "PPOConfig", "PPOEngine", "TorchEngine", "UpdateStats",
           "clipped_surrogate_loss", "explained_variance", "ppo_update"]


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


def torch_distill(policy: ActorCritic, states: torch.Tensor, actions: torch.Tensor, *,
                  epochs: int, minibatch: int, lr: float, max_grad_norm: float,
                  generator: torch.Generator, stop_loss: float = 0.0,
                  weights: torch.Tensor | None = None) -> tuple[float, int]:
    """Behaviour cloning (:meth:`PPOEngine.distill`) with autograd: binary
    cross-entropy of the logits against ``actions`` (a minibatch's loss is the
    mean, or with ``weights`` the weighted mean over rows of the mean over
    valves), the global norm clip, a fresh Adam (eps 1e-5); it stops after an
    epoch whose mean minibatch loss is below ``stop_loss``."""
    optimizer = torch.optim.Adam(policy.parameters(), lr=lr, eps=1e-5)
    loss_fn = nn.BCEWithLogitsLoss(reduction="mean" if weights is None else "none")
    n = len(states)
    loss = torch.tensor(float("nan"))
    ran = 0
    while ran < epochs:
        order = torch.randperm(n, generator=generator)
        total = 0.0
        for start in range(0, n, minibatch):
            idx = order[start:start + minibatch]
            logits, _ = policy(states[idx])
            loss = loss_fn(logits, actions[idx])
            if weights is not None:
                w = weights[idx]
                loss = (loss.mean(1) * w).sum() / w.sum()
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(policy.parameters(), max_grad_norm)
            optimizer.step()
            total += float(loss.detach())
        ran += 1
        if total / -(-n // minibatch) < stop_loss:
            break
    return float(loss.detach()), ran


class TorchEngine:
    """:class:`PPOEngine` with autograd and torch.optim.Adam: the reference."""

    name = "torch"

    def act(self, policy: ActorCritic, obs: torch.Tensor, generator: torch.Generator | None,
            deterministic: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return policy.act(obs, generator, deterministic)

    update = staticmethod(ppo_update)
    distill = staticmethod(torch_distill)


ENGINE_TYPES: dict[str, type] = {"torch": TorchEngine, "native": NativeEngine}


# --------------------------------------------------------------------------
# The algorithm
# --------------------------------------------------------------------------

class PPO:
    """Owns the policy, its optimiser and the torch generator used for sampling
    actions and shuffling minibatches, so a run is reproducible from its seed and
    resumable from :meth:`state_dict`; computes through the engine its config
    names (which may change between phases: pretraining runs torch's)."""

    def __init__(self, config: PPOConfig = PPOConfig(), seed: int = 0) -> None:
        config.validate()
        self.config = config
        torch.manual_seed(seed)  # network initialisation
        self.policy = ActorCritic(config.trunk_sizes, config.head_sizes)
        self.generator = torch.Generator().manual_seed(seed)
        self.optimizer = self.new_optimizer()
        self._engines: dict[str, PPOEngine] = {}

    @property
    def engine(self) -> PPOEngine:
        name = self.config.engine
        if name not in self._engines:
            self._engines[name] = ENGINE_TYPES[name]()
        return self._engines[name]

    def new_optimizer(self) -> torch.optim.Adam:
        return torch.optim.Adam(self.policy.parameters(), lr=self.config.learning_rate, eps=1e-5)

    def reset_optimizer(self) -> None:
        """A fresh optimiser state (at the start of adaptation: it narrows the spread
        across seeds)."""
        self.optimizer = self.new_optimizer()

    def act(self, obs: torch.Tensor, deterministic: bool = False
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Actions (N, 6), log-probs (N,), values (N,) for obs (N, 6)."""
        return self.engine.act(self.policy, obs, self.generator, deterministic)

    @torch.no_grad()
    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.policy.value(obs)

    def update(self, buffer: RolloutBuffer, last_values: torch.Tensor) -> UpdateStats:
        """GAE on the buffer, then the PPO update; leaves the buffer emptied."""
        c = self.config
        buffer.compute_returns_and_advantages(last_values, c.gamma, c.gae_lambda, c.reward_scale)
        stats = self.engine.update(self.policy, self.optimizer, buffer.batch(), c, self.generator)
        buffer.reset()
        return stats

    def clone(self) -> "PPO":
        """An independent copy (policy, optimiser state, generator) that can
        update on another thread while this one acts."""
        other = object.__new__(PPO)
        other.config, other._engines = self.config, {}
        other.policy = copy.deepcopy(self.policy)
        other.generator = torch.Generator()
        other.generator.set_state(self.generator.get_state())
        other.optimizer = other.new_optimizer()
        other.optimizer.load_state_dict(copy.deepcopy(self.optimizer.state_dict()))
        return other

    def state_dict(self) -> dict[str, Any]:
        """Tensors and plain containers only (loadable with weights_only=True)."""
        return {"policy": self.policy.state_dict(), "optimizer": self.optimizer.state_dict(),
                "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.policy.load_state_dict(state["policy"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
