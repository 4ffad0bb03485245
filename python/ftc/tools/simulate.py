"""Trajectory export: drive the real plant process over LCM with a fixed
policy and write one CSV row per control step.

    python -m ftc.simulate --scenario scenarios/single.toml --policy random \\
        --seed 1 --steps 2000 --out traj.csv

Columns: episode,step,age,u1..u6,x1..x6. ``step`` counts from 1 in each
episode, ``age`` is the degradation age (intervals) in force during the step,
``u`` the valves applied, ``x`` the true (noise-free) levels after the step.
Every episode starts from full tanks; the plant cuts the running episode at
each interval boundary. Anyone can check the physics against an independent
simulation of docs/plant-model.md with this file.

An existing --out is refused unless --overwrite; while the tool runs,
.NAME.lock beside --out keeps a second writer out.

Exit codes: 2 bad input (a flag, the scenario file, an --out that exists, is
a directory, cannot be written or is being written by another run), checked
before the plant starts; 1 the plant
failed or stopped answering; 5 the CSV could not be written (disk full): one
line naming the path, no partial or temporary file left.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ftc.common.atomic import atomic_write_csv
from ftc.common.cli import OneLineParser, at_least, check_out_file, checked
from ftc.common.errors import RunError
from ftc.common.lifetime import Stopped, stop_signals, stopped_line
from ftc.common.paths import scenario_file
from ftc.common.run_lock import RunLock, refuse_existing
from ftc.control.baselines import BASELINES, baseline_valves
from ftc.control.config import MAX_STEPS_PER_INTERVAL
from ftc.plant import PlantError, launch, trajectory

POLICIES = BASELINES
HEADER = trajectory.header()
MAX_STEPS = 100_000_000  # control steps of one export (~10 GB of CSV)


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


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="python -m ftc.simulate", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1].rsplit("\n\nExit codes", 1)[0])
    parser.add_argument("--scenario", type=checked(str, nonempty=True), default=None,
                        help="fault scenario: a packaged one's name (single, multiple, nominal, "
                             "abrupt) or a TOML file (default: nominal plant)")
    parser.add_argument("--policy", choices=POLICIES, default="closed",
                        help="valves all closed, all open, or uniformly random each step")
    parser.add_argument("--seed", type=checked(int, at_least(0, 2**63 - 1)), default=0,
                        help="seed of the random policy and plant")
    parser.add_argument("--steps", type=checked(int, at_least(1, MAX_STEPS)), default=1000,
                        help="control steps to simulate")
    parser.add_argument("--out", type=checked(Path, nonempty=True), required=True,
                        help="CSV file to write")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing --out file (atomically, once the new one is "
                             "complete; default: refuse it)")
    parser.add_argument("--steps-per-interval",
                        type=checked(int, at_least(1, MAX_STEPS_PER_INTERVAL)), default=None,
                        help="override the scenario's steps per degradation interval")
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The options, all checked (scenario file parsed, --out writable and not a
    directory) before the plant starts; bad input exits 2 with one line."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.scenario is not None:
        try:
            args.scenario = Path(scenario_file(args.scenario))
        except ValueError as e:
            parser.error(f"--scenario: {e}")
        if not args.scenario.is_file():
            parser.error(f"--scenario: no such file: {args.scenario}")
        from ftc import _core  # native: the plant's own scenario parser

        try:
            _core.load_scenario(str(args.scenario))
        except _core.ScenarioError as e:  # names the file and the key
            parser.error(f"--scenario: {e}")
    check_out_file(parser, args.out, args.overwrite, "the CSV file")  # nothing created
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    extra = ([] if args.steps_per_interval is None
             else ["--steps-per-interval", str(args.steps_per_interval)])
    try:
        with stop_signals(), RunLock(args.out, "ftc.simulate", beside=True) as lock:
            lock.announce_takeover()
            refuse_existing(args.out, args.overwrite)  # again, now that no one else writes
            n = run(str(args.scenario) if args.scenario else None, args.policy, args.seed,
                    args.steps, args.out, extra)
    except (KeyboardInterrupt, Stopped) as e:  # the plant shut down, nothing written
        line, code = stopped_line("ftc.simulate", e, f"; nothing written to {args.out}")
        print(f"\n{line}", file=sys.stderr)
        return code
    except PlantError as e:
        print(f"ftc.simulate: error: {e}", file=sys.stderr)
        return 2 if e.exit_code == 2 else 1
    except RunError as e:  # StorageError: the CSV could not be written (exit 5)
        print(f"ftc.simulate: error: {e}", file=sys.stderr)
        return e.exit_code
    print(f"wrote {n} steps to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
