"""The benchmark's report: each method's reward as a fraction of the oracle MPC's.

From results.json (written by benchmark.collect_benchmark) this computes, once,
fractions.csv: for every (scenario, method, seed, interval) the method's mean
reward per step experienced in that interval divided by the oracle MPC's
(``oracle-mpc``, the planner that knows the faults) in the same scenario, seed
and interval. The figure and report.md / report.html read fractions.csv.

Rewards per step are positive here (r = (1 - |cg| / 3) sigma - mean(u); a
full balanced plant earns 2.16, and interval means stay well above 0), so the
ratio is a fraction: 1 is the oracle's reward. A cell whose oracle reward is
missing or not positive has no fraction (the report counts them).
"""

from __future__ import annotations

import csv
import json
import math
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ftc.common.atomic import atomic_write_csv, atomic_write_text
from ftc.experiments import figures
from ftc.experiments.report import Block, to_html, to_markdown

ORACLE = "oracle-mpc"
FRACTION_COLUMNS = ("scenario", "method", "seed", "interval", "reward_per_step",
                    "oracle_reward_per_step", "fraction")
FIGURE = "benchmark_fraction"


def _num(v: object) -> float | None:
    try:
        x = None if v is None or v == "" else float(v)
    except (TypeError, ValueError):
        return None
    return x if x is not None and math.isfinite(x) else None


def oracle_fractions(rows: Sequence[dict], oracle: str = ORACLE) -> list[dict]:
    """Rows of results (scenario, method, seed, interval, reward_per_step) ->
    the same cells with the oracle's reward per step and the fraction (None
    where the oracle's reward is missing or not positive)."""
    base = {(r["scenario"], int(r["seed"]), int(r["interval"])): _num(r.get("reward_per_step"))
            for r in rows if r["method"] == oracle}
    out = []
    for r in rows:
        key = (r["scenario"], int(r["seed"]), int(r["interval"]))
        v, b = _num(r.get("reward_per_step")), base.get(key)
        out.append({"scenario": key[0], "method": r["method"], "seed": key[1],
                    "interval": key[2], "reward_per_step": v, "oracle_reward_per_step": b,
                    "fraction": v / b if v is not None and b is not None and b > 0 else None})
    return out


def read_fractions(path: Path) -> list[dict]:
    """fractions.csv back: seed and interval as ints, numbers as floats or None."""
    with open(path, newline="") as f:
        return [{"scenario": r["scenario"], "method": r["method"], "seed": int(r["seed"]),
                 "interval": int(r["interval"]), "reward_per_step": _num(r["reward_per_step"]),
                 "oracle_reward_per_step": _num(r["oracle_reward_per_step"]),
                 "fraction": _num(r["fraction"])} for r in csv.DictReader(f)]


@dataclass
class MethodSummary:
    """One method's fractions of the oracle: per-interval means (over scenarios and
    seeds), the mean over every cell, and the worst interval, seed and scenario
    (lowest mean over that interval's, seed's or scenario's cells); the worst
    cell is the lowest (scenario, interval), mean over seeds."""

    method: str
    per_interval: dict[int, float]
    mean: float
    worst_interval: tuple[int, float]
    worst_seed: tuple[int, float]
    worst_scenario: tuple[str, float]
    worst_cell: tuple[tuple[str, int], float]
    cells: int


def _worst(groups: dict) -> tuple:
    key = min(groups, key=lambda k: (float(np.mean(groups[k])), str(k)))
    return key, float(np.mean(groups[key]))


