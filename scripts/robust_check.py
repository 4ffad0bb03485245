#!/usr/bin/env python3
"""Fractions of oracle-mpc per scenario and interval, from finished runs: the
table of docs/controller.md's "Faults that change the plant's form".

    .venv/bin/python scripts/robust_check.py --oracle ROOT --method identified-mpc=ROOT ...
        [--label after] [--results docs/results/robust_check.csv --what TEXT --command TEXT]

A ROOT holds runs as ``ftc.experiments benchmark`` lays them out
(``runs/<scenario>/t00/<method>/s<seed>/metrics.csv``) or as
``<method>/<scenario>/s<seed>/metrics.csv`` or ``<scenario>/s<seed>/metrics.csv``.
For every scenario and seed the method and the oracle both finished (10
intervals), the method's reward per step over the oracle's in each interval;
the table gives the mean over those seeds per interval, the worst interval of
1-9 and the mean over 1-9. Prints the table; --results writes it as a result
file (provenance lines first) for scripts/render_results.py.
"""

from __future__ import annotations

import argparse
import csv
import platform
import subprocess
import sys
from datetime import date
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def rewards(root: Path, method: str) -> dict[tuple[str, int], np.ndarray]:
    """(scenario, seed) -> reward per step per interval, for the finished runs under root."""
    out = {}
    for path in root.rglob("metrics.csv"):
        if path.parent.name == "controller":
            continue  # a benchmark run's copy of the controller's own file
        parts = path.relative_to(root).parts
        seed = int(parts[-2].removeprefix("s"))
        if ("runs" in parts or len(parts) >= 4) and method not in parts:
            continue  # another method's run (the benchmark's layout, or <method>/<scenario>/...)
        scenario = parts[parts.index("runs") + 1] if "runs" in parts else parts[-3]
        with open(path) as f:
            rows = list(csv.DictReader(f))
        if len(rows) >= 10 and all(r["reward_per_step"] for r in rows):
            out[(scenario, seed)] = np.array([float(r["reward_per_step"]) for r in rows])
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--oracle", type=Path, required=True, help="root of the oracle-mpc runs")
    p.add_argument("--method", action="append", required=True, metavar="NAME=ROOT",
                   help="a method's name and the root of its runs (repeatable)")
    p.add_argument("--label", default="", help="appended to the method's name in the table")
    p.add_argument("--results", type=Path, help="write the table here as a result file")
    p.add_argument("--what", default="", help="the result file's 'what' line")
    p.add_argument("--command", default="", help="the result file's 'command' line")
    args = p.parse_args()
    oracle = rewards(args.oracle, "oracle-mpc")
    if not oracle:
        print(f"robust_check: no finished oracle-mpc run under {args.oracle}", file=sys.stderr)
        return 2
    head = ["method", "scenario", "seeds", *[f"interval {k}" for k in range(10)],
            "worst 1-9", "mean 1-9"]
    lines = []
    for spec in args.method:
        name, _, root = spec.partition("=")
        runs = rewards(Path(root), name)
        for scenario in sorted({s for s, _ in runs}):
            seeds = sorted(k for s, k in runs if s == scenario and (s, k) in oracle)
            if not seeds:
                continue
            frac = np.mean([runs[(scenario, k)][:10] / oracle[(scenario, k)][:10]
                            for k in seeds], axis=0)
            lines.append([f"{name}{' ' + args.label if args.label else ''}", scenario,
                          " ".join(map(str, seeds)), *[f"{x:.3f}" for x in frac],
                          f"{frac[1:].min():.3f} (interval {int(np.argmin(frac[1:])) + 1})",
                          f"{frac[1:].mean():.3f}"])
    text = [",".join(head)] + [",".join(f'"{c}"' if "," in c else c for c in r) for r in lines]
    print("\n".join(text))
    if args.results:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True,
                                text=True).stdout.strip()
        cpu = next((l.split(":", 1)[1].strip() for l in Path("/proc/cpuinfo").read_text()
                    .splitlines() if l.startswith("model name")), platform.processor())
        meta = [f"# what: {args.what}", f"# command: {args.command}", f"# commit: {commit}",
                f"# date: {date.today().isoformat()}", f"# machine: {cpu}, 2 cores"]
        mode = "a" if args.results.exists() else "w"
        with open(args.results, mode) as f:
            f.write("\n".join((meta if mode == "w" else []) + (text if mode == "w" else text[1:]))
                    + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
