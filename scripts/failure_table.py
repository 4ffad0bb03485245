#!/usr/bin/env python3
"""Where a method fails, measured: a result file of its worst cells.

    .venv/bin/python scripts/failure_table.py runs/benchmark-A runs/benchmark-C \\
        --methods learned-mpc ppo-learned --out docs/results/learned_failures.csv

For each method, from the benchmark directories' results.csv (the union of
their cells; ``oracle-mpc`` must have run in one of them): a summary row
(mean fraction of ``oracle-mpc`` over the scenario-intervals, the worst
interval, the worst scenario-interval, the median run's wall time), then its
``--worst`` worst scenario-intervals (fraction, mean over seeds), each with
what its model got wrong there: the one-step prediction error (RMSE over the
interval's steps, and the largest single error), beside the method's median
over all its cells, and the fraction of valves it opened. The methods whose
runs report no prediction error leave those columns blank.

scripts/render_results.py renders the file as a table (docs/controller.md).
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics as st
import sys
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))
sys.path.insert(0, str(REPO / "python"))

from suite_results import write_result_file  # noqa: E402

ORACLE = "oracle-mpc"


def _number(value: str) -> float | None:
    return float(value) if value not in ("", None) else None


def read(dirs: list[Path]) -> tuple[dict, dict, list[dict]]:
    """(cells: (scenario, method, seed, interval) -> row, wall times by
    (method, scenario, seed), provenance per directory)."""
    cells, walls, meta = {}, {}, []
    for d in dirs:
        if not (d / "results.csv").is_file() or not (d / "benchmark.json").is_file():
            raise SystemExit(f"failure_table: {d} holds no benchmark results "
                             "(results.csv and benchmark.json)")
        meta.append(json.loads((d / "benchmark.json").read_text()))
        with open(d / "results.csv", newline="") as f:
            for r in csv.DictReader(f):
                cells[(r["scenario"], r["method"], int(r["seed"]), int(r["interval"]))] = r
        for run in json.loads((d / "results.json").read_text())["runs"]:
            if run.get("wall_time_s") is not None:
                walls[(run["method"], run["scenario"], int(run["seed"]))] = run["wall_time_s"]
    return cells, walls, meta


def table(cells: dict, walls: dict, methods: list[str], worst: int) -> list[dict]:
    out = []
    for method in methods:
        by_cell: dict[tuple, list] = defaultdict(list)  # (scenario, interval) -> seed rows
        for (scenario, m, seed, interval), r in cells.items():
            oracle = cells.get((scenario, ORACLE, seed, interval))
            if m != method or oracle is None:
                continue
            by_cell[(scenario, interval)].append(
                (seed, float(r["reward_per_step"]) / float(oracle["reward_per_step"]), r))
        if not by_cell:
            raise SystemExit(f"failure_table: no cell of {method} beside {ORACLE}")
        fraction = {k: st.mean(f for _, f, _ in v) for k, v in by_cell.items()}
        intervals = sorted({i for _, i in fraction})
        per_interval = {i: st.mean(f for (s, j), f in fraction.items() if j == i)
                        for i in intervals}
        rmses = [x for v in by_cell.values() for _, _, r in v
                 if (x := _number(r.get("model_one_step_rmse", ""))) is not None]
        typical = st.median(rmses) if rmses else None
        worst_interval = min(per_interval, key=per_interval.get)
        worst_cell = min(fraction, key=fraction.get)
        runs = [w for (m, _, _), w in walls.items() if m == method]
        out.append({"method": method, "cell": "all", "fraction": f"{st.mean(fraction.values()):.3f}",
                    "seeds": "", "worst interval": f"{per_interval[worst_interval]:.3f} "
                    f"(interval {worst_interval})", "worst scenario-interval":
                    f"{fraction[worst_cell]:.3f} ({worst_cell[0]}, interval {worst_cell[1]})",
                    "model rmse, mm": _mm(typical), "largest error, mm": "",
                    "open fraction": "", "median run, s": f"{st.median(runs):.0f}" if runs else ""})
        for key in sorted(fraction, key=fraction.get)[:worst]:
            rows = sorted(by_cell[key], key=lambda t: t[0])
            rm = [x for _, _, r in rows if (x := _number(r.get("model_one_step_rmse", ""))) is not None]
            mx = [x for _, _, r in rows if (x := _number(r.get("model_max_step_error", ""))) is not None]
            op = [x for _, _, r in rows if (x := _number(r.get("open_fraction", ""))) is not None]
            out.append({"method": method, "cell": f"{key[0]}, interval {key[1]}",
                        "fraction": f"{fraction[key]:.3f}",
                        "seeds": " / ".join(f"{f:.3f}" for _, f, _ in rows),
                        "worst interval": "", "worst scenario-interval": "",
                        "model rmse, mm": _mm(st.mean(rm) if rm else None),
                        "largest error, mm": _mm(max(mx) if mx else None),
                        "open fraction": f"{st.mean(op):.3f}" if op else "",
                        "median run, s": ""})
    return out


def _mm(metres: float | None) -> str:
    return "" if metres is None else f"{1000 * metres:.1f}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dirs", nargs="+", type=Path, metavar="DIR",
                   help="benchmark run directories (ftc.experiments benchmark --out DIR)")
    p.add_argument("--methods", nargs="+", required=True, help="the methods to explain")
    p.add_argument("--worst", type=int, default=3, help="worst scenario-intervals per method")
    p.add_argument("--out", type=Path, required=True, help="the result file to write")
    args = p.parse_args(argv)
    cells, walls, meta = read(args.dirs)
    rows = table(cells, walls, args.methods, args.worst)
    text = ""
    for info in meta:
        c = info["config"]
        text += (f"# what: {len(c['scenarios'])} scenarios x {len(c['seeds'])} seeds, "
                 f"{c['intervals']} x {c['steps_per_interval']} steps, fraction of {ORACLE}, "
                 f"worst cells with the model's one-step prediction error\n"
                 f"# command: ftc.experiments benchmark --methods {' '.join(c['methods'])} "
                 f"--seeds {' '.join(map(str, c['seeds']))} --jobs {info.get('jobs', '?')}\n"
                 f"# commit: {info.get('git_revision', '?')}\n"
                 f"# date: {info.get('created', '?')[:10]}\n")
    write_result_file(args.out, text, rows)
    print(f"failure_table: {len(rows)} rows -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
