#!/usr/bin/env python3
"""Render the docs' result tables from the committed result files.

    .venv/bin/python scripts/render_results.py          # rewrite the tables in place
    .venv/bin/python scripts/render_results.py --check  # exit 1 naming each stale table

A table lives in a Markdown file between two markers,

    <!-- results: NAME -->
    ...rendered table...
    <!-- /results -->

and is rendered from docs/results/NAME.csv: '#' lines first (what was
measured, the command, commit, machine and date: the table's provenance line
comes from them), then a CSV header and rows, as the tool that measured them
wrote it (e.g. scripts/quality_controller.py --results). Nobody types a
number into a table: tests/python/test_docs.py fails when a table and its
file disagree.
"""

from __future__ import annotations

import argparse
import csv
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "python"))
RESULTS = REPO / "docs" / "results"
DOCUMENTS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
BLOCK = re.compile(r"(<!-- results: ([\w-]+)(?::(\w+))? -->\n)(.*?)(<!-- /results -->)", re.S)
# What a block shows of its file: NAME (the means, and their mean over
# intervals 1-9), NAME:std (the spread over seeds), NAME:eval (deterministic
# evaluation), NAME:score and NAME:fraction (a benchmark's per-interval means,
# scripts/suite_results.py), each a column per interval; NAME:summary, every
# column that is not per interval; NAME:table, the file's columns as they are
# (e.g. docs/results/headroom.csv, scripts/headroom.py); NAME:methods, the
# registry's methods (what each is, what it knows, the command that runs it)
# with their score in a suite file. Rows without values are left out.
KINDS = {"mean": "mean over seeds", "std": "std over seeds",
         "eval": "deterministic evaluation (open iff p > 0.5), mean over seeds",
         "score": "normalized score per interval, mean over scenarios and seeds",
         "fraction": "fraction of the oracle per interval, mean over scenarios and seeds",
         "summary": "per method", "table": "as measured",
         "methods": "the registered methods, normalized score and fraction of the oracle from"}
PER_INTERVAL = re.compile(r"\w+_\d+")


def read_results(path: Path) -> tuple[dict[str, str], list[dict[str, str]]]:
    """(provenance by key, rows) of a result file."""
    meta, body = {}, []
    for line in path.read_text().splitlines():
        if line.startswith("#"):
            key, _, value = line[1:].partition(":")
            key, value = key.strip(), value.strip()  # a key given again (several runs): joined
            meta[key] = f"{meta[key]}; {value}" if key in meta and value != meta[key] else value
        elif line.strip():
            body.append(line)
    return meta, list(csv.DictReader(body))


def render(name: str, kind: str = "mean") -> str:
    """The Markdown of table NAME (its ``kind`` of columns): a provenance line,
    then the table."""
    path = RESULTS / f"{name}.csv"
    if not path.is_file():
        raise SystemExit(f"render_results: no result file {path.relative_to(REPO)} for table "
                         f"'{name}'")
    if kind not in KINDS:
        raise SystemExit(f"render_results: table '{name}:{kind}': no such kind "
                         f"({', '.join(KINDS)})")
    meta, rows = read_results(path)
    if kind == "methods":
        return _methods(name, meta, rows)
    if kind == "table":
        head = list(rows[0])
        label, columns = head[0], head[1:]
    elif kind == "summary":
        columns = [c for c in rows[0] if c not in ("method", "label", "mean_1_9")
                   and not PER_INTERVAL.fullmatch(c)]
        head, label = ["method", *columns], "label"
    else:
        columns = [c for c in rows[0] if re.fullmatch(rf"{kind}_\d+", c)]
        head = ["method", *(c.removeprefix(f"{kind}_") for c in columns)]
        label = "label"
    head += ["mean 1-9"] if kind == "mean" else []
    lines = [f"{KINDS[kind].capitalize()}, {meta.get('what', '')}: "
             f"`{meta.get('command', '?')}`, {meta.get('machine', '?')}, {meta.get('date', '?')} "
             f"(file `docs/results/{name}.csv`, with the commits measured).", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r[c] for c in columns] + ([r["mean_1_9"]] if kind == "mean" else [])
        if any(cells):
            lines.append("| " + " | ".join([r[label], *cells]) + " |")
    return "\n".join(lines) + "\n"


def _methods(name: str, meta: dict[str, str], rows: list[dict[str, str]]) -> str:
    """The methods table: every method ftc.experiments compares, by what it
    knows, with its scores in suite file NAME and the command that runs it alone."""
    from ftc.control import registry  # the one list of methods

    scores = {r["method"]: r for r in rows}
    # the per-run score's IQM with its 95% interval, where NAME_scores.csv has it
    # (scripts/suite_results.py --scores)
    extra = RESULTS / f"{name}_scores.csv"
    iqm = {r["method"]: r["IQM"] for r in read_results(extra)[1]} if extra.is_file() else {}
    methods = sorted((m for m in registry.METHODS.values() if m.compared and m.benchmark),
                     key=lambda m: registry.KNOWS.index(m.knows))  # stable: registry order
    lines = [f"{KINDS['methods'].capitalize()} `docs/results/{name}.csv` "
             f"({meta.get('what', '')}, {meta.get('date', '?')})"
             + (f" and `docs/results/{extra.name}` (the per-run score's interquartile mean "
                "over runs, its 95% stratified-bootstrap interval; empty: not measured yet)"
                if iqm else "") + ":", "",
             "| method | what it is | knows | score, IQM [95% CI] | per-cell mean score | "
             "fraction of oracle-mpc | run it alone |", "|---|---|---|---|---|---|---|"]
    for m in methods:
        r = scores.get(m.name, {})
        command = " ".join([".venv/bin/python -m", m.tool, "--method", m.name,
                            *m.recommended, "--out", f"runs/{m.name}"])
        lines.append(f"| `{m.name}` | {m.label} | {m.knows} | {iqm.get(m.name, '')} | "
                     f"{r.get('normalized score', '')} | {r.get('fraction of the oracle', '')} | "
                     f"`{command}` |")
    return "\n".join(lines) + "\n"


def rendered(text: str) -> str:
    """``text`` with every results block rendered from its file."""
    return BLOCK.sub(lambda m: m.group(1) + render(m.group(2), m.group(3) or "mean")
                     + m.group(5), text)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--check", action="store_true",
                   help="write nothing; exit 1 naming every table that differs from its file")
    args = p.parse_args(argv)
    stale = []
    for doc in DOCUMENTS:
        text = doc.read_text()
        new = rendered(text)
        if new != text:
            stale.append(str(doc.relative_to(REPO)))
            if not args.check:
                doc.write_text(new)
    if args.check and stale:
        print(f"render_results: tables differ from docs/results in {', '.join(stale)}; run "
              "scripts/render_results.py", file=sys.stderr)
        return 1
    if stale:
        print(f"render_results: rendered {', '.join(stale)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
