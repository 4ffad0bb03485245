"""The baselines of the paper (all valves closed, all valves open) and random
valves, as agents of the interval runner; :func:`baseline_valves` is the one
valve rule that simulate and the experiments' baseline episodes use too."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ftc.common.constants import NUM_TANKS
from ftc.control.run.agent import Agent, StepContext
from ftc.control.run.config import RunConfig
from ftc.plant.link import PlantObservation

BASELINES = ("closed", "open", "random")


def baseline_valves(policy: str, rng: np.random.Generator | None = None) -> np.ndarray:
    """Valves (6,) int8 of a baseline: all closed, all open, or each valve open
    with p = 1/2 (drawn from ``rng``)."""
    if policy == "closed":
        return np.zeros(NUM_TANKS, np.int8)
    if policy == "open":
        return np.ones(NUM_TANKS, np.int8)
    if policy == "random":
        if rng is None:
            raise ValueError("the random baseline needs a generator")
        return rng.integers(0, 2, NUM_TANKS).astype(np.int8)
    raise ValueError(f"unknown baseline {policy!r}; one of {', '.join(BASELINES)}")


@dataclass
class BaselineConfig(RunConfig):
    """A baseline's run: the run's options alone (a fixed rule has none of its own)."""

    method: str = field(default="closed", metadata={"help": "the baseline (one of "
                                                    f"{', '.join(BASELINES)})"})


class BaselineAgent(Agent):
    """A fixed valve rule: learns nothing, so it has no evaluation episode."""

    evaluates = False
    Config = BaselineConfig

    def __init__(self, policy: str, seed: int) -> None:
        baseline_valves(policy, np.random.default_rng(0))  # refuse an unknown name now
        self.name = policy
        self.rng = np.random.default_rng(seed)

    @classmethod
    def from_configs(cls, configs: dict[str, Any]) -> "BaselineAgent":
        return cls(configs["controller"].method, configs["controller"].seed)

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        return baseline_valves(self.name, self.rng)

    def state_dict(self) -> dict[str, Any]:
        return {"np_rng": self.rng.bit_generator.state}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.rng.bit_generator.state = state["np_rng"]
