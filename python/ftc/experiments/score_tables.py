"""The benchmark's scores with their intervals, as files and report blocks:
aggregates.csv (IQM, mean, median and optimality gap of the per-run normalized
score, each with its 95% stratified-bootstrap interval: ftc.experiments.stats),
tracks.csv (the same IQM per challenge track: ftc.experiments.tracks) and the
performance profile (figures/benchmark_profile.png). benchmark_report and
compare call :func:`score_blocks`; the figure reads aggregates' inputs from
results.csv, as every figure reads saved results.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ftc.common.atomic import atomic_write_csv
from ftc.experiments import figures, stats, tracks
from ftc.experiments.report import Block

AGGREGATES_FILE = "aggregates.csv"
TRACKS_FILE = "tracks.csv"
PROFILE = "benchmark_profile"
TAUS = np.linspace(-0.5, 1.1, 161)  # the profile's thresholds of the normalized score


def method_tasks(rows: Sequence[Mapping], methods: Sequence[str],
                 scenarios: Sequence[str] | None = None) -> dict[str, list[np.ndarray]]:
    """method -> its run scores, one array per scenario (``scenarios``: only those),
    for every method of ``methods`` with a score."""
    scores = stats.run_scores(rows)
    out = {}
    for m in methods:
        per = scores.get(m, {})
        if scenarios is not None:
            per = {s: v for s, v in per.items() if s in scenarios}
        tasks = stats.tasks_of(per, sorted(per))
        if tasks:
            out[m] = tasks
    return out


def aggregate_rows(rows: Sequence[Mapping], methods: Sequence[str],
                   config: stats.BootstrapConfig = stats.BootstrapConfig()) -> list[dict]:
    """One row per method: runs, scenarios, and each aggregate's point, low, high."""
    out = []
    for m, tasks in method_tasks(rows, methods).items():
        row: dict = {"method": m, "runs": sum(len(t) for t in tasks), "scenarios": len(tasks)}
        for name, est in stats.aggregates(tasks, config).items():
            row |= {name: est.point, f"{name} low": est.low, f"{name} high": est.high}
        out.append(row)
    return out


def track_rows(rows: Sequence[Mapping], methods: Sequence[str],
               members: Mapping[str, Sequence[str]],
               config: stats.BootstrapConfig = stats.BootstrapConfig()) -> list[dict]:
    """One row per (track, method): scenarios, runs and the IQM with its interval."""
    out = []
    for track, scenarios in members.items():
        for m, tasks in method_tasks(rows, methods, scenarios).items():
            est = stats.bootstrap(tasks, stats.iqm, config)
            out.append({"track": track, "method": m, "scenarios": len(tasks),
                        "runs": sum(len(t) for t in tasks), "IQM": est.point,
                        "IQM low": est.low, "IQM high": est.high})
    return out


def _text(row: Mapping, name: str) -> str:
    return stats.Estimate(row[name], row[f"{name} low"], row[f"{name} high"]).text()


def draw_profile(run_dir: Path, rows: Sequence[Mapping], methods: Sequence[str],
                 labels: Mapping[str, str], hidden: Sequence[str]) -> Path | None:
    """figures/benchmark_profile.png: for every method but ``hidden``, the fraction
    of runs whose normalized score exceeds tau, with its 95% band."""
    plt = figures.pyplot()

    shown = {m: t for m, t in method_tasks(rows, methods).items() if m not in hidden}
    if not shown:
        return None
    with plt.rc_context(figures.STYLE):
        fig, ax = plt.subplots(figsize=(6.0, 4.0))
        for i, (m, tasks) in enumerate(shown.items()):
            point, low, high = stats.performance_profile(tasks, TAUS)
            color = figures.METHOD_COLORS.get(m, f"C{(i + 4) % 10}")
            ax.plot(TAUS, point, color=color, label=labels.get(m, m))
            ax.fill_between(TAUS, low, high, color=color, alpha=0.2, lw=0)
        ax.axvline(0.0, color="grey", ls=":", lw=0.8)
        ax.axvline(1.0, color="black", ls="--", lw=0.8)
        ax.set_xlabel("normalized score tau (0: all valves closed, 1: the reference)")
        ax.set_ylabel("fraction of runs with score > tau")
        ax.set_title("Performance profile (runs: scenario x seed; 95% bands)")
        ax.legend(loc="lower left", fontsize=7, frameon=False)
        fig.tight_layout()
        return figures._save(fig, Path(run_dir) / "figures" / PROFILE, ("png",))[0]


