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

With ``--min-gain G`` the set is also well conditioned: a per-scenario
score divides by the reference's gain over all-closed, so where all-closed
is nearly optimal one cell decides it. The script then draws ``--candidates``
scenarios, runs the benchmark's reference and all-closed on them (every
plant seed of ``--seeds``, ``python -m ftc.experiments benchmark --methods
closed --link core``), keeps the first ``--count`` whose reference earns at
least G more per step than all-closed over intervals 1-9 on every seed (the
suite's smallest gain is 0.315), deletes the others, and writes their
rewards, trimmed as ``scenarios/reference/*.csv`` are, to ``--rewards-out``
for ``ftc.experiments.adaptive evaluate --heldout-results``.

Draw the set once, before any choice is made on it, and score on it last:
a set that chose among methods is a development set (docs/adaptive.md).
Exit codes: 0 drawn, 2 bad input, 1 the benchmark failed or too few
candidates met the gain (the kept files and the rewards are then not
written).
"""

from __future__ import annotations

import argparse
import csv
import io
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from ftc import _core
from ftc.common.atomic import atomic_write_text
from ftc.common.constants import NUM_ENGINES, NUM_TANKS
from ftc.experiments.adaptive import distribution, evaluate
from ftc.experiments.adaptive.evaluate import FIRST_SCORED, benchmark_rewards
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


def well_conditioned(rewards: dict, names: list[str], seeds: list[int], count: int,
                     min_gain: float) -> tuple[list[str], dict[str, float]]:
    """(the first ``count`` of ``names`` whose reference beats all-closed by at
    least ``min_gain`` per step over intervals 1-9 on every seed, in order;
    each name's smallest gain over the seeds), from ``benchmark_rewards``'
    layout. A name or seed without both methods' rewards is an error."""
    gains: dict[str, float] = {}
    for name in names:
        cells = rewards.get(name, {}).get("rewards", {})
        per_seed = []
        for seed in seeds:
            try:
                ref, closed = (np.asarray(cells[m][str(seed)], np.float64)
                               for m in ("reference", "closed"))
            except KeyError:
                raise ValueError(f"no reference and closed rewards of {name}, seed {seed}") \
                    from None
            per_seed.append(float(evaluate.gains(ref[None], closed[None])[0])
                            / (len(ref) - FIRST_SCORED))
        gains[name] = min(per_seed)
    return [n for n in names if gains[n] >= min_gain][:count], gains


def trimmed_rewards(results_csv: Path, names: list[str], reference: str = "reference") -> str:
    """The benchmark's ``reference`` (named "reference") and closed cells of
    ``names``: scenario, method, seed, interval, reward_per_step (the columns
    ``evaluate.benchmark_rewards`` reads)."""
    columns = ["scenario", "method", "seed", "interval", "reward_per_step"]
    out = io.StringIO()
    writer = csv.DictWriter(out, columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    with open(results_csv, newline="") as f:
        for row in csv.DictReader(line for line in f if not line.startswith("#")):
            if row["scenario"] in names and row["method"] in (reference, "closed"):
                writer.writerow({**row, "method": "reference" if row["method"] == reference
                                 else "closed"})
    return out.getvalue()


def training_signatures() -> set[tuple]:
    """The fault signatures of every plant the default training draws."""
    return {distribution.signature(s)
            for drawn in distribution.training_draws(distribution.load(), TrainingConfig())
            for s in drawn}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    p.add_argument("--seed", type=int, required=True, help="numpy seed of the draw")
    p.add_argument("--count", type=int, default=10, help="scenarios to draw (default 10)")
    p.add_argument("--prefix", default="final", help="scenario names: PREFIX-00, ...")
    p.add_argument("--out", type=Path, required=True, help="directory for the .toml files")
    p.add_argument("--seeds", type=int, nargs="+", default=[5, 6],
                   help="the plant seeds the set is meant for, written in each file's header "
                        "(and run by the benchmark with --min-gain; default 5 6)")
    p.add_argument("--min-gain", type=float, default=None,
                   help="keep only scenarios where the reference earns at least this much more "
                        "per step than all-closed over intervals 1-9 on every seed (runs the "
                        "benchmark; the suite's smallest is 0.315); default: no such rule")
    p.add_argument("--candidates", type=int, default=None,
                   help="with --min-gain: scenarios drawn and run (default 2 x --count)")
    p.add_argument("--rewards-out", type=Path, default=None,
                   help="with --min-gain: the kept scenarios' reference and closed rewards "
                        "(CSV, as scenarios/reference/*.csv; required with --min-gain)")
    p.add_argument("--reference", default="reference",
                   help="with --min-gain: the benchmark's reference method (default: reference; "
                        "a cheaper one only to try the script)")
    p.add_argument("--jobs", type=int, default=None, help="with --min-gain: benchmark runs in "
                                                          "parallel (default: the cores)")
    a = p.parse_args(argv)
    if a.count < 1:
        p.error("--count must be >= 1")
    if a.min_gain is not None and a.rewards_out is None:
        p.error("--min-gain needs --rewards-out FILE")
    if a.min_gain is None and (a.candidates is not None or a.rewards_out is not None):
        p.error("--candidates and --rewards-out go with --min-gain")
    drawn = a.count if a.min_gain is None else (a.candidates or 2 * a.count)
    if drawn < a.count:
        p.error(f"--candidates ({drawn}) must be >= --count ({a.count})")
    forbidden = distribution.benchmark_signatures() | training_signatures()
    dist = distribution.load()  # the plants' life: the training distribution's
    life_steps = dist.life_intervals * dist.steps_per_interval
    rng = np.random.default_rng(a.seed)
    a.out.mkdir(parents=True, exist_ok=True)
    seeds = " ".join(str(v) for v in a.seeds)
    rule = ("" if a.min_gain is None else
            f"\n# The reference beats all-closed by >= {a.min_gain} per step on every seed.")
    paths = []
    for i in range(drawn):
        name = f"{a.prefix}-{i:02d}"
        path = a.out / f"{name}.toml"
        while True:
            text = draw_one(rng, name, life_steps)
            path.write_text(text)
            if distribution.signature(_core.load_scenario(str(path))) not in forbidden:
                break
        header = (f"# Held-out check of the adaptive policy (docs/adaptive.md), drawn by\n"
                  f"# scripts/draw_heldout.py --seed {a.seed} for the last check only (plant\n"
                  f"# seeds {seeds}): in no training draw, suite or check set.{rule}\n")
        path.write_text(header + text)
        paths.append(path)
    if a.min_gain is not None:
        return _keep_well_conditioned(a, paths)
    for path in paths:
        print(f"draw_heldout: {path}")
    return 0


def _keep_well_conditioned(a: argparse.Namespace, paths: list[Path]) -> int:
    """Run the benchmark on the candidates ``paths``; keep the first --count
    that meet --min-gain (the others deleted) and write their rewards."""
    with tempfile.TemporaryDirectory(prefix="draw_heldout-") as tmp:
        command = [sys.executable, "-m", "ftc.experiments", "benchmark", "--methods", "closed",
                   "--reference", a.reference, "--link", "core", "--out", tmp,
                   "--seeds", *(str(v) for v in a.seeds), "--scenarios", *(str(p) for p in paths)]
        if a.jobs:
            command += ["--jobs", str(a.jobs)]
        print(f"draw_heldout: running the {a.reference} and all-closed on {len(paths)} "
              f"candidates, seeds {' '.join(str(v) for v in a.seeds)}", flush=True)
        done = subprocess.run(command)
        results = Path(tmp) / "results.csv"
        if done.returncode != 0 or not results.is_file():
            for path in paths:
                path.unlink()
            print(f"draw_heldout: error: the benchmark exited {done.returncode} (the candidates "
                  f"were removed)", file=sys.stderr)
            return 1
        names = [p.stem for p in paths]
        trimmed = Path(tmp) / "trimmed.csv"  # the cells as the rule and evaluate read them
        trimmed.write_text(trimmed_rewards(results, names, a.reference))
        rewards = benchmark_rewards(trimmed)
        kept, gains = well_conditioned(rewards, names, a.seeds, a.count, a.min_gain)
        for name in names:
            fate = ("" if name in kept else " (dropped: below --min-gain)"
                    if gains[name] < a.min_gain else " (dropped: --count already kept)")
            print(f"draw_heldout: {name}: the reference's gain over closed "
                  f"{gains[name]:.3f} per step{fate}")
        if len(kept) < a.count:
            for path in paths:
                path.unlink()
            print(f"draw_heldout: error: {len(kept)} of {len(paths)} candidates have a gain of "
                  f">= {a.min_gain}, {a.count} needed: draw more (--candidates)", file=sys.stderr)
            return 1
        for path in paths:
            if path.stem not in kept:
                path.unlink()
        text = trimmed_rewards(results, kept, a.reference)
    header = (f"# The reference's and all-closed's reward per step on {a.out}/*.toml, each "
              f"seed and interval:\n# the cells of `python -m ftc.experiments benchmark "
              f"--methods closed --reference {a.reference} --seeds "
              f"{' '.join(str(v) for v in a.seeds)} --link core` on them, trimmed to these "
              f"columns\n# (scripts/draw_heldout.py --seed {a.seed} --min-gain {a.min_gain}). "
              f"`python -m ftc.experiments.adaptive evaluate --heldout-results` reads it.\n")
    a.rewards_out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(a.rewards_out, header + text)
    for name in kept:
        print(f"draw_heldout: {a.out / (name + '.toml')}")
    print(f"draw_heldout: {a.rewards_out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
