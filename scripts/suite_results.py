#!/usr/bin/env python3
"""Summarise benchmark runs into a committed result file (docs/results/NAME.csv).

    .venv/bin/python scripts/suite_results.py runs/benchmark-A [runs/benchmark-B ...] \\
        --out docs/results/suite.csv [--reference METHOD]

Reads each directory's results.csv (``ftc.experiments benchmark`` writes it)
and their union's cells, a (scenario, method, seed, interval) each, scores
every method as the benchmark's report does
(``ftc.experiments.benchmark_report``): the normalized score against
``--reference`` (default: the first directory's) and all valves closed, and
the fraction of ``oracle-mpc``. Several directories let a reference run made
apart (for instance on its own, once per scenario) rebase the others: a cell
given twice must hold the same reward, or nothing is written.

The file has one row per method: its label, the mean normalized score and
fraction, the worst interval, seed, scenario and scenario-interval of the
score, the cell count, then the per-interval means (``score_K``,
``fraction_K``), after '#' provenance lines (the directories' commands,
commits, machine, dates and wall times). scripts/render_results.py renders
its tables in README.md and docs/*.md.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import platform
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "python"))

from ftc.common.atomic import atomic_write_text  # noqa: E402
from ftc.control import registry  # noqa: E402
from ftc.experiments import benchmark_report as br  # noqa: E402


def _machine() -> str:
    try:
        names = [line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo")
                 if line.startswith("model name")]
    except OSError:
        names = []
    return f"{names[0] if names else platform.processor() or '?'}, {len(names) or '?'} cores"


def write_result_file(path: Path, provenance: str, table: list[dict]) -> None:
    """A result file, atomically: the '#' provenance lines given, the machine's, then
    the table as CSV (its first row's keys the header)."""
    text = io.StringIO(provenance)
    text.seek(0, io.SEEK_END)
    text.write(f"# machine: {_machine()}\n")
    w = csv.DictWriter(text, fieldnames=list(table[0]), lineterminator="\n")
    w.writeheader()
    w.writerows(table)
    atomic_write_text(path, text.getvalue())


def read_cells(dirs: list[Path]) -> tuple[list[dict], list[dict]]:
    """(rows, provenance per directory); SystemExit naming the cell given twice
    with different rewards, or a directory that is not a finished benchmark."""
    rows: dict[tuple, dict] = {}
    meta = []
    for d in dirs:
        results, info = d / "results.csv", d / "benchmark.json"
        if not results.is_file() or not info.is_file():
            raise SystemExit(f"suite_results: {d} holds no benchmark results "
                             "(results.csv and benchmark.json); run ftc.experiments benchmark")
        meta.append(json.loads(info.read_text()))
        with open(results, newline="") as f:
            for r in csv.DictReader(f):
                method = registry.canonical(r["method"])  # a former name: today's
                key = (r["scenario"], method, int(r["seed"]), int(r["interval"]))
                if key in rows and rows[key]["reward_per_step"] != r["reward_per_step"]:
                    raise SystemExit(f"suite_results: {key} is given twice with different "
                                     f"rewards ({rows[key]['reward_per_step']} and "
                                     f"{r['reward_per_step']}, the second in {results})")
                rows[key] = {"scenario": key[0], "method": key[1], "seed": key[2],
                             "interval": key[3], "reward_per_step": r["reward_per_step"]}
    return list(rows.values()), meta


def summary_rows(rows: list[dict], reference: str, labels: dict[str, str],
                 methods: list[str], intervals: int) -> list[dict]:
    scores = br.summarise(br.normalized_scores(rows, reference), methods, "normalized_score")
    fractions = {s.method: s for s in br.summarise(br.oracle_fractions(rows), methods)}
    out = []
    for s in scores:
        f = fractions.get(s.method)
        worst = br.worst_columns(s)
        out.append({
            "method": s.method, "label": f"`{s.method}` ({labels.get(s.method, s.method)})",
            "normalized score": br.fmt(s.mean), "fraction of the oracle": br.fmt(f and f.mean),
            **dict(zip(br.WORST_HEADER, worst)), "cells": str(s.cells),
            **{f"score_{k}": br.fmt(s.per_interval.get(k)) for k in range(intervals)},
            **{f"fraction_{k}": br.fmt(f.per_interval.get(k) if f else None)
               for k in range(intervals)}})
    return out


def interval_files(rows: list[dict], reference: str, labels: dict[str, str],
                   methods: list[str], intervals: int, args: argparse.Namespace,
                   provenance: str) -> None:
    """--scores and --tracks: the aggregates of the per-run score with their
    intervals, and the IQM per track, of the merged cells."""
    from ftc.experiments import score_tables, stats, tracks

    scored = br.normalized_scores([{**r, "reward_per_step": br._num(r["reward_per_step"]),
                                    "seed": int(r["seed"]), "interval": int(r["interval"])}
                                   for r in rows], reference)
    text = lambda r, n: stats.Estimate(r[n], r[f"{n} low"], r[f"{n} high"]).text()  # noqa
    if args.scores:
        table = [{"method": r["method"], **{n: text(r, n) for n in stats.AGGREGATES},
                  "runs": str(r["runs"]), "scenarios": str(r["scenarios"])}
                 for r in score_tables.aggregate_rows(scored, methods)]
        write_result_file(args.scores, provenance.replace(
            "normalized score against", "per-run normalized score (95% stratified-bootstrap "
            "intervals) against"), table)
        print(f"suite_results: {len(table)} methods -> {args.scores}")
    if args.tracks:
        stems = sorted({r["scenario"] for r in scored})
        scenario_dir = args.dirs[0] / "scenarios"
        members = tracks.members(tracks.label(scenario_dir, stems, scored, intervals))
        found = score_tables.track_rows(scored, methods, members)
        cells = {(r["track"], r["method"]): text(r, "IQM") for r in found}
        table = [{"method": m, **{f"{t} ({len(s)})": cells.get((t, m), "")
                                  for t, s in members.items()}}
                 for m in methods if any(r["method"] == m for r in found)]
        write_result_file(args.tracks, provenance.replace(
            "normalized score against", "IQM of the per-run normalized score per track "
            "(95% intervals) against"), table)
        print(f"suite_results: {len(members)} tracks -> {args.tracks}")


def _figure(rows: list[dict], reference: str, labels: dict[str, str], methods: list[str],
            intervals: int, path: Path) -> None:
    """The benchmark report's figure (benchmark_report.draw_figure) of the merged
    cells, drawn in a scratch run directory and moved to ``path``."""
    import shutil
    import tempfile

    scored = br.normalized_scores(rows, reference)
    with tempfile.TemporaryDirectory() as tmp:
        with open(Path(tmp) / "results.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(scored[0]), extrasaction="ignore")
            w.writeheader()
            w.writerows(scored)
        drawn = br.draw_figure(Path(tmp), methods, labels, reference, intervals)
        if drawn is None:
            raise SystemExit("suite_results: no method besides the reference and closed to draw")
        path.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(drawn, path.with_suffix(".part"))
        path.with_suffix(".part").replace(path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dirs", nargs="+", type=Path, metavar="DIR",
                   help="benchmark run directories (ftc.experiments benchmark --out DIR)")
    p.add_argument("--out", type=Path, required=True,
                   help="the result file to write (e.g. docs/results/suite.csv)")
    p.add_argument("--reference", help="the method whose normalized score is 1 (default: "
                                       "the first directory's --reference)")
    p.add_argument("--scores", type=Path, help="also write each method's aggregates with "
                   "their 95%% intervals (ftc.experiments.score_tables) into this result file "
                   "(e.g. docs/results/suite_scores.csv)")
    p.add_argument("--tracks", type=Path, help="also write each method's IQM per challenge "
                   "track into this result file (e.g. docs/results/suite_tracks.csv)")
    p.add_argument("--figure", type=Path, help="also draw the benchmark's score figure of "
                   "the merged cells into this PNG (e.g. docs/figures/benchmark_score.png)")
    args = p.parse_args(argv)
    rows, meta = read_cells(args.dirs)
    reference = args.reference or meta[0]["config"].get("reference", br.ORACLE)
    labels = {registry.canonical(m): spec["label"] for info in meta
              for m, spec in info.get("methods", {}).items()}
    labels |= {m: registry.METHODS[m].label for m in labels if m in registry.METHODS}
    methods = list(dict.fromkeys(registry.canonical(m) for info in meta
                                 for m in info["config"]["methods"]))
    if reference not in methods:
        raise SystemExit(f"suite_results: the reference '{reference}' has no runs in "
                         f"{', '.join(map(str, args.dirs))}")
    intervals = max(int(info["config"]["intervals"]) for info in meta)
    table = summary_rows(rows, reference, labels, methods, intervals)
    text = io.StringIO()
    for info in meta:
        c = info["config"]
        text.write(f"# what: {len(c['scenarios'])} scenarios x {len(c['seeds'])} seeds, "
                   f"{c['intervals']} x {c['steps_per_interval']} steps, normalized score "
                   f"against {reference} and closed, fraction of {br.ORACLE}\n")
        chosen = "" if c.get("reference", br.ORACLE) == br.REFERENCE else \
            f" --reference {c.get('reference', br.ORACLE)}"
        text.write(f"# command: ftc.experiments benchmark --methods {' '.join(c['methods'])} "
                   f"--seeds {' '.join(map(str, c['seeds']))}{chosen} "
                   f"--jobs {info.get('jobs', '?')}\n")
        text.write(f"# commit: {info.get('git_revision', '?')}\n")
        text.write(f"# date: {info.get('created', '?')[:10]}\n")
        text.write(f"# wall time: {info.get('wall_time_s', 0):.0f} s\n")
    write_result_file(args.out, text.getvalue(), table)
    if args.scores or args.tracks:
        interval_files(rows, reference, labels, methods, intervals, args, text.getvalue())
    print(f"suite_results: {len(table)} methods, {len(rows)} cells -> {args.out}")
    if args.figure:
        _figure(rows, reference, labels, methods, intervals, args.figure)
        print(f"suite_results: figure -> {args.figure}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