def summarise(fractions: Sequence[dict], methods: Sequence[str]) -> list[MethodSummary]:
    """A summary per method that has a fraction in at least one cell, in ``methods`` order."""
    out = []
    for m in methods:
        cells = [r for r in fractions if r["method"] == m and r["fraction"] is not None]
        if not cells:
            continue
        by: dict[str, dict] = {"interval": defaultdict(list), "seed": defaultdict(list),
                               "scenario": defaultdict(list)}
        by_cell: dict = defaultdict(list)
        for r in cells:
            for k in by:
                by[k][r[k]].append(r["fraction"])
            by_cell[(r["scenario"], r["interval"])].append(r["fraction"])
        out.append(MethodSummary(
            m, {k: float(np.mean(v)) for k, v in sorted(by["interval"].items())},
            float(np.mean([r["fraction"] for r in cells])), _worst(by["interval"]),
            _worst(by["seed"]), _worst(by["scenario"]), _worst(by_cell), len(cells)))
    return out


def per_scenario(fractions: Sequence[dict], scenario: str) -> dict[str, dict[int, float]]:
    """method -> interval -> mean fraction over seeds, in one scenario."""
    per: dict = defaultdict(lambda: defaultdict(list))
    for r in fractions:
        if r["scenario"] == scenario and r["fraction"] is not None:
            per[r["method"]][r["interval"]].append(r["fraction"])
    return {m: {k: float(np.mean(v)) for k, v in iv.items()} for m, iv in per.items()}


# ---------------------------------------------------------------------------
# The figure (reads fractions.csv)
# ---------------------------------------------------------------------------

def draw_figure(run_dir: Path, methods: Sequence[str], labels: dict[str, str]) -> Path | None:
    """figures/benchmark_fraction.png: left, each method's fraction of the oracle per
    interval (mean over scenarios and seeds); right, its spread over scenarios
    (one point per scenario: the mean over seeds and intervals; box: quartiles)."""
    import matplotlib.pyplot as plt  # Agg is selected by ftc.experiments.figures

    fractions = read_fractions(Path(run_dir) / "fractions.csv")
    shown = [s for s in summarise(fractions, methods) if s.method != ORACLE]
    if not shown:
        (Path(run_dir) / "figures" / f"{FIGURE}.png").unlink(missing_ok=True)
        return None
    with plt.rc_context(figures.STYLE):
        fig, (left, right) = plt.subplots(1, 2, figsize=(7.0, 2.8),
                                          gridspec_kw={"width_ratios": [3, 2]})
        left.axhline(1.0, color="black", ls="--", lw=0.8, label=labels.get(ORACLE, ORACLE))
        spread = []
        for i, s in enumerate(shown):
            k = sorted(s.per_interval)
            left.plot(k, [s.per_interval[j] for j in k], "-o", ms=3,
                      color=figures.METHOD_COLORS.get(s.method, f"C{(i + 4) % 10}"),
                      label=labels.get(s.method, s.method))
            by_scenario = defaultdict(list)
            for r in fractions:
                if r["method"] == s.method and r["fraction"] is not None:
                    by_scenario[r["scenario"]].append(r["fraction"])
            spread.append([float(np.mean(v)) for v in by_scenario.values()])
        left.set_xlabel("interval")
        left.set_ylabel("reward per step / oracle's")
        left.set_title("Fraction of the oracle (mean over scenarios and seeds)")
        left.xaxis.set_major_locator(plt.MaxNLocator(integer=True))
        left.legend(loc="upper center", bbox_to_anchor=(0.5, -0.3), frameon=False, ncol=2)
        right.boxplot(spread, showfliers=False, widths=0.5)
        rng = np.random.default_rng(0)  # jitter only
        for i, values in enumerate(spread):
            right.plot(i + 1 + rng.uniform(-0.15, 0.15, len(values)), values, "o", ms=2.5,
                       alpha=0.7, color=figures.METHOD_COLORS.get(shown[i].method,
                                                                  f"C{(i + 4) % 10}"))
        right.axhline(1.0, color="black", ls="--", lw=0.8)
        right.set_xticks(range(1, len(shown) + 1), [s.method for s in shown], rotation=30,
                         ha="right")
        right.set_title("Per scenario (mean over seeds, intervals)")
        fig.tight_layout()
        return figures._save(fig, Path(run_dir) / "figures" / FIGURE, ("png",))[0]


