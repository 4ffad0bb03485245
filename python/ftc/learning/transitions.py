"""Logged one-step transitions of the plant (what the world model trains on),
and the paper's random-valve data sets collected from any
:class:`~ftc.plant.PlantLink`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from ftc.common.constants import NUM_TANKS
from ftc.plant.link import CorePlant, PlantLink, PlantObservation



@dataclass
class Transitions:
    """Logged one-step transitions of the plant, as rows.

    level:      (T, 6) float64, levels before the step, m (as observed)
    valves:     (T, 6) int8, valves applied during the step, {0, 1}
    next_level: (T, 6) float64, levels after the step, m (as observed)
    episode:    (T,) int64, episode id; consecutive rows with the same id are
                consecutive steps of that episode (row t+1 starts where row t ended)
    """

    level: np.ndarray
    valves: np.ndarray
    next_level: np.ndarray
    episode: np.ndarray

    def __post_init__(self) -> None:
        self.level = np.asarray(self.level, dtype=np.float64).reshape(-1, NUM_TANKS)
        self.valves = np.asarray(self.valves, dtype=np.int8).reshape(-1, NUM_TANKS)
        self.next_level = np.asarray(self.next_level, dtype=np.float64).reshape(-1, NUM_TANKS)
        self.episode = np.asarray(self.episode, dtype=np.int64).reshape(-1)
        n = len(self.level)
        if not (len(self.valves) == len(self.next_level) == len(self.episode) == n):
            raise ValueError("level, valves, next_level and episode must have the same length")

    def __len__(self) -> int:
        return len(self.level)

    @classmethod
    def empty(cls) -> "Transitions":
        z = np.zeros((0, NUM_TANKS))
        return cls(z, z, z, np.zeros(0))

    @classmethod
    def concat(cls, parts: Iterable["Transitions"]) -> "Transitions":
        """Rows of all parts, in order. Episode ids are kept as they are, so
        chunks of one run concatenate into continuous episodes; rows of
        different sources that happen to share an id are still told apart by
        :meth:`segments` (it also cuts where a row does not start where the
        previous one ended)."""
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        return cls(np.concatenate([p.level for p in parts]),
                   np.concatenate([p.valves for p in parts]),
                   np.concatenate([p.next_level for p in parts]),
                   np.concatenate([p.episode for p in parts]))

    @classmethod
    def from_observations(cls, observations: Sequence[PlantObservation], *,
                          true_level: bool = False) -> "Transitions":
        """Transitions between successive observations of one plant link.

        ``observations`` is the stream a controller sees: the observation after
        each ``reset()``/``evaluate()`` and after each ``step()``, in order. A
        row is made from observation k-1 to k whenever k is the next step of
        the same episode (same ``episode``, ``step`` one more); a reset, or an
        episode the plant started by itself after a terminal/truncated step,
        starts no row until its first known level. ``true_level`` uses the
        noise-free levels (validation only: a controller sees ``level``).
        """
        rows = [(a, b) for a, b in zip(observations[:-1], observations[1:])
                if b.episode == a.episode and b.step == a.step + 1]
        if not rows:
            return cls.empty()
        get = (lambda o: o.true_level) if true_level else (lambda o: o.level)
        return cls(np.stack([get(a) for a, _ in rows]),
                   np.stack([b.valves for _, b in rows]),
                   np.stack([get(b) for _, b in rows]),
                   np.array([b.episode for _, b in rows]))

    def select(self, rows: np.ndarray) -> "Transitions":
        """The given rows (index array or boolean mask), in the given order."""
        return Transitions(self.level[rows], self.valves[rows], self.next_level[rows],
                           self.episode[rows])

    def tail(self, n: int) -> "Transitions":
        """The last ``n`` rows (the most recent data when rows are in time order)."""
        return self.select(np.arange(max(0, len(self) - n), len(self)))

    def segments(self) -> np.ndarray:
        """(T,) int64 id of the continuous run each row belongs to: a new run
        starts where the episode id changes or where a row does not start at
        the previous row's next level (to 1e-9 m)."""
        if len(self) == 0:
            return np.zeros(0, dtype=np.int64)
        cut = (self.episode[1:] != self.episode[:-1]) | np.any(
            np.abs(self.level[1:] - self.next_level[:-1]) > 1e-9, axis=1)
        return np.concatenate([[0], np.cumsum(cut)]).astype(np.int64)

    def save_npz(self, path: str | Path) -> None:
        """Write to a compressed .npz (plain arrays, no pickle)."""
        np.savez_compressed(path, level=self.level, valves=self.valves,
                            next_level=self.next_level, episode=self.episode)

    @classmethod
    def load_npz(cls, path: str | Path) -> "Transitions":
        with np.load(path, allow_pickle=False) as f:
            return cls(f["level"], f["valves"], f["next_level"], f["episode"])


