"""The Agent protocol: what every controller the interval runner drives
provides. A new controller is one small class; see docs/architecture.md.

The runner calls, per interval k:

    begin_interval(k)
    start_episode(obs)                 after every reset (full tanks)
    act(obs, ctx) -> valves            ctx.steps_left: steps left in the interval
    observe(transition)                after every operating step
    end_online() -> metrics            the interval's online statistics
    start_episode(obs); act(...)       evaluation episode (ctx.evaluation; if evaluates)
    end_interval(k, data) -> metrics   refit, offline phase, swap
    late_metrics() -> [(k, metrics)]   metrics of earlier intervals that arrived since
    finish()                           after the last interval (wait for background work)

and ``state_dict`` / ``load_state_dict`` for checkpoints (tensors, numpy
arrays and plain containers only: loadable with ``torch.load(weights_only=True)``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ftc.control.run.telemetry import NULL_TELEMETRY, Telemetry
from ftc.learning.transitions import Transitions
from ftc.plant.link import PlantObservation


@dataclass(frozen=True)
class StepContext:
    """Where a decision is taken.

    interval: the interval index; step: steps taken in the interval (operating)
    or in the evaluation episode; steps_left: operating steps left in the
    interval (None in evaluation); evaluation: the deterministic evaluation
    episode (age frozen; a learned policy acts greedily)."""

    interval: int
    step: int
    steps_left: int | None
    evaluation: bool = False


@dataclass(frozen=True)
class Transition:
    """One operating step as the agent saw it.

    obs: acted on; valves: applied; reward: of the step (plant-model.md);
    next_obs: the plant's answer (terminal / truncated flags on it);
    following: the observation the agent acts on next (after a reset when the
    episode ended and the interval goes on; else next_obs)."""

    obs: PlantObservation
    valves: np.ndarray
    reward: float
    next_obs: PlantObservation
    following: PlantObservation

    @property
    def truncated(self) -> bool:
        """Cut off at the interval boundary (bootstrap), not terminal."""
        return self.next_obs.truncated and not self.next_obs.terminal


class Agent:
    """Base class with the no-op defaults; subclasses override what they need.

    name: shown in progress lines; evaluates: run the deterministic evaluation
    episode after each interval; extra_columns: the metrics.csv columns it adds
    to every run's (:data:`ftc.control.run.metrics.METRIC_COLUMNS`); progress_keys: (metric, label) pairs shown per interval;
    telemetry: set by the runner (--tensorboard), for the agent's own scalars
    (PPO: ``telemetry.update(stats)`` after every update); a no-op by default;
    background_learning: set by the runner on a real-time plant
    (:mod:`ftc.control.run.realtime`): ``act`` and ``observe`` must return within
    a plant step, so updates, refits and offline phases run on another thread
    or process and the acting policy is swapped in between two steps."""

    name = "agent"
    #: the run config of its method (a RunConfig with the agent's own options), and
    #: the configs of its other parts by name, with their option prefix
    #: ({"ppo": (PPOConfig, "ppo-")}); the command line offers exactly these
    Config: type | None = None
    parts: dict[str, tuple[type, str]] = {}
    evaluates = True
    extra_columns: tuple[str, ...] = ()
    progress_keys: tuple[tuple[str, str], ...] = ()
    telemetry: Telemetry = NULL_TELEMETRY
    background_learning = False
    learning = False  # a fit runs off the loop now (ftc.control.run.deferred)

    @classmethod
    def from_configs(cls, configs: dict[str, Any]) -> "Agent":
        """The agent of a run whose config parts are ``configs`` (by name, as in
        config.json: {"controller": ..., "ppo": ...} or {"mpc": ...})."""
        raise NotImplementedError(f"{cls.__name__} does not say how it is built")

    def prepare(self) -> dict[str, Any]:
        """Before interval 0 of a new run (not on resume): pretraining. Returns info."""
        return {}

    def begin_interval(self, interval: int) -> None:
        pass

    def start_episode(self, obs: PlantObservation) -> None:
        pass

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        raise NotImplementedError

    def observe(self, t: Transition) -> None:
        pass

    def end_online(self) -> dict[str, Any]:
        return {}

    def end_interval(self, interval: int, data: Transitions) -> dict[str, Any]:
        return {}

    def late_metrics(self) -> list[tuple[int, dict[str, Any]]]:
        return []

    def finish(self) -> None:
        pass

    def close(self) -> None:
        """Release resources (worker processes); called once, also on failure."""

    def wants_data(self) -> bool:
        """Whether the runner should hand it each interval's transitions."""
        return False

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        pass

    def exported_policy(self) -> Any:
        """The acting policy as ``ftc.export`` writes it (an ActorCritic), for
        --push-policy; None when the agent has none."""
        return None

    def config_doc(self) -> dict[str, Any]:
        """Extra entries of config.json (e.g. the world model's config)."""
        return {}
