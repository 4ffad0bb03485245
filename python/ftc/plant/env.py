"""Gymnasium environment on the plant (the real process over LCM by default).

Observation: ``Box(0, 1, (6,))`` published tank levels in metres (tank heights
are 1 m; noisy readings are clipped to the physical range, as a saturating
sensor would). Action: ``MultiBinary(6)``, valve i open (1) or closed (0).
Reward: :func:`ftc.reward.reward_terms` of the published levels after the step;
its components are in ``info``. ``terminated``: fuel exhausted;
``truncated``: the plant's interval boundary (the plant then degrades).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from ftc.common.constants import NUM_TANKS
from ftc.plant.lcm_link import launch
from ftc.plant.link import PlantLink, PlantObservation
from ftc.plant.reward import reward_terms


class FuelTransferEnv(gym.Env):
    """The fuel-transfer plant as a Gymnasium env.

    link: a PlantLink to drive (CorePlant, attach(...)); if None, a private plant
        process is launched on first reset with ``scenario`` and ``plant_seed``
        and stopped by close().
    """

    metadata = {"render_modes": []}

    def __init__(self, scenario: str | None = None, *, link: PlantLink | None = None,
                 plant_seed: int = 0) -> None:
        self.observation_space = gym.spaces.Box(0.0, 1.0, shape=(NUM_TANKS,), dtype=np.float32)
        self.action_space = gym.spaces.MultiBinary(NUM_TANKS)
        self._scenario = scenario
        self._plant_seed = plant_seed
        self._link = link
        self._owns_link = link is None

    def _obs(self, o: PlantObservation) -> np.ndarray:
        return np.clip(o.level, 0.0, 1.0).astype(np.float32)

    def _info(self, o: PlantObservation, valves: np.ndarray) -> dict[str, Any]:
        terms = reward_terms(o.level, valves)
        return {"cg": float(terms.cg), "spread": float(terms.spread),
                "activity": float(terms.activity), "deficit": o.deficit.copy(),
                "age": o.age, "step": o.step,
                "true_level": o.true_level.copy()}

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        if self._link is None:
            self._link = launch(self._scenario, self._plant_seed)
        o = self._link.reset()
        return self._obs(o), self._info(o, np.zeros(NUM_TANKS))

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._link is None:
            raise RuntimeError("call reset() before step()")
        u = np.asarray(action, dtype=np.int8)
        o = self._link.step(u)
        info = self._info(o, u)
        r = float(reward_terms(o.level, u).reward)
        return self._obs(o), r, o.terminal, o.truncated and not o.terminal, info

    def close(self) -> None:
        if self._link is not None and self._owns_link:
            self._link.close()
            self._link = None
