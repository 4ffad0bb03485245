#!/usr/bin/env python3
"""Draw a held-out set of fault scenarios for the adaptive policy's last check.

Usage:
    .venv/bin/python scripts/draw_heldout.py --seed 20261206 --count 10 \\
        --prefix final --out scenarios/heldout/final

Each scenario mixes what the field calls faults, at random: up to two worn
tanks (a factor in [5, 35]) and up to one worn engine ([10, 35]), stepwise or
continuous wear, sensor noise (std in [0, 0.006] m) in a fifth of them, and up
to three abrupt events within the life (a valve stuck open or closed, or a
component's factor jumping to [3, 10]). A draw that has the faults of a
benchmark scenario or of any plant the default training could draw (every
member's every DAgger iteration, ``ftc.experiments.adaptive.distribution``)
is drawn again, so the set is disjoint from both; the files name the seed.

Draw the set once, before any choice is made on it, and score on it last:
a set that chose among methods is a development set (docs/adaptive.md).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ftc import _core
from ftc.common.constants import NUM_ENGINES, NUM_TANKS
from ftc.experiments.adaptive import distribution
from ftc.learning.history_policy import TrainingConfig

def draw_one(rng: np.random.Generator, name: str, life_steps: int) -> str:
    """One scenario's TOML text."""
    tanks = [float("inf")] * NUM_TANKS
    for i in rng.choice(NUM_TANKS, size=rng.integers(0, 3), replace=False):
        tanks[int(i)] = round(float(rng.uniform(5.0, 35.0)), 1)
    engines = [float("inf")] * NUM_ENGINES
    if rng.random() < 0.5:
        engines[int(rng.integers(NUM_ENGINES))] = round(float(rng.uniform(10.0, 35.0)), 1)
    lines = [f'name = "{name}"',
             f"tank_factor = [{', '.join(_num(v) for v in tanks)}]",
             f"engine_factor = [{', '.join(_num(v) for v in engines)}]",
             f'degradation = "{"continuous" if rng.random() < 0.3 else "stepwise"}"',
             "steps_per_interval = 512"]
    if rng.random() < 0.2:
        lines += ["", "[noise]", f"std = {float(rng.uniform(0.0, 0.006)):.4f}"]
    stuck: set[int] = set()
    for at in sorted(int(a) for a in rng.integers(512, life_steps - 512, rng.integers(0, 4))):
        lines += ["", "[[event]]", f"at_step = {at}"]
        free = [v for v in range(1, NUM_TANKS + 1) if v not in stuck]
        if rng.random() < 0.5 and free:
            valve = int(rng.choice(free))
            stuck.add(valve)
            lines += [f"stuck_valve = {valve}",
                      f'state = "{"open" if rng.random() < 0.5 else "closed"}"']
        elif rng.random() < 0.5:
            lines += [f"engine = {int(rng.integers(1, NUM_ENGINES + 1))}",
                      f"factor = {float(rng.uniform(3.0, 10.0)):.1f}"]
        else:
            lines += [f"tank = {int(rng.integers(1, NUM_TANKS + 1))}",
                      f"factor = {float(rng.uniform(3.0, 10.0)):.1f}"]
    return "\n".join(lines) + "\n"


def _num(v: float) -> str:
    return "inf" if not np.isfinite(v) else f"{v:.1f}"


def training_signatures() -> set[tuple]:
    """The fault signatures of every plant the default training draws."""
    dist, config = distribution.load(), TrainingConfig()
    signatures: set[tuple] = set()
    for member in range(config.members):
        seed = config.seed + member
        for k in range(config.iterations):
            signatures |= {distribution.signature(s)
                           for s in distribution.draw(dist, config.envs, seed * 1000 + k)}
    return signatures


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    p.add_argument("--seed", type=int, required=True, help="numpy seed of the draw")
    p.add_argument("--count", type=int, default=10, help="scenarios to draw (default 10)")
    p.add_argument("--prefix", default="final", help="scenario names: PREFIX-00, ...")
    p.add_argument("--out", type=Path, required=True, help="directory for the .toml files")
    p.add_argument("--seeds", default="5 6", help="the plant seeds the set is meant for, "
                                                  "written in each file's header")
    a = p.parse_args(argv)
    if a.count < 1:
        p.error("--count must be >= 1")
    forbidden = distribution.benchmark_signatures() | training_signatures()
    dist = distribution.load()  # the plants' life: the training distribution's
    life_steps = dist.life_intervals * dist.steps_per_interval
    rng = np.random.default_rng(a.seed)
    a.out.mkdir(parents=True, exist_ok=True)
    for i in range(a.count):
        name = f"{a.prefix}-{i:02d}"
        path = a.out / f"{name}.toml"
        while True:
            text = draw_one(rng, name, life_steps)
            path.write_text(text)
            if distribution.signature(_core.load_scenario(str(path))) not in forbidden:
                break
        header = (f"# Held-out check of the adaptive policy (docs/adaptive.md), drawn by\n"
                  f"# scripts/draw_heldout.py --seed {a.seed} for the last check only (plant\n"
                  f"# seeds {a.seeds}): in no training draw, suite or check set.\n")
        path.write_text(header + text)
        print(f"draw_heldout: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
