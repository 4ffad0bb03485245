"""Trajectory export: drive the real plant process over LCM with a fixed
policy and write one CSV row per control step.

    python -m ftc.simulate --scenario scenarios/single.toml --policy random \\
        --seed 1 --steps 2000 --out traj.csv

Columns: episode,step,age,u1..u6,x1..x6. ``step`` counts from 1 in each
episode, ``age`` is the degradation age (intervals) in force during the step,
``u`` the valves applied, ``x`` the true (noise-free) levels after the step.
Every episode starts from full tanks; the plant cuts the running episode at
each interval boundary. Anyone can check the physics against an independent
simulation of ../shared/design/plant-model.md with this file.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ftc.common.atomic import atomic_write_csv
from ftc.common.cli import out_dir_problem
from ftc.control.baselines import BASELINES, baseline_valves
from ftc.plant import PlantError, launch, trajectory

POLICIES = BASELINES
HEADER = trajectory.header()


def _level(x: float) -> str:
    return f"{x:.12g}"


def run(scenario: str | None, policy: str, seed: int, steps: int, out: Path,
        extra_plant_args: list[str] | None = None) -> int:
    """Simulate and write ``out`` atomically; returns the number of rows."""
    rng = np.random.default_rng(seed)
    rows = []
    with launch(scenario, seed, extra_args=extra_plant_args or []) as plant:
        plant.reset()
        for _ in range(steps):
            u = baseline_valves(policy, rng)
            o = plant.step(u)
            rows.append(trajectory.row(o.episode, o.step, o.age, u, o.true_level,
                                       level_format=_level))
            if o.done:
                plant.reset()
    atomic_write_csv(out, HEADER, rows)
    return len(rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m ftc.simulate", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("--scenario", type=Path, default=None,
                        help="fault scenario TOML file (default: nominal plant)")
    parser.add_argument("--policy", choices=POLICIES, default="closed",
                        help="valves all closed, all open, or uniformly random each step")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random policy and plant")
    parser.add_argument("--steps", type=int, default=1000, help="control steps to simulate")
    parser.add_argument("--out", type=Path, required=True, help="CSV file to write")
    parser.add_argument("--steps-per-interval", type=int, default=None,
                        help="override the scenario's steps per degradation interval")
    args = parser.parse_args(argv)
    if args.steps <= 0:
        parser.error(f"--steps must be positive, got {args.steps}")
    if args.scenario is not None and not args.scenario.is_file():
        parser.error(f"--scenario: no such file: {args.scenario}")
    # An unwritable --out is an error before the plant starts; nothing is created.
    problem = out_dir_problem(args.out.resolve().parent)
    if problem:
        parser.error(f"--out {args.out}: cannot write there ({problem})")
    extra = ([] if args.steps_per_interval is None
             else ["--steps-per-interval", str(args.steps_per_interval)])
    try:
        n = run(str(args.scenario) if args.scenario else None, args.policy, args.seed,
                args.steps, args.out, extra)
    except PlantError as e:
        print(f"ftc.simulate: error: {e}", file=sys.stderr)
        return 2 if e.exit_code == 2 else 1
    print(f"wrote {n} steps to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