# ---------------------------------------------------------------------------
# The report
# ---------------------------------------------------------------------------

def _f(v: float | None) -> str:
    return "" if v is None else f"{v:.3f}"


def summary_blocks(summaries: Sequence[MethodSummary], labels: dict[str, str],
                   intervals: int) -> list[Block]:
    """The summary table (mean, worst interval, worst seed, worst scenario) and the
    per-interval table."""
    name = lambda m: f"{m} ({labels.get(m, m)})"  # noqa: E731
    return [
        Block("table", header=["method", "mean fraction", "worst interval", "worst seed",
                               "worst scenario", "worst scenario-interval", "cells"],
              rows=[[name(s.method), _f(s.mean),
                     f"{_f(s.worst_interval[1])} (interval {s.worst_interval[0]})",
                     f"{_f(s.worst_seed[1])} (seed {s.worst_seed[0]})",
                     f"{_f(s.worst_scenario[1])} ({s.worst_scenario[0]})",
                     f"{_f(s.worst_cell[1])} ({s.worst_cell[0][0]}, interval {s.worst_cell[0][1]})",
                     str(s.cells)]
                    for s in summaries]),
        Block("p", "Fraction of the oracle per interval (mean over scenarios and seeds)."),
        Block("table", header=["method", *[str(k) for k in range(intervals)], "mean"],
              rows=[[name(s.method), *[_f(s.per_interval.get(k)) for k in range(intervals)],
                     _f(s.mean)] for s in summaries]),
    ]


def build_blocks(run_dir: Path) -> list[Block]:
    run_dir = Path(run_dir)
    meta = json.loads((run_dir / "benchmark.json").read_text())
    config = meta["config"]
    methods, n_int = config["methods"], int(config["intervals"])
    labels = {m: spec["label"] for m, spec in meta.get("methods", {}).items()}
    results = json.loads((run_dir / "results.json").read_text())
    fractions = read_fractions(run_dir / "fractions.csv")
    expected = len(config["scenarios"]) * len(methods) * len(config["seeds"])
    blocks = [
        Block("h1", f"Benchmark report ({run_dir.name})"),
        Block("p", f"Created {meta.get('created', '?')}; git revision "
                   f"`{meta.get('git_revision', '?')}`"
                   + (f" (runs made at {', '.join(meta['git_revisions'])})"
                      if len(meta.get("git_revisions", [])) > 1 else "") + "."),
        Block("table", header=["setting", "value"], rows=[
            ["scenarios", f"{len(config['scenarios'])}: {', '.join(config['scenarios'])}"],
            ["methods", ", ".join(f"{m} ({labels.get(m, m)})" for m in methods)],
            ["controller seeds", ", ".join(str(s) for s in config["seeds"])],
            ["intervals x steps per interval", f"{n_int} x {config['steps_per_interval']}"],
            ["plant link", config["link"]],
            ["finished runs", f"{len(results['runs'])} of {expected}"],
        ])]
    if len(results["runs"]) < expected:
        blocks.append(Block("p", f"**Incomplete:** {expected - len(results['runs'])} of "
                                 f"{expected} runs have no results (failed or not run); "
                                 "complete them with `--resume`."))
    missing = sum(1 for r in fractions if r["fraction"] is None)
    blocks += [
        Block("h2", "Fraction of the oracle"),
        Block("p", "In every scenario, seed and interval, a method's *fraction* is its mean "
                   "reward per step experienced in that interval (`reward_per_step`, "
                   "exploration included) divided by the oracle MPC's (`oracle-mpc`, which "
                   "knows the faults) in the same scenario, seed and interval. Rewards per "
                   "step are positive here, so 1 is the oracle's reward and the oracle's own "
                   "fraction is exactly 1. *Mean*: over every cell; *worst interval*: the "
                   "lowest per-interval mean (over scenarios and seeds); *worst seed*: the "
                   "lowest mean over one seed's cells; *worst scenario*: the lowest mean over "
                   "one scenario's cells; *worst scenario-interval*: the lowest mean over "
                   "seeds of one scenario's interval."
                   + (f" {missing} cells have no fraction (oracle run missing or its reward "
                      "not positive)." if missing else ""))]
    summaries = summarise(fractions, methods)
    if summaries:
        blocks += summary_blocks(summaries, labels, n_int)
    if (run_dir / "figures" / f"{FIGURE}.png").is_file():
        blocks.append(Block("img", "Fraction of the oracle's reward per step: per interval "
                                   "(left, mean over scenarios and seeds) and per scenario "
                                   "(right, one point per scenario)",
                            path=f"figures/{FIGURE}.png"))
    blocks += _scenario_blocks(meta, fractions, methods, labels, n_int)
    if results["runs"]:
        per: dict = defaultdict(list)
        for r in results["runs"]:
            if r.get("wall_time_s") is not None:
                per[r["method"]].append(float(r["wall_time_s"]))
        blocks += [Block("h2", "Wall times"),
                   Block("table", header=["method", "runs", "mean (s)", "max (s)", "total (s)"],
                         rows=[[m, str(len(v)), f"{np.mean(v):.1f}", f"{np.max(v):.1f}",
                                f"{np.sum(v):.1f}"] for m, v in per.items()])]
        if meta.get("wall_time_s"):
            executor = meta.get("executor", {})
            where = (f"on Ray at {executor.get('address')} ({len(executor.get('nodes', []))} "
                     f"nodes)" if executor.get("kind") == "ray"
                     else f"at --jobs {meta.get('jobs', '?')}")
            blocks.append(Block("p", f"The last session took {meta['wall_time_s']:.0f} s "
                                     f"{where}."))
    return blocks


