"""The reward of plant-model.md ("Reward"): the one definition in Python.

r = (1 - |cg| / max|m|) * sigma - u_bar, with w_i = c_i * max(x'_i, 0),
cg the mass-weighted mean moment arm, sigma the mass-weighted standard
deviation of the signed arms about cg, and u_bar the fraction of open valves.
Works on single steps (shape (6,)) and on batches (shape (..., 6)), in numpy
or torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ftc.common.constants import EMPTY_VOLUME, NUM_TANKS

if TYPE_CHECKING:
    import torch

MOMENT_ARMS = np.array([-3.0, -2.0, -1.0, 1.0, 2.0, 3.0])  # m_i, tanks one unit apart
AREAS = np.ones(NUM_TANKS)  # c_i, m^2


class RewardTerms(NamedTuple):
    reward: np.ndarray
    cg: np.ndarray
    spread: np.ndarray
    activity: np.ndarray


def reward_terms(level_next: np.ndarray, valves: np.ndarray,
                 areas: np.ndarray = AREAS) -> RewardTerms:
    """Reward and its components for levels after a step, (..., 6) m, and valves (..., 6)."""
    x = np.asarray(level_next, dtype=np.float64)
    u = np.asarray(valves, dtype=np.float64)
    w = areas * np.maximum(x, 0.0)
    total = w.sum(axis=-1)
    nonempty = total >= EMPTY_VOLUME
    safe_total = np.where(nonempty, total, 1.0)
    cg = np.where(nonempty, (w * MOMENT_ARMS).sum(axis=-1) / safe_total, 0.0)
    var = (w * (MOMENT_ARMS - cg[..., None]) ** 2).sum(axis=-1) / safe_total
    spread = np.where(nonempty, np.sqrt(np.maximum(var, 0.0)), 0.0)
    activity = u.mean(axis=-1)
    r = (1.0 - np.abs(cg) / np.abs(MOMENT_ARMS).max()) * spread - activity
    return RewardTerms(r, cg, spread, activity)


def reward(level_next: np.ndarray, valves: np.ndarray) -> np.ndarray:
    """Reward only; float for one step, array for a batch."""
    return reward_terms(level_next, valves).reward


def reward_torch(level_next: "torch.Tensor", valves: "torch.Tensor") -> "torch.Tensor":
    """The same reward on torch tensors (..., 6), for batched model rollouts."""
    import torch

    arms = torch.as_tensor(MOMENT_ARMS, dtype=level_next.dtype, device=level_next.device)
    w = level_next.clamp_min(0.0)  # areas are 1 m^2
    total = w.sum(-1)
    nonempty = total >= EMPTY_VOLUME
    safe_total = torch.where(nonempty, total, torch.ones_like(total))
    cg = torch.where(nonempty, (w * arms).sum(-1) / safe_total, torch.zeros_like(total))
    var = (w * (arms - cg.unsqueeze(-1)) ** 2).sum(-1) / safe_total
    spread = torch.where(nonempty, var.clamp_min(0.0).sqrt(), torch.zeros_like(total))
    activity = valves.to(level_next.dtype).mean(-1)
    return (1.0 - cg.abs() / arms.abs().max()) * spread - activity
