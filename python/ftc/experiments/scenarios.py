"""What an experiment runs: its configuration, the presets, and the fault
scenarios of its trials (docs/plant-model.md, "The paper's
experiments").

single: engine E1 D_E = 20; multiple: E1 D_E = 20, tanks 5 and 6 D_T = 20;
aggregate: N trials, each one random tank and one random engine with factors
uniform in [10, 30], drawn from the configured scenario seed.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ftc.common.constants import NUM_ENGINES, NUM_TANKS
from ftc.common.paths import scenario_file
from ftc.experiments.methods import DEFAULT_METHODS

EXPERIMENTS = ("single", "multiple", "aggregate")
INF = math.inf


@dataclass(frozen=True)
class ExperimentConfig:
    """Everything that determines an experiment's results (jobs does not).

    experiments: which of single, multiple, aggregate to run
    methods: registered method names
    seeds: controller (and plant) seeds; every trial and method runs each
    trials: aggregate trials
    scenario_seed: seed of the aggregate trials' random faults
    intervals: degradation intervals per run (paper: 10)
    steps_per_interval: real control steps per interval, t_online (paper: 512)
    controller_args: extra controller arguments (e.g. --pretrain), each to the
        methods it acts on (ftc.experiments.method_args)
    run_timeout: seconds after which a run is killed and counted as failed (0: none)
    nice: niceness added to each controller and its plant (the recorder keeps the
        normal priority, so that it keeps up on a loaded machine)
    link: the controllers' plant link: lcm (a plant process per run, recorded) or
        core (the physics in the controller's process: no plant process, no log)
    tensorboard: directory of TensorBoard event files, one subdirectory per run
        (DIR/EXP/tNN/METHOD/sS, the run's key), or None; like jobs it does not
        change results, and --resume takes it from the command line
    """

    experiments: tuple[str, ...] = EXPERIMENTS
    methods: tuple[str, ...] = DEFAULT_METHODS
    seeds: tuple[int, ...] = (0,)
    trials: int = 20
    scenario_seed: int = 2020
    intervals: int = 10
    steps_per_interval: int = 512
    controller_args: tuple[str, ...] = ()
    run_timeout: float = 0.0
    nice: int = 5
    link: str = "lcm"
    tensorboard: str | None = None

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> "ExperimentConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()
                      if k in names})


#: Presets: the short default and the paper's protocol (--full).
PRESETS: dict[str, dict] = {
    "quick": dict(trials=2, intervals=10, steps_per_interval=512, seeds=(0,)),
    "full": dict(trials=20, intervals=10, steps_per_interval=512, seeds=(0,)),
}


@dataclass(frozen=True)
class Scenario:
    """A fault scenario: degradation factors (inf = healthy) of the 6 tanks and 2 engines."""

    name: str
    tank_factor: tuple[float, ...] = (INF,) * NUM_TANKS
    engine_factor: tuple[float, ...] = (INF,) * NUM_ENGINES

    def toml(self, steps_per_interval: int) -> str:
        """The scenario file the plant reads with --scenario."""
        def fmt(v: float) -> str:
            return "inf" if math.isinf(v) else repr(float(v))

        return (f'# Written by ftc.experiments; the plant reads it with --scenario.\n'
                f'name = "{self.name}"\n'
                f'tank_factor = [{", ".join(fmt(v) for v in self.tank_factor)}]\n'
                f'engine_factor = [{", ".join(fmt(v) for v in self.engine_factor)}]\n'
                f'degradation = "stepwise"\n'
                f'steps_per_interval = {int(steps_per_interval)}\n')

    def describe(self) -> str:
        parts = [f"tank {i + 1} D_T={v:.2f}" for i, v in enumerate(self.tank_factor)
                 if not math.isinf(v)]
        parts += [f"engine E{j + 1} D_E={v:.2f}" for j, v in enumerate(self.engine_factor)
                  if not math.isinf(v)]
        return ", ".join(parts) or "nominal"

    def to_json(self) -> dict:
        return {"name": self.name,
                "tank_factor": [None if math.isinf(v) else v for v in self.tank_factor],
                "engine_factor": [None if math.isinf(v) else v for v in self.engine_factor],
                "description": self.describe()}


def aggregate_scenarios(trials: int, seed: int) -> list[Scenario]:
    """The aggregate experiment's trials: one random tank and one random engine each,
    factors uniform in [10, 30], all drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    out = []
    for t in range(trials):
        tank, engine = int(rng.integers(0, NUM_TANKS)), int(rng.integers(0, NUM_ENGINES))
        d_t, d_e = float(rng.uniform(10.0, 30.0)), float(rng.uniform(10.0, 30.0))
        tanks = [INF] * NUM_TANKS
        tanks[tank] = d_t
        engines = [INF] * NUM_ENGINES
        engines[engine] = d_e
        out.append(Scenario(f"aggregate-{t:02d}", tuple(tanks), tuple(engines)))
    return out


def experiment_scenarios(config: ExperimentConfig) -> dict[str, list[Scenario]]:
    """Trials of each configured experiment (single and multiple have one trial)."""
    table = {
        "single": [Scenario("single", engine_factor=(20.0, INF))],
        "multiple": [Scenario("multiple", tank_factor=(INF, INF, INF, INF, 20.0, 20.0),
                              engine_factor=(20.0, INF))],
        "aggregate": aggregate_scenarios(config.trials, config.scenario_seed),
    }
    return {e: table[e] for e in config.experiments}


def scenario_texts(files: Sequence[Path]) -> dict[str, tuple[str, str]]:
    """stem -> (source, TOML text) of scenario files (or packaged scenarios' names), each read by the plant's own
    parser so that a malformed file is refused before any run; ValueError naming
    the file (and key), or two files of one stem (results name a scenario by it)."""
    from ftc import _core  # the bindings: the plant's scenario parser

    texts: dict[str, tuple[str, str]] = {}
    for given in files:
        path = Path(scenario_file(str(given)))  # a packaged scenario's name: its file
        try:
            _core.load_scenario(str(path))
            text = path.read_text()
        except (_core.ScenarioError, OSError, UnicodeDecodeError) as e:
            raise ValueError(str(e)) from None
        if path.stem in texts:
            raise ValueError(f"two files named {path.stem} ({texts[path.stem][0]}, {path}): "
                             "results name a scenario by its file's stem")
        texts[path.stem] = (str(path), text)
    return texts
