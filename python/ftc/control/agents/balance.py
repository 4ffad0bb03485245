"""A rule that balances the wings: the worked example of a new controller
(docs/architecture.md). It is told nothing about the faults and learns
nothing; it looks at the centre of gravity of the levels it is given.

When the centre of gravity leaves the band |cg| <= ``band`` (moment-arm
units), it opens two valves: the fullest tank on the heavy wing (a source:
the conduit takes its level) and the emptiest tank on the light wing (a
sink), so fuel flows across; otherwise every valve stays closed (the optimum
of a balanced plant, as the activity term costs 1/6 per open valve).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ftc.common.constants import NUM_TANKS
from ftc.common.cli import between
from ftc.control.run.agent import Agent, StepContext
from ftc.control.run.config import RunConfig
from ftc.plant.link import PlantObservation
from ftc.plant.reward import AREAS, MOMENT_ARMS

LEFT, RIGHT = np.arange(0, 3), np.arange(3, 6)


@dataclass
class BalanceConfig(RunConfig):
    """A run of the balance rule: the run's options and the rule's band."""

    method: str = field(default="balance", metadata={"help": "the method"})
    band: float = field(default=0.1, metadata={"check": between(0.0, 1.0), "help": (
        "|cg| (moment-arm units) above which the rule moves fuel to the light wing")})


class BalanceAgent(Agent):
    name = "balance"
    Config = BalanceConfig

    def __init__(self, band: float = 0.1) -> None:
        self.band = band

    @classmethod
    def from_configs(cls, configs: dict[str, Any]) -> "BalanceAgent":
        return cls(configs["controller"].band)

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        return balance_valves(obs.level, self.band)


def balance_valves(level: np.ndarray, band: float = 0.1) -> np.ndarray:
    """The rule's valves (6,) int8 for tank levels (6,) m: the fullest tank of the
    heavy wing and the emptiest of the light one open where |cg| > band."""
    mass = AREAS * np.maximum(level, 0.0)
    u = np.zeros(NUM_TANKS, np.int8)
    if mass.sum() <= 0:
        return u
    cg = float(mass @ MOMENT_ARMS / mass.sum())
    if abs(cg) <= band:
        return u
    heavy, light = (RIGHT, LEFT) if cg > 0 else (LEFT, RIGHT)
    u[heavy[np.argmax(level[heavy])]] = 1
    u[light[np.argmin(level[light])]] = 1
    return u
