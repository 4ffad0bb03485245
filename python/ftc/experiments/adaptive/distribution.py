"""The adaptive policy's training distribution of degradations: declared in one
file (``scenarios/training/adaptive.toml``), drawn from a seed, and disjoint
from every benchmark scenario.

A draw is the C++ ``ScenarioDistribution``'s (the file's ``[draw]`` table:
worn tanks and engines, a dying pump, an abrupt event, a stuck valve, sensor
noise), then the file's ``[extra]`` table applied to each scenario from the
same seed: continuous wear instead of stepwise, a second abrupt event, a
random start, a second stuck valve. :func:`draw` refuses (ValueError) any scenario whose faults
are those of a benchmark scenario (:func:`benchmark_signatures`: the default
suite, ``scenarios/abrupt.toml`` and ``scenarios/check/*.toml``), so the student
and its teacher never meet one.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ftc.common.constants import NUM_ENGINES, NUM_TANKS
from ftc.common.paths import SCENARIO_DIR
from ftc.experiments.suite import default_suite
from ftc.plant.vector import scenario_distribution

DISTRIBUTION_FILE = SCENARIO_DIR / "training" / "adaptive.toml"
EXTRA_FIELDS = ("continuous_probability", "second_event_probability", "random_start_probability",
                "second_stuck_probability")


@dataclass(frozen=True)
class TrainingDistribution:
    """The declared distribution: ``draw_fields`` for ``_core.ScenarioDistribution``
    and the ``extra`` probabilities; ``text``: the file's text (the cache key's)."""

    draw_fields: dict[str, Any]
    extra: dict[str, float]
    text: str
    source: str

    @property
    def steps_per_interval(self) -> int:
        return int(self.draw_fields.get("steps_per_interval", 512))

    @property
    def life_intervals(self) -> int:
        return int(self.draw_fields.get("life_intervals", 10))

    def core(self) -> Any:
        return scenario_distribution(**self.draw_fields)


def load(path: Path | str = DISTRIBUTION_FILE) -> TrainingDistribution:
    """The distribution declared in ``path``; ValueError (one line, the file and
    the key) on a file that does not declare one."""
    path = Path(path)
    try:
        text = path.read_text()
        doc = tomllib.loads(text)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise ValueError(f"{path}: {e}") from None
    unknown = sorted(set(doc) - {"draw", "extra"})
    if unknown or "draw" not in doc:
        raise ValueError(f"{path}: needs a [draw] table and optionally [extra], got "
                         f"{sorted(doc)}")
    extra = dict(doc.get("extra", {}))
    for key, value in extra.items():
        if key not in EXTRA_FIELDS:
            raise ValueError(f"{path}: [extra] {key}: unknown (known: {', '.join(EXTRA_FIELDS)})")
        if not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
            raise ValueError(f"{path}: [extra] {key} = {value!r}: a probability in [0, 1]")
    dist = TrainingDistribution(dict(doc["draw"]), {k: float(extra.get(k, 0.0))
                                                    for k in EXTRA_FIELDS}, text, str(path))
    try:
        dist.core()
    except (ValueError, TypeError) as e:
        raise ValueError(f"{path}: [draw] {e}") from None
    return dist


def draw(dist: TrainingDistribution, count: int, seed: int,
         forbidden: set[tuple] | None = None) -> list[Any]:
    """``count`` scenarios (``_core.Scenario``) drawn from ``seed``. ValueError if
    one of them has the faults of a benchmark scenario (``forbidden``: their
    signatures, default :func:`benchmark_signatures`)."""
    scenarios = dist.core().draw(count, seed)
    rng = np.random.default_rng([seed, 38])
    life_steps = dist.life_intervals * dist.steps_per_interval
    for s in scenarios:
        u = rng.random(4)
        if u[0] < dist.extra["continuous_probability"]:
            s.mode = "continuous"
        if u[1] < dist.extra["second_event_probability"]:
            at = int(rng.integers(dist.steps_per_interval, life_steps))
            low, high = dist.draw_fields.get("event_factor", (2.0, 10.0))
            component = int(rng.integers(0, NUM_TANKS + NUM_ENGINES))
            factor = float(rng.uniform(low, high))
            event = ({"at_step": at, "tank": component + 1, "factor": factor}
                     if component < NUM_TANKS else
                     {"at_step": at, "engine": component - NUM_TANKS + 1, "factor": factor})
            s.events = sorted([*s.events, event], key=lambda e: e["at_step"])
        if u[2] < dist.extra["random_start_probability"]:
            s.random_start = True
        if u[3] < dist.extra["second_stuck_probability"]:
            s.events = sorted([*s.events, _another_stuck_valve(s.events, rng, dist)],
                              key=lambda e: e["at_step"])
        s.name = "training"
    refuse_benchmark(scenarios, benchmark_signatures() if forbidden is None else forbidden)
    return scenarios


def draw_seed(seed: int, iteration: int) -> int:
    """The draw seed of DAgger iteration ``iteration`` of the member trained
    with seed ``seed``: the one numbering the trainer, the held-out draws' guard
    and the tests share."""
    return seed * 1000 + iteration


def training_draws(dist: TrainingDistribution, config: Any,
                   forbidden: set[tuple] | None = None) -> Iterator[list[Any]]:
    """Every batch of plants a training run of ``config`` (a
    ``TrainingConfig``: its seed, members, iterations and envs) draws, member
    by member and iteration by iteration."""
    for seed in range(config.seed, config.seed + config.members):
        for k in range(config.iterations):
            yield draw(dist, config.envs, draw_seed(seed, k), forbidden)


def _another_stuck_valve(events: list[dict], rng: np.random.Generator,
                         dist: TrainingDistribution) -> dict:
    """A stuck-valve event on a valve no earlier event sticks, open or closed
    (even odds), after the first interval: with the draw's own stuck valve,
    two valves stuck in one run, as compound faults have."""
    stuck = {e["stuck_valve"] for e in events if "stuck_valve" in e}
    free = [v for v in range(1, NUM_TANKS + 1) if v not in stuck]
    at = int(rng.integers(dist.steps_per_interval, dist.life_intervals * dist.steps_per_interval))
    return {"at_step": at, "stuck_valve": int(rng.choice(free)),
            "state": "open" if rng.random() < 0.5 else "closed"}


def signature(s: Any) -> tuple:
    """What makes a scenario's faults: its factors, wear mode, events and noise,
    rounded to 9 significant digits (a file's values are written with fewer)."""
    def r(v: float) -> float:
        return v if math.isinf(v) else float(f"{v:.9g}")

    events = tuple(tuple(sorted((k, r(v) if isinstance(v, float) else v)
                                for k, v in e.items())) for e in s.events)
    return (tuple(r(v) for v in s.tank_factor), tuple(r(v) for v in s.engine_factor),
            s.mode, r(float(s.noise_std)), events)


def benchmark_signatures(steps_per_interval: int = 512) -> set[tuple]:
    """The signatures of every benchmark scenario: the default suite's (single and
    multiple among them), ``scenarios/abrupt.toml`` and ``scenarios/check/``.
    (The healthy plant, ``nominal.toml``, is no fault scenario: a draw may be healthy.)"""
    from ftc import _core  # the plant's scenario parser

    out = set()
    for sc in default_suite():
        s = _core.Scenario()
        s.tank_factor, s.engine_factor = list(sc.tank_factor), list(sc.engine_factor)
        out.add(signature(s))
    for path in [SCENARIO_DIR / "abrupt.toml", *sorted((SCENARIO_DIR / "check").glob("*.toml"))]:
        out.add(signature(_core.load_scenario(str(path))))
    return out


def refuse_benchmark(scenarios: list[Any], forbidden: set[tuple]) -> None:
    """ValueError naming the first scenario whose faults are a benchmark scenario's."""
    for i, s in enumerate(scenarios):
        if signature(s) in forbidden:
            raise ValueError(f"training draw {i} has the faults of a benchmark scenario "
                             f"({s!r}): the training distribution must be disjoint from it")