def _scenario_blocks(meta: dict, fractions: Sequence[dict], methods: Sequence[str],
                     labels: dict[str, str], intervals: int) -> list[Block]:
    """Per scenario: its faults, and every method's fraction per interval (mean over
    seeds) with the mean reward per step it earned."""
    blocks = [Block("h2", "Per scenario")]
    for stem in meta["config"]["scenarios"]:
        info = meta.get("scenarios", {}).get(stem, {})
        table = per_scenario(fractions, stem)
        rps: dict = defaultdict(list)
        for r in fractions:
            if r["scenario"] == stem and r["reward_per_step"] is not None:
                rps[r["method"]].append(r["reward_per_step"])
        blocks.append(Block("h3", f"{stem}: {info.get('description', '?')}"))
        rows = [[m, *[_f(table[m].get(k)) for k in range(intervals)],
                 _f(float(np.mean(list(table[m].values())))),
                 _f(float(np.mean(rps[m])) if rps[m] else None)]
                for m in methods if m in table]
        if rows:
            blocks.append(Block("table", header=["method", *[str(k) for k in range(intervals)],
                                                 "mean", "reward/step"], rows=rows))
        else:
            blocks.append(Block("p", "No fractions (no finished oracle run)."))
    return blocks


def write_report(run_dir: Path) -> tuple[Path, Path]:
    """fractions.csv from results.json, the figure from fractions.csv, then
    report.md and report.html."""
    run_dir = Path(run_dir)
    meta = json.loads((run_dir / "benchmark.json").read_text())
    rows = json.loads((run_dir / "results.json").read_text())["metrics"]
    fractions = oracle_fractions(rows)
    atomic_write_csv(run_dir / "fractions.csv", list(FRACTION_COLUMNS),
                     [["" if r[c] is None else r[c] for c in FRACTION_COLUMNS]
                      for r in fractions])
    labels = {m: spec["label"] for m, spec in meta.get("methods", {}).items()}
    draw_figure(run_dir, meta["config"]["methods"], labels)
    blocks = build_blocks(run_dir)
    md, page = run_dir / "report.md", run_dir / "report.html"
    atomic_write_text(md, to_markdown(blocks))
    atomic_write_text(page, to_html(blocks, run_dir))
    return md, page
