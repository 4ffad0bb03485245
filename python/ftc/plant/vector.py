"""The batched plant pool as a Gymnasium vector env (``ftc._core.PlantPool``).

``gym.make_vec("ftc/FuelTransfer-v0", num_envs=N, vectorization_mode=
"vector_entry_point", scenario=...)`` (and ``ftc/FuelTransferCore-v0``) returns a
:class:`FuelTransferVectorEnv`: N plants in this process, stepped by one C++ call
across a thread pool, results written into preallocated NumPy arrays. Both ids
give the same pool (the C++ core in process; there is no LCM in it).

Each env is the plant :class:`ftc.plant.env.FuelTransferEnv` drives, driven the
same way: the same observation (published levels clipped to [0, 1], float32),
reward (the plant's reward of the published levels and the commanded valves),
``terminated`` (fuel exhausted) and ``truncated`` (the plant's interval
boundary), and after an episode ends a new one at the plant's age: each env
ages over intervals as the single env does. Env ``i`` seeded ``s + i`` (reset
``seed=s``, or ``plant_seed=s``) follows the single env seeded ``s + i``:
bit-identically with ``method="cvode"``; with the default ``"closed_form"``
(closed-form steps where they apply, CVODE for the rest) within the tolerance
docs/benchmarks.md states, with its measured maximum.

Autoreset: ``metadata["autoreset_mode"]``. NEXT_STEP (Gymnasium's default):
the step after an env's episode ends resets it (its action is ignored, reward
0, not done). SAME_STEP (``autoreset="same_step"``, what SB3 expects): the
env resets within the step; the observation returned is the new episode's and
the last one is ``info["final_obs"]`` (rows where ``info["_final_obs"]``).

Info: a dict of arrays (N,): ``age`` (intervals), ``step`` (in the episode),
``cg``, ``spread``, ``activity`` (the reward's terms), and (N, 6) int8
``valves``: the valves the plant applied during the step just taken (a stuck
valve as it stayed, whatever was commanded; 0 after a reset), what the
plant's state message publishes. Each has its ``_key`` mask (all True).
"""

from __future__ import annotations

import os
from typing import Any, Sequence

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

from ftc.common.constants import NUM_TANKS
from ftc.plant.env import MAX_SEED, _check_scenario_file, resolve_scenario

AUTORESET = {"next_step": AutoresetMode.NEXT_STEP, "same_step": AutoresetMode.SAME_STEP}
METHODS = ("closed_form", "cvode")
INFO_KEYS = ("age", "step", "cg", "spread", "activity", "valves")


def scenario_distribution(**fields: Any) -> Any:
    """A declared, seeded distribution of fault scenarios (``_core.ScenarioDistribution``).

    Fields (defaults in cpp/plant/core/scenario_distribution.h): mode,
    steps_per_interval, life_intervals; tank_probability, tank_factor [low, high];
    engine_probability, engine_factor; dead_pump_probability; event_probability,
    event_factor; stuck_valve_probability; noise_probability, noise_std.
    Raises ValueError (one line, the field named) on a bad declaration.
    """
    from ftc import _core

    return _core.ScenarioDistribution(**fields)


def _load(item: Any) -> Any:
    from ftc import _core

    if isinstance(item, _core.Scenario):
        return item
    path = resolve_scenario(item)
    if path is None:
        return _core.Scenario()
    _check_scenario_file(path)
    return _core.load_scenario(path)


def resolve_scenarios(scenario: Any, num_envs: int, seed: int) -> tuple[list, Any]:
    """(N scenarios, the distribution or None) for ``scenario``: a name, a path,
    None or a ``_core.Scenario`` (every env the same); a sequence of N of those;
    or a ScenarioDistribution (or a dict of its fields), drawn from ``seed``."""
    from ftc import _core

    if isinstance(scenario, dict):
        scenario = scenario_distribution(**scenario)
    if isinstance(scenario, _core.ScenarioDistribution):
        return scenario.draw(num_envs, seed), scenario
    if isinstance(scenario, (str, os.PathLike, _core.Scenario)) or scenario is None:
        one = _load(scenario)
        return [one] * num_envs, None
    if isinstance(scenario, Sequence):
        if len(scenario) != num_envs:
            raise ValueError(f"FuelTransferVectorEnv: {len(scenario)} scenarios for "
                             f"num_envs={num_envs}")
        return [_load(s) for s in scenario], None
    raise TypeError(f"FuelTransferVectorEnv: scenario must be a name, a path, a Scenario, a "
                    f"list of them or a ScenarioDistribution, got {type(scenario).__name__}")