# ---------------------------------------------------------------------------
# Data collection
# ---------------------------------------------------------------------------

def collect_random_episodes(plant: PlantLink, episodes: int, seed: int = 0, *,
                            max_hold: int = 30, evaluation: bool = False,
                            max_episode_steps: int = 4096) -> Transitions:
    """Run ``episodes`` episodes of random valve settings on ``plant``.

    Each setting (every valve open with probability 1/2) is held for a
    duration drawn uniformly from 1..``max_hold`` steps (default 30, about
    half a nominal episode), then redrawn; a new episode starts with a new
    setting. ``evaluation=True`` starts episodes with ``plant.evaluate()``
    (age frozen, steps not counted towards degradation) instead of ``reset()``.
    An episode is cut after ``max_episode_steps`` (a dead pump can keep one from
    ever ending). Rows use the observed levels, as a controller sees them.
    """
    rng = np.random.default_rng(seed)
    observations: list[PlantObservation] = []
    for _ in range(episodes):
        obs = plant.evaluate() if evaluation else plant.reset()
        observations.append(obs)
        hold, steps = 0, 0
        while not obs.done and steps < max_episode_steps:
            steps += 1
            if hold == 0:
                valves = rng.integers(0, 2, NUM_TANKS).astype(np.int8)
                hold = int(rng.integers(1, max_hold + 1))
            obs = plant.step(valves)
            observations.append(obs)
            hold -= 1
    return Transitions.from_observations(observations)


def collect_sparse_episodes(plant: PlantLink, episodes: int, seed: int = 0, *,
                            max_hold: int = 10, max_open: float = 0.3,
                            max_episode_steps: int = 4096) -> Transitions:
    """Run ``episodes`` episodes of sparse valve openings on ``plant``: each
    episode draws an open probability from [0, ``max_open``], each setting opens
    every valve with it and is held 1..``max_hold`` steps. Closed valves, which
    a good controller mostly chooses, are common here and rare in the paper's
    set (1 setting in 64)."""
    rng = np.random.default_rng(seed)
    observations: list[PlantObservation] = []
    for _ in range(episodes):
        obs = plant.reset()
        observations.append(obs)
        p_open, hold, steps = rng.uniform(0.0, max_open), 0, 0
        while not obs.done and steps < max_episode_steps:
            steps += 1
            if hold == 0:
                valves = (rng.random(NUM_TANKS) < p_open).astype(np.int8)
                hold = int(rng.integers(1, max_hold + 1))
            obs = plant.step(valves)
            observations.append(obs)
            hold -= 1
    return Transitions.from_observations(observations)


def _core_plant(seed: int) -> PlantLink:
    return CorePlant(None, seed)


def collect_nominal_dataset(episodes: int = 50, seed: int = 0,
                            plant_factory: Callable[[int], PlantLink] = _core_plant,
                            max_hold: int = 30) -> Transitions:
    """The paper's nominal data set: ``episodes`` (50) episodes of random
    valve settings, each held for up to ``max_hold`` (30) steps, on the
    nominal plant ``plant_factory(seed)`` (default ``CorePlant(None, seed)``).
    About 59 rows per episode."""
    plant = plant_factory(seed)
    try:
        return collect_random_episodes(plant, episodes, seed, max_hold=max_hold)
    finally:
        plant.close()
