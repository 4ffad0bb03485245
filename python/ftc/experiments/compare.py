"""Compare benchmark directories: several methods, seeds or commits in one report.

    python -m ftc.experiments compare runs/bench-A runs/bench-B --out runs/compare
    python -m ftc.experiments compare runs/mine runs/bench --against reference --out runs/c

Each DIR is a finished ``ftc.experiments benchmark`` directory. They must hold
the same suite (the same scenario files, byte for byte, as their runs used
them), the same number of intervals and the same steps per interval; anything
else is refused with one line naming the difference (exit 2). Seeds may differ:
paired comparisons use the cells both sides have.

Every (directory, method) is one entry, named by the method alone where only one
directory holds it and ``METHOD@DIR`` (the directory's name, or its path where
two directories share a name) where several do.
Scores are taken as the benchmark takes them: the normalized score against the
reference (``--reference``, default: the first directory's) and ``closed`` in
the same cell, the fraction of ``oracle-mpc``'s reward; the reference's,
closed's and the oracle's cells may come from any directory (the reference
runs once per scenario, so a directory made with ``--reference oracle-mpc``
is rebased on one that holds ``reference``). A cell given differently by two
directories is taken from the entry's own directory.

Paired differences: an entry against another on the cells both have
(scenario, seed, interval >= 1), mean of the normalized-score difference and its
standard error over the (scenario, seed) runs (a run's intervals are not
independent); for every method that several directories hold (the first
directory's entry against the others) and, with ``--against ENTRY``, every
entry against that one.

Aggregates and chances: each entry's IQM, mean, median and optimality gap of the
per-run score with 95% stratified-bootstrap intervals (aggregates.csv), and the
probability of improvement P(X > Y) with its interval between every pair of
entries (improvement.csv; ftc.experiments.improvement), printed for the pairs above.

Writes into --out: compare.md and compare.html (the tables and the figures),
results.csv (the merged cells, with each entry's name), entries.csv (the summary
per entry), paired.csv, aggregates.csv, improvement.csv, figures/benchmark_score.png,
figures/benchmark_profile.png. Exit 0; 2 bad input.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import sys
from collections import defaultdict
from pathlib import Path
from typing import Sequence

import numpy as np

from ftc.common.atomic import atomic_write_csv, atomic_write_text
from ftc.common.cli import OneLineParser, out_dir_problem
from ftc.control.registry import canonical
from ftc.experiments import benchmark_report as br
from ftc.experiments import improvement, score_tables
from ftc.experiments.report import Block, to_html, to_markdown

TOOL = "ftc.experiments compare"


class CompareError(ValueError):
    """Directories that cannot be compared; the message names the difference."""


def load(directory: Path) -> tuple[dict, list[dict]]:
    """(benchmark.json's config, results.csv's rows: scenario, method, seed,
    interval, reward_per_step) of a finished benchmark directory."""
    info, results = directory / "benchmark.json", directory / "results.csv"
    if not info.is_file() or not results.is_file():
        raise CompareError(f"{directory} holds no finished benchmark (benchmark.json and "
                           "results.csv); run ftc.experiments benchmark --out there first")
    try:
        config = json.loads(info.read_text())["config"]
        with open(results, newline="") as f:
            rows = [{"scenario": r["scenario"], "method": canonical(r["method"]),
                     "seed": int(r["seed"]), "interval": int(r["interval"]),
                     "reward_per_step": br._num(r["reward_per_step"])}
                    for r in csv.DictReader(f)]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise CompareError(f"{directory}: unreadable benchmark ({type(e).__name__}: {e})")
    return config, rows


def _suite(directory: Path, config: dict) -> dict[str, str]:
    """scenario stem -> SHA-256 of the file its runs read."""
    out = {}
    for stem in config["scenarios"]:
        path = directory / "scenarios" / f"{stem}.toml"
        if not path.is_file():
            raise CompareError(f"{directory}: scenario file {path} is missing")
        out[stem] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def check_compatible(dirs: Sequence[Path], configs: Sequence[dict]) -> None:
    """CompareError naming the first difference of suite, intervals or steps."""
    first, base = dirs[0], configs[0]
    suite = _suite(first, base)
    for d, c in zip(dirs[1:], configs[1:]):
        for key, what in (("intervals", "intervals"), ("steps_per_interval", "steps per interval")):
            if c[key] != base[key]:
                raise CompareError(f"{d} has {c[key]} {what}, {first} has {base[key]}: "
                                   "compare benchmarks of one protocol")
        other = _suite(d, c)
        if set(other) != set(suite):
            only = sorted(set(other) ^ set(suite))
            raise CompareError(f"{d} and {first} ran different suites (scenario "
                               f"{only[0]} is in one only)")
        changed = sorted(s for s in suite if other[s] != suite[s])
        if changed:
            raise CompareError(f"scenario {changed[0]} differs between {d} and {first} "
                               f"(scenarios/{changed[0]}.toml): compare runs of one suite")


def entries(dirs: Sequence[Path], rows_by_dir: Sequence[list[dict]]) -> list[tuple[str, int, str]]:
    """(entry name, directory index, method) for every method of every directory."""
    holders: dict[str, list[int]] = defaultdict(list)
    for i, rows in enumerate(rows_by_dir):
        for m in dict.fromkeys(r["method"] for r in rows):
            holders[m].append(i)
    tags = [d.name for d in dirs]
    if len(set(tags)) < len(tags):  # two directories of one name: their paths tell them apart
        tags = [str(d) for d in dirs]
    out = []
    for m, where in holders.items():
        for i in where:
            out.append((m if len(where) == 1 else f"{m}@{tags[i]}", i, m))
    return out


def scored_rows(rows_by_dir: Sequence[list[dict]], names: list[tuple[str, int, str]],
                reference: str) -> list[dict]:
    """Every entry's cells with normalized_score, fraction and the entry's name as
    method; the reference's, closed's and the oracle's cells from the entry's own
    directory first, then from the others in order."""
    def lookup(method: str) -> list[dict]:
        per_dir = []
        for rows in rows_by_dir:
            per_dir.append({(r["scenario"], r["seed"], r["interval"]): r["reward_per_step"]
                            for r in rows if r["method"] == method})
        return per_dir

    ref, closed, oracle = lookup(reference), lookup(br.CLOSED), lookup(br.ORACLE)

    def find(tables: list[dict], i: int, key: tuple) -> float | None:
        for j in (i, *range(len(tables))):
            if tables[j].get(key) is not None:
                return tables[j][key]
        return None

    out = []
    for name, i, method in names:
        for r in rows_by_dir[i]:
            if r["method"] != method:
                continue
            key = (r["scenario"], r["seed"], r["interval"])
            o, b, c = find(oracle, i, key), find(ref, i, key), find(closed, i, key)
            out.append({**r, "method": name, "reference_reward_per_step": b,
                        "closed_reward_per_step": c,
                        "normalized_score": br.normalized_score(r["reward_per_step"], b, c),
                        "fraction": (r["reward_per_step"] / o if o and o > 0
                                     and r["reward_per_step"] is not None else None)})
    return out


def paired(rows: list[dict], a: str, b: str) -> dict | None:
    """b - a in normalized score on the cells both have (interval >= 1): mean, its
    standard error over the (scenario, seed) runs, and the counts; None if none."""
    def cells(name: str) -> dict:
        return {(r["scenario"], r["seed"], r["interval"]): r["normalized_score"]
                for r in rows if r["method"] == name and r["interval"] >= 1
                and r["normalized_score"] is not None}

    ca, cb = cells(a), cells(b)
    shared = sorted(set(ca) & set(cb))
    if not shared:
        return None
    runs: dict[tuple, list[float]] = defaultdict(list)
    for k in shared:
        runs[k[:2]].append(cb[k] - ca[k])
    means = np.array([np.mean(v) for v in runs.values()])
    se = float(np.std(means, ddof=1) / np.sqrt(len(means))) if len(means) > 1 else None
    return {"entry": b, "against": a, "difference": float(np.mean(means)),
            "standard error": se, "runs": len(means), "cells": len(shared)}


def _pairs(names: list[tuple[str, int, str]], against: str | None) -> list[tuple[str, str]]:
    out = []
    by_method: dict[str, list[str]] = defaultdict(list)
    for name, _, method in names:
        by_method[method].append(name)
    for group in by_method.values():
        out += [(group[0], other) for other in group[1:]]
    if against is not None:
        out += [(against, name) for name, _, _ in names if name != against]
    return list(dict.fromkeys(out))


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = OneLineParser(prog=f"python -m {TOOL}", description=__doc__.split("\n\n")[0],
                           formatter_class=argparse.RawDescriptionHelpFormatter,
                           epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("dirs", nargs="+", type=Path, metavar="DIR",
                        help="finished benchmark directories (ftc.experiments benchmark --out)")
    parser.add_argument("--out", required=True, help="directory of the report")
    parser.add_argument("--reference", default=None, metavar="METHOD",
                        help="the normalized score's 1 (default: the first directory's)")
    parser.add_argument("--against", default=None, metavar="ENTRY",
                        help="also pair every entry against this one (a method, or METHOD@DIR)")
    args = parser.parse_args(argv)
    if len(set(d.resolve() for d in args.dirs)) != len(args.dirs):
        parser.error("a directory is given twice")
    problem = out_dir_problem(Path(args.out))
    if problem:
        parser.error(f"--out {args.out}: cannot write there ({problem})")
    args.parser = parser
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        loaded = [load(d) for d in args.dirs]
        configs, rows_by_dir = [c for c, _ in loaded], [r for _, r in loaded]
        check_compatible(args.dirs, configs)
        names = entries(args.dirs, rows_by_dir)
        if args.against is not None and args.against not in {n for n, _, _ in names}:
            raise CompareError(f"--against {args.against}: no such entry (entries: "
                               f"{', '.join(n for n, _, _ in names)})")
        reference = args.reference or configs[0].get("reference", br.ORACLE)
        if not any(r["method"] == reference for rows in rows_by_dir for r in rows):
            raise CompareError(f"no directory holds runs of the reference {reference}")
    except CompareError as e:
        args.parser.error(str(e))
    rows = scored_rows(rows_by_dir, names, reference)
    pairs = _pairs(names, args.against)
    found = write_report(Path(args.out), rows, names, reference, pairs,
                         int(configs[0]["intervals"]), args.dirs)
    for line in improvement.lines(found, pairs):
        print(f"{TOOL}: {line}")
    print(f"{TOOL}: {len(names)} entries from {len(args.dirs)} directories -> "
          f"{Path(args.out) / 'compare.md'}")
    return 0


def write_report(out: Path, rows: list[dict], names: list[tuple[str, int, str]],
                 reference: str, pairs: list[tuple[str, str]], intervals: int,
                 dirs: Sequence[Path]) -> list[dict]:
    """compare.md / .html and the CSV files; returns the probabilities of improvement
    (:func:`ftc.experiments.improvement.every_pair`)."""
    out.mkdir(parents=True, exist_ok=True)
    order = [n for n, _, _ in names]
    labels = {n: f"{m}, {dirs[i]}" for n, i, m in names}
    scores = br.summarise(rows, order, "normalized_score")
    fractions = br.summarise(rows, order, "fraction")
    columns = ["scenario", "method", "seed", "interval", "reward_per_step",
               "normalized_score", "fraction"]
    atomic_write_csv(out / "results.csv", columns,
                     [["" if r[c] is None else r[c] for c in columns] for r in rows])
    fraction = {s.method: s for s in fractions}
    atomic_write_csv(out / "entries.csv",
                     ["entry", "directory", "normalized score", "worst scenario-interval",
                      "fraction of the oracle", "worst fraction", "cells"],
                     [[s.method, str(dirs[next(i for n, i, _ in names if n == s.method)]),
                       br.fmt(s.mean), br.worst_columns(s)[3],
                       br.fmt(fraction[s.method].mean) if s.method in fraction else "",
                       br.worst_columns(fraction[s.method])[3] if s.method in fraction else "",
                       s.cells] for s in scores])
    found = [p for p in (paired(rows, a, b) for a, b in pairs) if p is not None]
    fmt_se = lambda v: "" if v is None else f"{v:.3f}"  # noqa: E731
    atomic_write_csv(out / "paired.csv", ["entry", "against", "difference", "standard error",
                                          "runs", "cells"],
                     [[p["entry"], p["against"], f"{p['difference']:.4f}",
                       fmt_se(p["standard error"]), p["runs"], p["cells"]] for p in found])
    figure = br.draw_figure(out, order, labels, reference, intervals)
    blocks = [Block("h1", "Benchmark comparison"),
              Block("p", f"{len(order)} entries from {', '.join(map(str, dirs))}; normalized "
                         f"score against {reference} and closed, fraction of {br.ORACLE}.")]
    hidden = [n for n, _, m in names if m in (reference, br.CLOSED)]
    blocks += score_tables.score_blocks(out, rows, order, labels, None, intervals, hidden)
    chances = improvement.every_pair(rows, [n for n in order if n not in hidden])
    blocks += improvement.blocks(out, chances)
    blocks += [Block("h2", "Per cell")] + br.score_blocks(scores, fractions, labels, intervals)
    if found:
        blocks += [Block("h2", "Paired differences"),
                   Block("p", "Normalized score of the entry minus the other's, on the cells "
                              "both have (intervals 1 on); standard error over the runs."),
                   Block("table", header=["entry", "against", "difference", "standard error",
                                          "runs", "cells"],
                         rows=[[p["entry"], p["against"], f"{p['difference']:+.3f}",
                                fmt_se(p["standard error"]), str(p["runs"]), str(p["cells"])]
                               for p in found])]
    if figure is not None:
        blocks.append(Block("img", "normalized score per interval and per scenario",
                            path=str(figure.relative_to(out))))
    atomic_write_text(out / "compare.md", to_markdown(blocks))
    atomic_write_text(out / "compare.html", to_html(blocks, out))
    return chances


if __name__ == "__main__":
    sys.exit(main())
