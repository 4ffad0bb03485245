"""Behaviour cloning of a teacher's valve decisions into the PPO policy (the
actor's Bernoulli logits), for guided policy search: a planner labels states,
the policy learns to act as it does, PPO then goes on from there."""

from __future__ import annotations

import numpy as np
import torch

from ftc.learning.ppo import PPO


def distill(ppo: PPO, states: torch.Tensor, actions: torch.Tensor, *, epochs: int = 30,
            minibatch: int = 128, lr: float = 1e-3, seed: int = 0,
            stop_loss: float = 0.0, weights: torch.Tensor | None = None) -> dict[str, float]:
    """Fit the policy's valve-open probabilities to ``actions`` (N, 6) in {0, 1}
    at ``states`` (N, 6) by binary cross-entropy (a fresh Adam; PPO's own
    optimiser state is kept), with the PPO's engine, for ``epochs`` epochs or
    until an epoch's mean minibatch loss is below ``stop_loss`` (0: never).
    ``weights`` (N,), if given, weight each row's loss (a minibatch's loss is
    its weighted mean: rows repeated k times can be given once with weight k,
    :func:`distinct`). Returns the final loss, the epochs run and the share of
    valve decisions the deterministic policy (open iff p > 0.5) now agrees on
    (weighted)."""
    loss, ran = ppo.engine.distill(ppo.policy, states, actions, epochs=epochs,
                                   minibatch=minibatch, lr=lr,
                                   max_grad_norm=ppo.config.max_grad_norm,
                                   generator=torch.Generator().manual_seed(seed),
                                   stop_loss=stop_loss, weights=weights)
    return {"distill_loss": loss, "distill_epochs": ran,
            "distill_agreement": _agreement(ppo, states, actions, weights)}


@torch.no_grad()
def _agreement(ppo: PPO, states: torch.Tensor, actions: torch.Tensor,
               weights: torch.Tensor | None = None) -> float:
    """Share of valve decisions the deterministic policy (open iff p > 0.5) agrees
    on (rows weighted by ``weights`` if given)."""
    logits, _ = ppo.policy(states)
    agree = ((logits > 0).float() == actions).float().mean(1)
    if weights is None:
        return float(agree.mean())
    return float((agree * weights).sum() / weights.sum())


def distinct(states: np.ndarray, actions: np.ndarray
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The distinct (state, action) rows of ``states`` (N, 6) and ``actions`` (N, 6)
    and how often each occurs, as float32 tensors for :func:`distill`'s
    ``weights``: the same objective in fewer rows (sorted, so deterministic)."""
    rows, counts = np.unique(np.concatenate([states, actions], axis=1), axis=0,
                             return_counts=True)
    k = states.shape[1]
    as32 = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32)  # noqa: E731
    return as32(rows[:, :k]), as32(rows[:, k:]), as32(counts)
