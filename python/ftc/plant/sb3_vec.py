"""Stable-Baselines3's ``VecEnv`` over the batched plant pool, so that
``PPO("MlpPolicy", PoolVecEnv(num_envs=N, scenario=...))`` trains on it directly.

SB3's contract: one call steps every env; a finished env is reset within the
step and its last observation is ``infos[i]["terminal_observation"]``;
``infos[i]["TimeLimit.truncated"]`` marks a truncation (the plant's interval
boundary), which SB3 bootstraps from the critic. The pool runs in Gymnasium's
SAME_STEP autoreset mode for it. Requires stable-baselines3 (requirements-extra.txt).

The pool made here hands over its own arrays (``copy=False``); the adapter copies
only what SB3 keeps past the next step: the observation (its ``_last_obs``) and
each finished env's terminal observation. Rewards are converted to float32 (a new
array) and ``dones`` is a new array, as SB3 stores them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices

from ftc.plant.vector import FuelTransferVectorEnv


class PoolVecEnv(VecEnv):
    """SB3 VecEnv over a :class:`FuelTransferVectorEnv` in SAME_STEP mode.

    env: the pool to drive (made with ``autoreset="same_step"``); or None to
        make one from ``kwargs`` (FuelTransferVectorEnv's, e.g. num_envs, scenario)
    """

    def __init__(self, env: FuelTransferVectorEnv | None = None, **kwargs: Any) -> None:
        if env is None:
            env = FuelTransferVectorEnv(autoreset="same_step", **{"copy": False, **kwargs})
        elif kwargs:
            raise ValueError("PoolVecEnv: give a pool or its arguments, not both")
        if env.metadata["autoreset_mode"].value != "SameStep":
            raise ValueError("PoolVecEnv: the pool must autoreset in the same step "
                             "(FuelTransferVectorEnv(..., autoreset='same_step'))")
        self.env = env
        self._actions: np.ndarray | None = None
        super().__init__(env.num_envs, env.single_observation_space, env.single_action_space)

    def reset(self) -> np.ndarray:
        seeds = None if self._seeds[0] is None else [int(s) for s in self._seeds]
        obs, _ = self.env.reset(seed=seeds)
        self._reset_seeds()
        self._reset_options()
        return obs.copy()

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        obs, reward, terminated, truncated, info = self.env.step(self._actions)
        dones = terminated | truncated
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for i in np.flatnonzero(dones):
            infos[i] = {"terminal_observation": info["final_obs"][i].copy(),
                        "TimeLimit.truncated": bool(truncated[i])}
        return obs.copy(), reward.astype(np.float32), dones, infos

    def close(self) -> None:
        self.env.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """The pool's attribute, once per env asked for (the envs share it)."""
        value = getattr(self.env, attr_name)
        return [value for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        raise AttributeError(f"PoolVecEnv: the pool's envs have no settable attribute "
                             f"{attr_name!r}")

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None,
                   **method_kwargs: Any) -> list[Any]:
        raise AttributeError(f"PoolVecEnv: the pool's envs are not Python objects; no method "
                             f"{method_name!r}")

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]
