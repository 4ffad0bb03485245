"""A world model learned online, one step at a time: x' - x = W^T phi(x, u).

phi is a fixed set of generic features of the six levels and six valves: a
constant, the 12 inputs (scaled to [-1, 1]), their 66 pairwise products and
``features`` random ReLU features ``max(0, a . z + b)`` (a, b drawn once from
the seed). Nothing of the tanks' physics is in it: no pumps, no conduit, no
parameters. W is fitted by Bayesian linear regression with exponential
forgetting:

    W = (G + ridge I)^-1 (M + ridge W_prior),
    G <- forget G + phi phi^T,  M <- forget M + phi (x' - x)^T / SCALE

after every observed step, so a step ``k`` steps old weighs ``forget**k``.
The prior ``W_prior`` is the fit at the last :meth:`settle` (the end of the
previous interval): it holds what the recent data say nothing about (a
valve setting not tried since the plant changed), as a Gaussian prior does,
while the data of the plant as it is now take over where they exist.

Why this and not the MLP of :mod:`ftc.learning.world_model`: the fit is
exact and cheap (a 335 x 335 solve every ``solve_every`` steps), so the model
follows the plant within an interval instead of after it, and a pump that
dies mid-interval is in the model a few dozen steps later (docs/controller.md
has the measurements).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ftc.common.constants import NUM_TANKS, TANK_HEIGHT
from ftc.common.errors import CheckpointError

SCALE = 0.05  # m per step: the order of a level's change, so the targets are O(1)
INPUTS = 2 * NUM_TANKS


class FeatureModel:
    """Levels (..., 6) m and valves (..., 6) {0, 1} -> next levels; see the module."""

    def __init__(self, features: int = 256, forget: float = 0.998, ridge: float = 1e-2,
                 seed: int = 0, solve_every: int = 8) -> None:
        rng = np.random.default_rng(seed)
        self.proj = rng.normal(0.0, 1.5 / np.sqrt(INPUTS), (INPUTS, features))
        self.offset = rng.uniform(-1.0, 1.0, features)
        self.pairs = np.triu_indices(INPUTS, 1)
        self.size = 1 + INPUTS + features + len(self.pairs[0])
        self.forget, self.ridge, self.solve_every = forget, ridge, solve_every
        self.gram = np.zeros((self.size, self.size))
        self.moment = np.zeros((self.size, NUM_TANKS))
        self.weights = np.zeros((self.size, NUM_TANKS))
        self.prior = np.zeros((self.size, NUM_TANKS))
        self.pending = 0  # steps added since the last solve

    def features(self, level: np.ndarray, valves: np.ndarray) -> np.ndarray:
        """phi (..., size) of levels (..., 6) and valves (..., 6)."""
        z = np.concatenate([2.0 * np.asarray(level, np.float64) / TANK_HEIGHT - 1.0,
                            2.0 * np.asarray(valves, np.float64) - 1.0], axis=-1)
        return np.concatenate([np.ones(z.shape[:-1] + (1,)), z,
                               np.maximum(z @ self.proj + self.offset, 0.0),
                               z[..., self.pairs[0]] * z[..., self.pairs[1]]], axis=-1)

    def fit(self, level: np.ndarray, valves: np.ndarray, next_level: np.ndarray) -> None:
        """Fit afresh on rows (N, 6) each (the nominal data set); the fit becomes the prior."""
        f = self.features(level, valves)
        self.gram = f.T @ f
        self.moment = f.T @ ((np.asarray(next_level) - level) / SCALE)
        self.prior = np.zeros_like(self.prior)
        self.settle()

    def add(self, level: np.ndarray, valves: np.ndarray, next_level: np.ndarray) -> np.ndarray:
        """One observed step (each (6,)): older ones fade by ``forget``. Returns the
        prediction's error on it (6,) m, made before it was learned."""
        f = self.features(level, valves)
        error = np.clip(level + f @ self.weights * SCALE, 0.0, TANK_HEIGHT) - next_level
        self.gram *= self.forget
        self.moment *= self.forget
        self.gram += np.outer(f, f)
        self.moment += np.outer(f, (np.asarray(next_level) - level) / SCALE)
        self.pending += 1
        if self.pending >= self.solve_every:
            self.solve()
        return error

    def solve(self) -> None:
        self.weights = np.linalg.solve(self.gram + self.ridge * np.eye(self.size),
                                       self.moment + self.ridge * self.prior)
        self.pending = 0

    def settle(self) -> None:
        """Solve on every step seen; the fit becomes the prior of later ones."""
        self.solve()
        self.prior = self.weights.copy()

    def predict(self, level: np.ndarray, valves: np.ndarray) -> np.ndarray:
        """Next levels (..., 6) m, within [0, tank height]."""
        change = self.features(level, valves) @ self.weights * SCALE
        return np.clip(level + change, 0.0, TANK_HEIGHT)

    # -- persistence -------------------------------------------------------------
    ARRAYS = ("gram", "moment", "weights", "prior")

    def state_dict(self) -> dict[str, Any]:
        return {**{k: getattr(self, k).tolist() for k in self.ARRAYS}, "pending": self.pending}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for k in self.ARRAYS:
            value = np.asarray(state[k], np.float64)
            if value.shape != getattr(self, k).shape:
                raise CheckpointError(f"learned model's {k}: shape {value.shape} in the "
                                      f"checkpoint, {getattr(self, k).shape} here")
            setattr(self, k, value)
        self.pending = int(state["pending"])
