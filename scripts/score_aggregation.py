#!/usr/bin/env python3
"""Measure how the benchmark's normalized score is aggregated: the choice of
docs/benchmarks.md ("Scores and their intervals"), and its evidence.

    .venv/bin/python scripts/score_aggregation.py runs/bench-A [runs/bench-B ...] \\
        --out docs/results/aggregation.csv [--reference reference] [--worst random-19]

Reads the benchmark directories' cells (as scripts/suite_results.py does: a
reference run apart rebases the others) and, for every method, aggregates its
normalized score four ways:

* ``cell mean``: (r - closed) / (reference - closed) per (scenario, seed,
  interval) cell, then the mean over cells (the benchmark's original score);
* ``cell IQM``: the same cells, their interquartile mean;
* ``floor mean``: per cell with the denominator floored at ``--floor`` reward
  per step, the mean over cells;
* ``run mean`` and ``run IQM``: normalized per run (ftc.experiments.stats:
  intervals 1 on summed), the mean over scenarios of the mean over seeds, and
  the IQM of the runs.

Then drops each (scenario, seed, interval >= 1) cell in turn and records, per
method and aggregate, the largest move of the aggregate; and the ranks. A
second file (``--worst-out``) gives, for the scenario ``--worst``, each method's
per-cell scores by interval (mean over seeds) beside its per-run score.
"""

from __future__ import annotations

import argparse
import io
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
from scipy.stats import trim_mean

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "python"))
sys.path.insert(0, str(REPO / "scripts"))

from ftc.experiments import benchmark_report as br  # noqa: E402
from ftc.experiments import stats  # noqa: E402
from suite_results import read_cells, write_result_file  # noqa: E402

AGGREGATES = ("cell mean", "cell IQM", "floor mean", "run mean", "run IQM")


def _float_rows(rows: list[dict], reference: str) -> list[dict]:
    scored = br.normalized_scores([{**r, "reward_per_step": br._num(r["reward_per_step"])}
                                   for r in rows], reference)
    return [r for r in scored if r["interval"] >= 1 and r["reward_per_step"] is not None
            and r["reference_reward_per_step"] is not None
            and r["closed_reward_per_step"] is not None]


def _contributions(rows: list[dict], floor: float) -> dict[str, dict]:
    """method -> {"cells": {(scenario, seed, k): (score, floored score)},
    "runs": {(scenario, seed): {k: (r - closed, reference - closed)}}}."""
    out: dict = defaultdict(lambda: {"cells": {}, "runs": defaultdict(dict)})
    for r in rows:
        num = r["reward_per_step"] - r["closed_reward_per_step"]
        den = r["reference_reward_per_step"] - r["closed_reward_per_step"]
        key = (r["scenario"], int(r["seed"]), int(r["interval"]))
        cell = num / den if den != 0 else None
        out[r["method"]]["cells"][key] = (cell, num / max(den, floor))
        out[r["method"]]["runs"][key[:2]][key[2]] = (num, den)
    return out


def _aggregates(c: dict, drop: tuple | None = None) -> dict[str, float]:
    cells = [v for k, v in c["cells"].items() if k != drop]
    plain = np.array([v[0] for v in cells if v[0] is not None])
    floored = np.array([v[1] for v in cells])
    per_scenario: dict = defaultdict(list)
    for (scenario, seed), ks in c["runs"].items():
        kept = [v for k, v in ks.items() if drop is None or (scenario, seed, k) != drop]
        den = sum(v[1] for v in kept)
        if kept and den > 0:
            per_scenario[scenario].append(sum(v[0] for v in kept) / den)
    tasks = [np.array(v)[None, :] for v in per_scenario.values()]
    return {"cell mean": float(plain.mean()), "cell IQM": float(trim_mean(plain, 0.25)),
            "floor mean": float(floored.mean()), "run mean": float(stats.mean(tasks)[0]),
            "run IQM": float(stats.iqm(tasks)[0])}


def measure(rows: list[dict], floor: float) -> dict[str, dict]:
    """method -> {aggregate: value, aggregate + " max move": largest move when one
    cell is dropped, aggregate + " worst drop": that cell}."""
    out = {}
    for method, c in _contributions(rows, floor).items():
        base = _aggregates(c)
        moves = {a: (0.0, None) for a in AGGREGATES}
        for key in c["cells"]:
            dropped = _aggregates(c, key)
            for a in AGGREGATES:
                move = abs(dropped[a] - base[a])
                if move > moves[a][0]:
                    moves[a] = (move, key)
        out[method] = {**base, **{f"{a} max move": moves[a][0] for a in AGGREGATES},
                       **{f"{a} worst drop": moves[a][1] for a in AGGREGATES}}
    return out


