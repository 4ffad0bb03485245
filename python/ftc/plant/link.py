"""Talking to the plant: the observation type, the link protocol every
controller uses, its errors, and the in-process link (:class:`CorePlant`: the
C++ core without LCM, for simulation and tests). The real plant process over
LCM is :mod:`ftc.plant.lcm_link`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence

import numpy as np

from ftc.common.constants import NUM_TANKS


@dataclass(frozen=True)
class PlantObservation:
    """What the plant reports after a reset or a step.

    level:       (6,) published levels, m (sensor noise included if enabled)
    true_level:  (6,) noise-free levels, m (logging and validation only)
    valves:      (6,) int valves applied during the step (zeros after a reset)
    deficit:     (2,) unmet engine demand over the step, m^3
    age:         degradation age in force during the step, intervals
    step:        steps taken in the episode (0 after a reset)
    episode:     episode counter since the plant started
    operating_steps: steps counted towards degradation so far
    terminal:    fuel exhausted (do not bootstrap)
    truncated:   cut off at an interval boundary (bootstrap)
    evaluation:  an evaluation episode (age frozen, steps not counted)
    """

    level: np.ndarray
    true_level: np.ndarray
    valves: np.ndarray
    deficit: np.ndarray
    age: float
    step: int
    episode: int
    operating_steps: int
    terminal: bool
    truncated: bool
    evaluation: bool

    @property
    def done(self) -> bool:
        return self.terminal or self.truncated


class PlantLink(Protocol):
    """The interface every controller drives a plant through."""

    def reset(self) -> PlantObservation:
        """Start a new operating episode from full tanks at the current age."""

    def evaluate(self) -> PlantObservation:
        """Start an evaluation episode (age frozen at the last operating step's)."""

    def step(self, valves: Sequence[int] | np.ndarray) -> PlantObservation:
        """Apply valves (6 ints in {0, 1}) for one 1 s control step."""

    def close(self) -> None:
        """Release the link (and stop the plant process if this link owns it)."""


def valves_array(valves: Sequence[int] | np.ndarray) -> np.ndarray:
    u = np.asarray(valves)
    if u.shape != (NUM_TANKS,):
        raise ValueError(f"valves must have shape ({NUM_TANKS},), got {u.shape}")
    if not np.all((u == 0) | (u == 1)):
        raise ValueError(f"valves must be 0 or 1, got {u.tolist()}")
    return u.astype(np.int8)


class CorePlant:
    """The C++ plant core in this process (no LCM): same physics, same episodes.

    Used for nominal pretraining in simulation and as the reference the LCM
    plant is checked against.
    """

    def __init__(self, scenario: str | None = None, seed: int = 0, *,
                 steps_per_interval: int | None = None, start_step: int = 0) -> None:
        from ftc import _core  # built by CMake into build/python

        self._core = _core
        self.scenario = _core.load_scenario(str(scenario)) if scenario else _core.Scenario()
        if steps_per_interval is not None:
            self.scenario.steps_per_interval = int(steps_per_interval)
        self._plant = _core.Plant(self.scenario, int(seed))
        if start_step:
            self._plant.set_operating_steps(int(start_step))

    def _observation(self, d: dict) -> PlantObservation:
        return PlantObservation(
            level=np.array(d["observed"], dtype=np.float64),
            true_level=np.array(d["level"], dtype=np.float64),
            valves=np.array(d["valves"], dtype=np.int8),
            deficit=np.array(d["deficit"], dtype=np.float64),
            age=float(d["age"]), step=int(d["step"]), episode=int(d["episode"]),
            operating_steps=int(self._plant.operating_steps),
            terminal=bool(d["terminal"]), truncated=bool(d["truncated"]),
            evaluation=bool(d["evaluation"]))

    def reset(self) -> PlantObservation:
        self._plant.reset()
        return self._observation(self._plant.last())

    def evaluate(self) -> PlantObservation:
        self._plant.reset_evaluation()
        return self._observation(self._plant.last())

    def step(self, valves: Sequence[int] | np.ndarray) -> PlantObservation:
        return self._observation(self._plant.step(valves_array(valves).tolist()))

    def close(self) -> None:
        pass


class PlantError(RuntimeError):
    """The plant link failed (plant gone, refused to start, or answered nonsense).

    exit_code: the plant process's exit code when it exited (2: bad input).
    """

    def __init__(self, message: str, exit_code: int | None = None) -> None:
        super().__init__(message)
        self.exit_code = exit_code


class PlantGoneError(PlantError):
    """The plant stopped answering (killed, crashed, or not there)."""


class ForeignTrafficError(PlantGoneError):
    """Another process commanded the plant in this run's control session (it read
    the session id off the bus: without a bus key nothing else tells them apart);
    the run stops rather than go on from a state it did not drive."""