def check_actions(actions: Any, num_envs: int) -> np.ndarray:
    """Actions as the pool takes them, (N, 6) int8 of 0/1; bool, integer and float
    arrays of 0/1 are accepted (SB3 hands floats). Anything else: a one-line
    ValueError saying what and where, before any env moves."""
    a = np.asarray(actions)
    where = "FuelTransferVectorEnv.step: actions"
    if a.shape != (num_envs, NUM_TANKS):
        raise ValueError(f"{where} must have shape ({num_envs}, {NUM_TANKS}), got {a.shape}")
    if a.dtype == np.int8:
        return np.ascontiguousarray(a)  # the pool checks 0/1 itself (one pass in C++)
    if a.dtype.kind not in "biuf":
        raise ValueError(f"{where} must be bool, integer or float 0/1, got dtype {a.dtype}")
    if a.dtype.kind == "b" or ((a == 0) | (a == 1)).all():  # NaN is neither: refused below
        return a.astype(np.int8)
    if a.dtype.kind == "f" and np.isnan(a).any():
        env, valve = np.argwhere(np.isnan(a))[0]
        raise ValueError(f"{where}: NaN at env {env}, valve {valve}")
    env, valve = np.argwhere((a != 0) & (a != 1))[0]
    raise ValueError(f"{where} must be 0 or 1, got {a[env, valve].item()!r} at env {env}, "
                     f"valve {valve}")


def _seeds(seed: int | Sequence[int], num_envs: int) -> list[int]:
    seeds = ([int(seed) + i for i in range(num_envs)] if np.isscalar(seed)
             else [int(s) for s in seed])
    if len(seeds) != num_envs or any(not 0 <= s < MAX_SEED for s in seeds):
        raise ValueError(f"FuelTransferVectorEnv: seed must be an int (env i gets seed + i) or "
                         f"{num_envs} ints, each in [0, 2**64), got {seed!r}")
    return seeds


