"""Gymnasium environment on the plant (the real process over LCM by default).

Registered on ``import ftc`` (see ``ftc/__init__.py``) as ``ftc/FuelTransfer-v0``
(a private plant process per env, over LCM) and ``ftc/FuelTransferCore-v0``
(the same C++ physics in this process); ``gymnasium.make("ftc:ftc/FuelTransfer-v0")``
imports ftc itself.

Observation: ``Box(0, 1, (6,))`` published tank levels in metres (tank heights
are 1 m; noisy readings are clipped to the physical range, as a saturating
sensor would). Action: ``MultiBinary(6)``, valve i open (1) or closed (0).
Reward: the plant's own reward (``ftc._core.reward``, cpp/plant/core/reward.cpp,
which tests check against :func:`ftc.plant.reward.reward_terms`) of the
published levels after the step and the commanded valves; its components are
in ``info``. The batched pool (ftc.plant.vector) calls the same C++ function, so
the two envs' rewards agree to the last bit. ``terminated``: fuel exhausted;
``truncated``: the plant's interval boundary (the plant then degrades).

The plant ages across episodes: ``reset()`` starts a new episode from full tanks
at the plant's current age. ``reset(seed=s)`` starts a fresh plant (age 0)
seeded ``s`` (its sensor noise and random starts), so a seeded reset followed by
the same actions gives the same trajectory.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from ftc.common.constants import NUM_TANKS
from ftc.common.paths import scenario_file
from ftc.plant.lcm_link import launch
from ftc.plant.link import CorePlant, PlantLink, PlantObservation
from ftc.plant.render import draw_plant
from ftc.plant.reward import reward_terms
from ftc.plant.valves import checked_valves

LINKS = ("lcm", "core")
MAX_SEED = 2**64  # the plant's --seed and the core's seed are uint64


def resolve_scenario(scenario: str | os.PathLike | None) -> str | None:
    """The scenario file to give the plant.

    scenario: a path to a TOML file; or the name of one of the repository's
        ``scenarios/`` ("single", "multiple", "nominal", "abrupt"); or None for
        the plant's built-in nominal parameters.
    Raises ValueError (unknown name) or FileNotFoundError (no such file), one line.
    """
    if scenario is None:
        return None
    if not isinstance(scenario, (str, os.PathLike)):
        raise TypeError(f"FuelTransferEnv: scenario must be a path, a scenario name or None, "
                        f"got {type(scenario).__name__}")
    text = os.fspath(scenario)
    if isinstance(scenario, str):
        try:
            text = scenario_file(text)
        except ValueError as e:
            raise ValueError(f"FuelTransferEnv: {e}; or give the path of a .toml file") from None
    path = Path(text)
    if not path.is_file():
        raise FileNotFoundError(f"FuelTransferEnv: scenario file not found: {text} "
                                f"(resolved to {path.resolve()})")
    return str(path)


def _check_scenario_file(path: str) -> None:
    """Parse the scenario with the plant's own reader, so a malformed file fails
    when the env is made, not at the first reset in some worker process."""
    from ftc import _core  # built by CMake into build/python

    try:
        _core.load_scenario(path)
    except Exception as e:  # noqa: BLE001  (_core.ScenarioError; the message names the line)
        raise ValueError(f"FuelTransferEnv: bad scenario file: {e}") from None


class FuelTransferEnv(gym.Env):
    """The fuel-transfer plant as a Gymnasium env.

    scenario: fault scenario (see :func:`resolve_scenario`); default the paper's
        single fault, ``scenarios/single.toml``
    link: "lcm" (a private plant process, launched on the first reset and on
        every seeded reset, stopped by close()), "core" (the C++ core in this
        process), or a PlantLink to drive (not owned: seeded resets do not
        restart it and close() leaves it open)
    plant_seed: the plant's seed until a reset gives one
    render_mode: None or "rgb_array" (tank levels, open valves, centre of gravity)
    """

    # one control step is 1 s of plant time (plant-model.md), so real time is 1 frame/s
    metadata = {"render_modes": ["rgb_array"], "render_fps": 1}

    def __init__(self, scenario: str | os.PathLike | None = "single", *,
                 link: str | PlantLink = "lcm", plant_seed: int = 0,
                 render_mode: str | None = None) -> None:
        if isinstance(link, str) and link not in LINKS:
            raise ValueError(f"FuelTransferEnv: link must be one of {', '.join(LINKS)} or a "
                             f"PlantLink, got {link!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"FuelTransferEnv: render_mode must be None or one of "
                             f"{self.metadata['render_modes']}, got {render_mode!r}")
        _check_seed("plant_seed", plant_seed)
        self._scenario = resolve_scenario(scenario)
        if self._scenario is not None:
            _check_scenario_file(self._scenario)
        self.observation_space = gym.spaces.Box(0.0, 1.0, shape=(NUM_TANKS,), dtype=np.float32)
        self.action_space = gym.spaces.MultiBinary(NUM_TANKS)
        self.render_mode = render_mode
        self._plant_seed = int(plant_seed)
        self._kind = link if isinstance(link, str) else None
        self._link: PlantLink | None = None if isinstance(link, str) else link
        self._last: tuple[PlantObservation, np.ndarray] | None = None

    # -- the link ----------------------------------------------------------
    def _open_link(self) -> PlantLink:
        if self._kind == "core":
            return CorePlant(self._scenario, self._plant_seed)
        # A plant launched from the main thread dies with this process even when it
        # is killed (a vector-env worker terminated): launch()'s default.
        return launch(self._scenario, self._plant_seed)

    def _close_link(self) -> None:
        if self._link is not None and self._kind is not None:
            self._link.close()
            self._link = None

    @property
    def plant_pid(self) -> int | None:
        """Process id of the plant this env launched (None: none running, or not LCM)."""
        process = getattr(self._link, "process", None) if self._kind == "lcm" else None
        return process.pid if process is not None else None

    # -- gymnasium ---------------------------------------------------------
    def _obs(self, o: PlantObservation) -> np.ndarray:
        return np.clip(o.level, 0.0, 1.0).astype(np.float32)

    def _info(self, o: PlantObservation, terms: dict[str, float]) -> dict[str, Any]:
        return {"cg": terms["cg"], "spread": terms["spread"],
                "activity": terms["activity"], "deficit": o.deficit.copy(),
                "age": o.age, "step": o.step,
                "true_level": o.true_level.copy()}

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode (full tanks); ``seed``: a fresh plant seeded so. No options."""
        if options:
            raise ValueError(f"FuelTransferEnv.reset: no options are supported, got "
                             f"{sorted(options)}")
        if seed is not None:
            _check_seed("seed", seed)
        super().reset(seed=seed)
        if seed is not None and self._kind is not None:
            self._close_link()
            self._plant_seed = int(seed)
        if self._link is None:
            self._link = self._open_link()
        o = self._link.reset()
        valves = np.zeros(NUM_TANKS, dtype=np.int8)
        self._last = (o, valves)
        return self._obs(o), self._info(o, _reward_terms(o.level, valves))

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._link is None:
            raise gym.error.ResetNeeded("FuelTransferEnv: call reset() before step()")
        u = checked_valves(action, "FuelTransferEnv.step")
        o = self._link.step(u)
        self._last = (o, u.copy())
        terms = _reward_terms(o.level, u)
        info = self._info(o, terms)
        return self._obs(o), terms["reward"], o.terminal, o.truncated and not o.terminal, info

    def render(self) -> np.ndarray | None:
        """(400, 640, 3) uint8 RGB of the last state with render_mode="rgb_array"; else None."""
        if self.render_mode is None:
            return None
        if self._last is None:
            raise gym.error.ResetNeeded("FuelTransferEnv: call reset() before render()")
        o, u = self._last
        terms = reward_terms(o.level, u)
        caption = (f"step {o.step}   age {o.age:g} intervals   reward {float(terms.reward):.3f}"
                   + ("   (fuel exhausted)" if o.terminal else ""))
        return draw_plant(o.level, u, float(terms.cg), caption)

    def close(self) -> None:
        """Stop the plant this env launched (safe to call twice)."""
        self._close_link()


def _reward_terms(level: np.ndarray, valves: np.ndarray) -> dict[str, float]:
    """The plant's reward and its terms (reward, cg, spread, activity), floats."""
    from ftc import _core

    return _core.reward(level, valves)


def _check_seed(name: str, seed: Any) -> None:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) \
            or not 0 <= int(seed) < MAX_SEED:
        raise ValueError(f"FuelTransferEnv: {name} must be an integer in [0, 2**64), got {seed!r}")
