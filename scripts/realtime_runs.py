#!/usr/bin/env python3
"""One line per controller run: the plant's rate (lockstep or real time), the
seed, the mean reward per step online and in evaluation over the intervals,
the last interval's, and, for real-time runs, the deadlines summed over the
intervals (misses, the plant's own count, watchdog trips, lost states) and
the worst interval's latency p99 and max.

    .venv/bin/python scripts/realtime_runs.py runs/lock-s0 runs/rt10-s0 ... \\
        [--results docs/results/realtime_learning.csv --command "how the runs were made"]

What it compares: a real-time run's results against lockstep runs of the
same command (docs/deploy.md, "Measured").
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))


def summary(run: Path) -> dict[str, str]:
    """The run's line; SystemExit naming the file that is missing or broken."""
    try:
        with open(run / "metrics.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        config = json.loads((run / "config.json").read_text())
    except (OSError, ValueError) as e:
        raise SystemExit(f"realtime_runs: {run}: {e}")
    if not rows:
        raise SystemExit(f"realtime_runs: {run}/metrics.csv has no interval")
    part = next(v for v in config.values() if isinstance(v, dict) and "seed" in v)

    def mean(column: str) -> str:
        return f"{statistics.mean(float(r[column]) for r in rows):.4f}"

    line = {"run": run.name, "rate_hz": f"{part.get('realtime') or 0:g}",
            "seed": str(config.get("seed", part["seed"])), "intervals": str(len(rows)),
            "online_reward": mean("reward_per_step"), "eval_reward": mean("eval_reward_per_step"),
            "last_interval_reward": f"{float(rows[-1]['reward_per_step']):.4f}"}
    timed = "deadline_misses" in rows[0]
    for column in ("deadline_misses", "plant_missed_ticks", "watchdog_trips", "lost_states"):
        line[column] = str(sum(int(r[column]) for r in rows)) if timed else ""
    for column in ("latency_p99_ms", "latency_max_ms"):
        line[f"worst_{column}"] = (f"{max(float(r[column]) for r in rows):.2f}" if timed else "")
    return line


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", type=Path, nargs="+", help="run directories (metrics.csv, config.json)")
    p.add_argument("--results", type=Path, help="write the table as a result file")
    p.add_argument("--command", default="", help="how the runs were made (the file's record)")
    args = p.parse_args(argv)
    lines = [summary(run) for run in args.runs]
    commits = sorted({json.loads((run / "config.json").read_text()).get("git_revision", "?")
                      for run in args.runs})
    print(",".join(lines[0]))
    for line in lines:
        print(",".join(line.values()))
    if args.results:
        from suite_results import write_result_file

        write_result_file(args.results, (
            "# what: controller runs in lockstep (rate 0) and on the plant in real time, "
            "means over the intervals; deadlines summed over them\n"
            f"# command: {args.command or 'scripts/realtime_runs.py'}\n"
            f"# commit: {' '.join(commits)}\n"), lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
