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


def balance_valves_batch(levels: np.ndarray, band: float = 0.1) -> np.ndarray:
    """The rule's valves (N, 6) int8 for N rows of tank levels (N, 6) m, each
    row as :func:`balance_valves` (on ties, the first fullest tank of the
    heavy wing and the first emptiest of the light one)."""
    levels = np.asarray(levels, np.float64)
    mass = AREAS * np.maximum(levels, 0.0)
    total = mass.sum(axis=1)
    u = np.zeros(levels.shape, np.int8)
    rows = np.flatnonzero(total > 0)
    # elementwise, then summed per row: a row's cg does not depend on the others
    cg = (mass[rows] * MOMENT_ARMS).sum(axis=1) / total[rows]
    outside = np.abs(cg) > band
    rows, cg = rows[outside], cg[outside]
    right = cg > 0  # the right wing is heavy: from it to the left
    x = levels[rows]
    source = np.where(right, 3 + np.argmax(x[:, RIGHT], axis=1), np.argmax(x[:, LEFT], axis=1))
    sink = np.where(right, np.argmin(x[:, LEFT], axis=1), 3 + np.argmin(x[:, RIGHT], axis=1))
    u[rows, source] = 1
    u[rows, sink] = 1
    return u


def balance_valves(level: np.ndarray, band: float = 0.1) -> np.ndarray:
    """The rule's valves (6,) int8 for tank levels (6,) m: the fullest tank of the
    heavy wing and the emptiest of the light one open where |cg| > band."""
    return balance_valves_batch(np.asarray(level, np.float64)[None], band)[0]