def score_blocks(run_dir: Path, rows: Sequence[Mapping], methods: Sequence[str],
                 labels: Mapping[str, str], scenario_dir: Path | None, intervals: int,
                 hidden: Sequence[str] = ()) -> list[Block]:
    """Write aggregates.csv, tracks.csv (with ``scenario_dir``: where the scenario
    files are) and the profile into ``run_dir``; return the report's blocks."""
    run_dir = Path(run_dir)
    table = aggregate_rows(rows, methods)
    names = list(stats.AGGREGATES)
    columns = ["method", "runs", "scenarios",
               *[f"{n}{s}" for n in names for s in ("", " low", " high")]]
    atomic_write_csv(run_dir / AGGREGATES_FILE, columns, [[r[c] for c in columns] for r in table])
    blocks = [Block("h2", "Scores with 95% intervals"),
              Block("p", "Each (scenario, seed) run is normalized over its intervals 1 on: "
                         "sum(r - closed) / sum(reference - closed) of rewards per step, so "
                         "closed scores 0 and the reference 1 and no single interval where "
                         "the reference barely beats closed can carry the score (interval 0, "
                         "the healthy plant, has no spread and is left out). Aggregated over "
                         "the runs with the interquartile mean (IQM), the mean and median "
                         "over scenarios, and the optimality gap (mean shortfall from 1), "
                         "each with a 95% stratified-bootstrap interval (scenarios are the "
                         "tasks, seeds the runs; ftc.experiments.stats). "
                         f"File: `{AGGREGATES_FILE}`."),
              Block("table", header=["method", *names, "runs"],
                    rows=[[r["method"], *[_text(r, n) for n in names], str(r["runs"])]
                          for r in table])]
    if draw_profile(run_dir, rows, methods, labels, hidden) is not None:
        blocks.append(Block("img", "Performance profile: the fraction of runs scoring above "
                                   "each threshold, with 95% bands",
                            path=f"figures/{PROFILE}.png"))
    if scenario_dir is None:
        return blocks
    stems = sorted({r["scenario"] for r in rows})
    labelled = tracks.label(scenario_dir, stems, rows, intervals)
    members = tracks.members(labelled)
    found = track_rows(rows, methods, members)
    track_columns = ["track", "method", "scenarios", "runs", "IQM", "IQM low", "IQM high"]
    atomic_write_csv(run_dir / TRACKS_FILE, track_columns,
                     [[r[c] for c in track_columns] for r in found])
    shown = [m for m in methods if any(r["method"] == m for r in found)]
    cell = {(r["track"], r["method"]): _text(r, "IQM") for r in found}
    blocks += [
        Block("h3", "Tracks"),
        Block("p", "Each scenario's challenge axis and difficulty (ftc.experiments.tracks: "
                   "the share of the reference's reward that all valves closed gives up over "
                   "intervals 1 on), then every method's IQM with its 95% interval per track. "
                   f"File: `{TRACKS_FILE}`."),
        Block("table", header=["scenario", "axis", "closed gives up", "difficulty"],
              rows=[[s, str(lab["axis"]),
                     "" if lab["share"] is None else f"{lab['share']:.3f}",
                     str(lab["difficulty"] or "")] for s, lab in labelled.items()]),
        Block("table", header=["method", *[f"{t} ({len(s)})" for t, s in members.items()]],
              rows=[[m, *[cell.get((t, m), "") for t in members]] for m in shown])]
    return blocks
