"""The benchmark suite's default scenarios: the paper's single and multiple
faults and random fault scenarios drawn wider than the paper's aggregate.

Each random scenario degrades one or two tanks (valve and pump) and one or
both engines, with factors uniform in [6, 30]. The tanks are drawn from all
six, so faults fall on either wing, or on both. With the pump capacity
p(a) = p0 max(0, 1 - a / D_T) at age a (in intervals), a factor below 9
kills the pump within the 10 intervals of a run: the paper's [10, 30] never
does. Everything is drawn from one seed, so the same configuration writes
the same files.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ftc.common.atomic import atomic_write_text
from ftc.common.constants import NUM_ENGINES, NUM_TANKS
from ftc.experiments.scenarios import INF, ExperimentConfig, Scenario, experiment_scenarios


@dataclass(frozen=True)
class SuiteConfig:
    """The default suite.

    random_scenarios: how many random scenarios follow single and multiple
    seed: seed of the random scenarios' draw
    factor_low, factor_high: degradation factors are uniform in this range
    max_tanks: each random scenario degrades 1..max_tanks tanks (and 1..2 engines)
    """

    random_scenarios: int = 20
    seed: int = 1100
    factor_low: float = 6.0
    factor_high: float = 30.0
    max_tanks: int = 2


def random_scenarios(config: SuiteConfig = SuiteConfig()) -> list[Scenario]:
    """The suite's random scenarios, ``random-00`` ...: one to ``max_tanks`` tanks
    and one or both engines each, factors uniform in [factor_low, factor_high]."""
    rng = np.random.default_rng(config.seed)
    out = []
    for i in range(config.random_scenarios):
        n_tanks = int(rng.integers(1, config.max_tanks + 1))
        n_engines = int(rng.integers(1, NUM_ENGINES + 1))
        tanks = sorted(int(t) for t in rng.choice(NUM_TANKS, n_tanks, replace=False))
        engines = sorted(int(e) for e in rng.choice(NUM_ENGINES, n_engines, replace=False))
        tank_factor, engine_factor = [INF] * NUM_TANKS, [INF] * NUM_ENGINES
        for t in tanks:
            tank_factor[t] = round(float(rng.uniform(config.factor_low, config.factor_high)), 3)
        for e in engines:
            engine_factor[e] = round(float(rng.uniform(config.factor_low, config.factor_high)), 3)
        out.append(Scenario(f"random-{i:02d}", tuple(tank_factor), tuple(engine_factor)))
    return out


def default_suite(config: SuiteConfig = SuiteConfig()) -> list[Scenario]:
    """single, multiple (the paper's, as in scenarios/*.toml), then the random ones."""
    paper = experiment_scenarios(ExperimentConfig(experiments=("single", "multiple")))
    return [paper["single"][0], paper["multiple"][0], *random_scenarios(config)]


def write_suite(directory: Path, steps_per_interval: int = 512,
                config: SuiteConfig = SuiteConfig()) -> list[Path]:
    """Write the default suite's scenario files (``<name>.toml``) into ``directory``;
    returns their paths in suite order."""
    directory = Path(directory)
    paths = []
    for sc in default_suite(config):
        path = directory / f"{sc.name}.toml"
        atomic_write_text(path, sc.toml(steps_per_interval))
        paths.append(path)
    return paths