class FuelTransferVectorEnv(gym.vector.VectorEnv):
    """N fuel-transfer plants in one batched C++ pool (see the module docstring).

    num_envs: N
    scenario: see :func:`resolve_scenarios` (default the paper's single fault)
    link: "core" or "lcm", accepted for the registered ids' kwargs; the pool is
        always the C++ core in this process
    plant_seed: env i's plant seed is plant_seed + i until a seeded reset
    method: "closed_form" (default) or "cvode" (plant.h StepMethod)
    threads: C++ worker threads, 0 = every core
    autoreset: "next_step" (default) or "same_step"
    life_intervals: renew a plant (age 0, a fresh draw of the distribution)
        after this many intervals; default the distribution's life_intervals, or
        0 (never) for given scenarios
    max_episode_steps: the registration's backstop; must not be shorter than an
        interval (the plant truncates there itself)
    copy: return copies of the arrays (False: the pool's own, overwritten by
        the next step)
    """

    def __init__(self, num_envs: int = 1, scenario: Any = "single", *, link: str = "core",
                 plant_seed: int = 0, method: str = "closed_form", threads: int = 0,
                 autoreset: str = "next_step", life_intervals: int | None = None,
                 max_episode_steps: int | None = None, copy: bool = True,
                 render_mode: str | None = None) -> None:
        from ftc import _core

        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) \
                or num_envs < 1:
            raise ValueError(f"FuelTransferVectorEnv: num_envs must be an int >= 1, got "
                             f"{num_envs!r}")
        for name, value, known in (("link", link, ("core", "lcm")), ("method", method, METHODS),
                                   ("autoreset", autoreset, tuple(AUTORESET))):
            if value not in known:
                raise ValueError(f"FuelTransferVectorEnv: {name} must be one of "
                                 f"{', '.join(known)}, got {value!r}")
        if render_mode is not None:
            raise ValueError("FuelTransferVectorEnv: no render modes (render one plant with "
                             "FuelTransferEnv)")
        self.num_envs = int(num_envs)
        seeds = _seeds(plant_seed, self.num_envs)
        scenarios, self.distribution = resolve_scenarios(scenario, self.num_envs, seeds[0])
        interval = max(s.steps_per_interval for s in scenarios)
        if max_episode_steps is not None and max_episode_steps < interval:
            raise ValueError(f"FuelTransferVectorEnv: max_episode_steps={max_episode_steps} is "
                             f"shorter than an interval ({interval} steps): not supported")
        if life_intervals is None:
            life_intervals = self.distribution.life_intervals if self.distribution else 0
        self._copy = copy
        self.metadata = {"autoreset_mode": AUTORESET[autoreset], "render_modes": []}
        self.render_mode = None
        self.single_observation_space = gym.spaces.Box(0.0, 1.0, (NUM_TANKS,), np.float32)
        self.single_action_space = gym.spaces.MultiBinary(NUM_TANKS)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space,
                                                              self.num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self.pool = _core.PlantPool(scenarios, seeds, method=method, threads=threads,
                                    autoreset=autoreset, life_intervals=life_intervals,
                                    distribution=self.distribution)
        n = self.num_envs
        self._obs = np.zeros((n, NUM_TANKS), np.float32)
        self._reward = np.zeros(n, np.float64)
        self._terminated = np.zeros(n, bool)
        self._truncated = np.zeros(n, bool)
        self._info = {"age": np.zeros(n), "step": np.zeros(n, np.int64), "cg": np.zeros(n),
                      "spread": np.zeros(n), "activity": np.zeros(n),
                      "valves": np.zeros((n, NUM_TANKS), np.int8)}
        self._final_obs = np.zeros((n, NUM_TANKS), np.float32)
        self._final_mask = np.zeros(n, bool)
        self._all = np.ones(n, bool)
        self.pool.bind_outputs(self._obs, self._reward, self._terminated, self._truncated,
                               self._info["age"], self._info["step"], self._info["cg"],
                               self._info["spread"], self._info["activity"], self._final_obs,
                               self._final_mask, self._info["valves"])
        self._reset_once = False

    def _out(self, a: np.ndarray) -> np.ndarray:
        return a.copy() if self._copy else a

    def _infos(self) -> dict[str, Any]:
        info: dict[str, Any] = {}
        for k in INFO_KEYS:
            info[k] = self._out(self._info[k])
            info[f"_{k}"] = self._all
        if self.metadata["autoreset_mode"] is AutoresetMode.SAME_STEP and self._final_mask.any():
            info["final_obs"] = self._out(self._final_obs)
            info["_final_obs"] = self._out(self._final_mask)
        return info

    def reset(self, *, seed: int | Sequence[int] | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """A new episode in every env at its age. ``seed``: fresh plants (age 0),
        env i seeded seed + i (or seed[i]); a distribution is drawn anew from it."""
        if options:
            raise ValueError(f"FuelTransferVectorEnv.reset: no options are supported, got "
                             f"{sorted(options)}")
        if seed is not None:
            seeds = _seeds(seed, self.num_envs)
            if self.distribution is not None:
                self.pool.reseed(self.distribution.draw(self.num_envs, seeds[0]), seeds)
            else:
                self.pool.reseed([self.pool.scenario(i) for i in range(self.num_envs)], seeds)
            self._np_random, _ = gym.utils.seeding.np_random(seeds[0])
        self.pool.reset()
        self._reset_once = True
        return self._out(self._obs), self._infos()

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                          dict[str, Any]]:
        """One step of every env: actions (N, 6) of 0/1 (see :func:`check_actions`)."""
        if not self._reset_once:
            raise gym.error.ResetNeeded("FuelTransferVectorEnv: call reset() before step()")
        self.pool.step(check_actions(actions, self.num_envs))
        return (self._out(self._obs), self._out(self._reward), self._out(self._terminated),
                self._out(self._truncated), self._infos())

    def close_extras(self, **kwargs: Any) -> None:
        self.pool = None


def make_vector(num_envs: int = 1, **kwargs: Any) -> FuelTransferVectorEnv:
    """The registered ids' ``vector_entry_point``."""
    return FuelTransferVectorEnv(num_envs, **kwargs)
