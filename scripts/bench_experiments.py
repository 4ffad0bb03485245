#!/usr/bin/env python3
"""Benchmark of the experiments pipeline: wall time of an `all` reproduction
with --jobs 1 and --jobs 2 (or any list), and the speed-up.

    .venv/bin/python scripts/bench_experiments.py              # the full paper protocol
    .venv/bin/python scripts/bench_experiments.py --reduced    # a check in a few minutes

The full protocol (3 experiments, 20 aggregate trials, 4 methods, 10
intervals of 512 steps) takes long with --jobs 1; every run directory is kept
under --work so a stopped benchmark can be inspected. Each measurement is a
fresh `python -m ftc.experiments all` in its own directory; the time includes
the figures and report.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def run_all(out: Path, jobs: int, extra: list[str]) -> float:
    """Wall time (s) of one `all` run into out with the given jobs."""
    cmd = [sys.executable, "-m", "ftc.experiments", "all", "--out", str(out), "--jobs", str(jobs),
           *extra]
    print("$ " + " ".join(cmd), flush=True)
    start = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"bench_experiments: `all` with --jobs {jobs} failed "
                         f"(exit {proc.returncode}); see {out}")
    return wall


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--jobs", type=int, nargs="+", default=[1, 2],
                        help="job counts to measure (the first is the speed-up's reference)")
    parser.add_argument("--reduced", action="store_true",
                        help="2 trials, 2 intervals of 64 steps, small offline budget: checks "
                             "the script in minutes instead of measuring the reproduction")
    parser.add_argument("--work", type=Path, default=REPO / "runs" / "bench",
                        help="directory for the benchmark's run directories")
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = parser.parse_args()
    if args.reduced:
        extra = ["--trials", "2", "--intervals", "2", "--steps-per-interval", "64",
                 "--controller-args", "--update-every 32 --model-episodes 4 --offline-steps 128"]
        label = "reduced (2 trials, 2 x 64 steps)"
    else:
        extra = ["--full"]
        label = "full paper protocol (20 trials, 10 x 512 steps)"
    stamp = time.strftime("%Y%m%d-%H%M%S")
    times = {}
    for jobs in args.jobs:
        times[jobs] = run_all(args.work / f"{stamp}-jobs{jobs}", jobs, extra)
        print(f"jobs {jobs}: {times[jobs]:.1f} s", flush=True)
    ref = args.jobs[0]
    print(f"\n`python -m ftc.experiments all`, {label}, {os.cpu_count()} cores")
    print("| jobs | wall time (s) | speed-up |\n|---|---|---|")
    for jobs, wall in times.items():
        print(f"| {jobs} | {wall:.1f} | {times[ref] / wall:.2f} |")
    if args.json:
        args.json.write_text(json.dumps({"protocol": label, "cores": os.cpu_count(),
                                         "wall_time_s": times}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