def _ranks(measured: dict[str, dict], aggregate: str) -> dict[str, int]:
    order = sorted(measured, key=lambda m: -measured[m][aggregate])
    return {m: i + 1 for i, m in enumerate(order)}


def table(measured: dict[str, dict], methods: list[str]) -> list[dict]:
    ranks = {a: _ranks(measured, a) for a in AGGREGATES}
    out = []
    for m in methods:
        if m not in measured:
            continue
        row = {"method": m}
        for a in AGGREGATES:
            key = measured[m][f"{a} worst drop"]
            row[f"{a} (rank)"] = f"{measured[m][a]:.3f} ({ranks[a][m]})"
            row[f"{a}: largest move"] = f"{measured[m][f'{a} max move']:.3f}" + (
                "" if key is None else f" ({key[0]} s{key[1]} i{key[2]})")
        out.append(row)
    return out


def worst_table(rows: list[dict], scenario: str, methods: list[str],
                intervals: int) -> list[dict]:
    """Per method: the per-cell score of ``scenario`` per interval (mean over
    seeds) and its per-run score (mean over seeds)."""
    mine = [r for r in rows if r["scenario"] == scenario]
    runs = stats.run_scores(mine)
    out = []
    for m in methods:
        cells: dict = defaultdict(list)
        for r in mine:
            if r["method"] == m and r["normalized_score"] is not None:
                cells[r["interval"]].append(r["normalized_score"])
        if not cells:
            continue
        per_run = list(runs.get(m, {}).get(scenario, {}).values())
        out.append({"method": m, **{f"cell_{k}": f"{np.mean(cells[k]):.2f}" if cells[k] else ""
                                    for k in range(1, intervals)},
                    "run score": f"{np.mean(per_run):.3f}" if per_run else ""})
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dirs", nargs="+", type=Path, metavar="DIR")
    p.add_argument("--out", type=Path, required=True, help="the aggregates' result file")
    p.add_argument("--worst-out", type=Path, help="the --worst scenario's result file")
    p.add_argument("--worst", default="random-19", help="the scenario shown cell by cell")
    p.add_argument("--reference", default=br.REFERENCE)
    p.add_argument("--floor", type=float, default=0.05,
                   help="the floored per-cell denominator, reward per step (default 0.05)")
    args = p.parse_args(argv)
    raw, meta = read_cells(args.dirs)
    rows = _float_rows(raw, args.reference)
    methods = [m for m in dict.fromkeys(r["method"] for r in raw)
               if m not in (args.reference, br.CLOSED)]
    measured = measure([r for r in rows if r["method"] in methods], args.floor)
    scenarios = sorted({r["scenario"] for r in raw})
    seeds = sorted({int(r["seed"]) for r in raw})
    intervals = max(int(r["interval"]) for r in raw) + 1
    head = io.StringIO()
    head.write(f"# what: {len(scenarios)} scenarios x {len(seeds)} seeds, {intervals} "
               f"intervals, normalized score against {args.reference} and closed aggregated "
               f"five ways; each cell (scenario, seed, interval >= 1) dropped in turn, the "
               f"largest move; floor {args.floor}\n")
    head.write(f"# command: scripts/score_aggregation.py {' '.join(d.name for d in args.dirs)}\n")
    for info in meta:
        head.write(f"# commit: {info.get('git_revision', '?')}\n")
        head.write(f"# date: {info.get('created', '?')[:10]}\n")
    write_result_file(args.out, head.getvalue(), table(measured, methods))
    if args.worst_out:
        every = br.normalized_scores([{**r, "reward_per_step": br._num(r["reward_per_step"])}
                                      for r in raw], args.reference)
        what = (f"# what: {args.worst}, {len(seeds)} seeds, normalized score against "
                f"{args.reference} and closed per cell (interval 1-{intervals - 1}, mean over "
                "seeds) and per run (intervals 1 on summed, mean over seeds)\n")
        write_result_file(args.worst_out, what + head.getvalue().split("\n", 1)[1],
                          worst_table(every, args.worst, methods, intervals))
    print(f"score_aggregation: {len(methods)} methods, {len(rows)} cells -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
