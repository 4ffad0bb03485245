#!/usr/bin/env python3
"""How far the reference is above oracle-mpc, and how far any controller could
still be above the reference: a committed result file (docs/results/headroom.csv).

    .venv/bin/python scripts/headroom.py runs/bench-A [runs/bench-B ...] \\
        --out docs/results/headroom.csv

Reads the benchmark directories' results.csv (merged as scripts/suite_results.py
merges them: a cell given twice must agree) and their scenario files, and writes
one row per line of the table:

* the reference's reward per step over oracle-mpc's, mean over the scenarios
  (mean over seeds first) of intervals 1-9 and of each interval, then the
  scenario-intervals where it gains most and least;
* the bound: a controller that keeps every engine served earns at most the
  spread of the most outward balanced distribution of the fuel left,
  sigma_max(V), a step (the reward is (1 - |cg|/3) sigma - mean(u), and
  sigma_max falls as V grows), with the volume V falling by the whole demand
  every step. It is computed for the scenario-intervals where every pump can
  carry its engine's demand alone, so an engine goes short only when its
  whole wing is dry, a step that earns at most 0.67; with a weaker pump, fuel
  stranded in an outer tank can earn up to 3 a step and no bound is claimed;
* the cells where a method earns more than the reference by over 0.05%.

Exit 1 (naming them) if the reference earns less than oracle-mpc in any
scenario-interval, nothing written.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "python"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from suite_results import read_cells, write_result_file  # noqa: E402

ARMS = np.array([-3.0, -2.0, -1.0, 1.0, 2.0, 3.0])
WINGS = ((0, 1, 2), (3, 4, 5))  # tanks 1-3 feed engine 1, tanks 4-6 engine 2
TOLERANCE = 5e-4  # "beats the reference by more than 0.05%"


def sigma_max(volume: float) -> float:
    """The largest spread of a balanced distribution of ``volume`` m^3 over six
    1 m^3 tanks: half on each wing, the outer tanks filled first."""
    w, half = np.zeros(6), volume / 2
    for left, right in ((0, 5), (1, 4), (2, 3)):
        fill = min(1.0, half)
        w[left] = w[right] = fill
        half -= fill
    total = w.sum()
    if total < 1e-6:
        return 0.0
    return float(np.sqrt((w * ARMS ** 2).sum() / total))  # cg = 0


def volume_bound(demand: float, steps: int, capacity: float = 6.0,
                 tolerance: float = 1e-6) -> float:
    """Mean over ``steps`` steps of sigma_max(V) with V falling by ``demand`` m^3
    a step from full tanks, a new episode after the step that leaves V below the
    demand (the plant's termination rule)."""
    volume, total = capacity, 0.0
    for _ in range(steps):
        volume -= demand
        total += sigma_max(volume)
        if volume < demand + tolerance:
            volume = capacity
    return total / steps


def interval_bound(scenario_file: Path, interval: int, steps: int) -> float | None:
    """volume_bound at the interval's parameters, or None where a pump cannot
    carry its engine's demand alone."""
    from ftc import _core  # native: the scenario parser and degradation

    scenario = _core.load_scenario(str(scenario_file))
    params = _core.degraded_params(scenario, float(interval))
    pumps, demand = np.asarray(params["pump"]), np.asarray(params["demand"])
    if any(pumps[i] < demand[j] for j, wing in enumerate(WINGS) for i in wing):
        return None
    return volume_bound(float(demand.sum()), steps)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dirs", nargs="+", type=Path, metavar="DIR",
                   help="benchmark run directories holding reference and oracle-mpc runs")
    p.add_argument("--out", type=Path, required=True, help="the result file to write")
    p.add_argument("--top", type=int, default=5, help="scenario-intervals listed at each end")
    args = p.parse_args(argv)
    rows, meta = read_cells(args.dirs)
    cell: dict[tuple, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    for r in rows:  # (scenario, interval) -> method -> rewards over seeds
        if r["reward_per_step"] not in ("", None):
            cell[(r["scenario"], r["interval"])][r["method"]].append(float(r["reward_per_step"]))
    mean = {k: {m: float(np.mean(v)) for m, v in ms.items()} for k, ms in cell.items()}
    pairs = {k: v["reference"] / v["oracle-mpc"] - 1 for k, v in mean.items()
             if "reference" in v and "oracle-mpc" in v}
    if not pairs:
        raise SystemExit("headroom: no scenario-interval has both reference and oracle-mpc runs")
    below = sorted(k for k, g in pairs.items() if g < 0)
    if below:
        print("headroom: the reference earns less than oracle-mpc in "
              + ", ".join(f"{s} interval {i} ({pairs[(s, i)]:+.4%})" for s, i in below),
              file=sys.stderr)
        return 1
    config = meta[0]["config"]
    steps = int(config["steps_per_interval"])
    files = {stem: d / "scenarios" / f"{stem}.toml" for d in reversed(args.dirs)
             for stem in json.loads((d / "benchmark.json").read_text())["config"]["scenarios"]}
    bound = {k: interval_bound(files[k[0]], k[1], steps) for k in pairs}
    above = {k: [m for m, r in v.items() if m != "reference" and "reference" in v
                 and r > v["reference"] * (1 + TOLERANCE)] for k, v in mean.items()}

    def line(label: str, keys: list[tuple]) -> dict[str, str]:
        g = [pairs[k] for k in keys]
        b = [bound[k] / mean[k]["reference"] - 1 for k in keys if bound[k] is not None]
        return {"cells": label, "reference over oracle-mpc": f"{np.mean(g):+.2%}",
                "bound over reference": f"{np.mean(b):+.2%}" if b else "",
                "bound (reward per step)": (f"{np.mean([bound[k] for k in keys if bound[k]]):.3f}"
                                            if b else ""),
                "scenario-intervals": f"{len(keys)} ({len(b)} with a bound)"}

    late = sorted(k for k in pairs if k[1] >= 1)
    table = [line("intervals 1-9, mean", late)]
    table += [line(f"interval {i}, mean", [k for k in late if k[1] == i])
              for i in sorted({k[1] for k in late})]
    ranked = sorted(late, key=lambda k: (-pairs[k], k))
    table += [line(f"most: {s}, interval {i}", [(s, i)]) for s, i in ranked[:args.top]]
    table += [line(f"least: {s}, interval {i}", [(s, i)]) for s, i in ranked[::-1][:args.top]]
    over = sorted((k, m) for k, ms in above.items() for m in ms)
    table.append({"cells": "a method above the reference by over 0.05%",
                  "reference over oracle-mpc": str(len(over)), "bound over reference": "",
                  "bound (reward per step)": "",
                  "scenario-intervals": "; ".join(f"{m} in {s} interval {i}"
                                                  for (s, i), m in over) or "none"})
    text = io.StringIO()
    text.write(f"# what: {len({k[0] for k in pairs})} scenarios, {config['intervals']} x {steps} "
               "steps, reward per step (mean over seeds) of the reference over oracle-mpc's, "
               "and the volume bound (scripts/headroom.py)\n")
    text.write(f"# command: scripts/headroom.py {' '.join(d.name for d in args.dirs)}\n")
    for info in meta:
        text.write(f"# commit: {info.get('git_revision', '?')}\n")
        text.write(f"# date: {info.get('created', '?')[:10]}\n")
        text.write(f"# wall time: {info.get('wall_time_s', 0):.0f} s\n")
    write_result_file(args.out, text.getvalue(), table)
    print(f"headroom: {len(pairs)} scenario-intervals -> {args.out}; reference over oracle-mpc "
          f"{table[0]['reference over oracle-mpc']} over intervals 1-9, {len(over)} cells with a "
          "method above it by over 0.05%")
    return 0


if __name__ == "__main__":
    sys.exit(main())
