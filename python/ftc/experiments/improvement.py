"""The probability of improvement between compared entries (``ftc.experiments
compare``): for every ordered pair, P(a run of X scores above a run of Y) on the
per-run normalized score, averaged over the scenarios both have, with its 95%
stratified-bootstrap interval (:func:`ftc.experiments.stats.probability_of_improvement`).
Above 0.5, X tends to beat Y; an interval that holds 0.5 cannot tell them apart.
Written to improvement.csv and a table of compare.md; the pairs compare pairs by
default (the same method in several directories, and ``--against``) are printed.
"""

from __future__ import annotations

from itertools import permutations
from pathlib import Path
from typing import Mapping, Sequence

from ftc.common.atomic import atomic_write_csv
from ftc.experiments import stats
from ftc.experiments.report import Block

FILE = "improvement.csv"
COLUMNS = ("entry", "against", "probability", "low", "high", "scenarios")


def every_pair(rows: Sequence[Mapping], entries: Sequence[str],
               config: stats.BootstrapConfig = stats.BootstrapConfig()) -> list[dict]:
    """P(entry > against) for every ordered pair of ``entries`` with a run score in a
    common scenario (results rows with the reference's and closed's rewards)."""
    scores = stats.run_scores(rows)
    out = []
    for x, y in permutations([e for e in entries if e in scores], 2):
        common = sorted(set(scores[x]) & set(scores[y]))
        if not common:
            continue
        est = stats.probability_of_improvement(stats.tasks_of(scores[x], common),
                                               stats.tasks_of(scores[y], common), config)
        out.append({"entry": x, "against": y, "probability": est.point, "low": est.low,
                    "high": est.high, "scenarios": len(common)})
    return out


def _text(r: Mapping) -> str:
    return (f"P({r['entry']} > {r['against']}) = "
            f"{stats.Estimate(r['probability'], r['low'], r['high']).text()} "
            f"over {r['scenarios']} scenarios")


def lines(found: Sequence[Mapping], pairs: Sequence[tuple[str, str]]) -> list[str]:
    """One line per pair of ``pairs`` (against, entry) found; every pair where
    ``pairs`` is empty (each unordered pair once)."""
    by = {(r["against"], r["entry"]): r for r in found}
    if pairs:
        return [_text(by[p]) for p in pairs if p in by]
    seen, out = set(), []
    for r in found:
        key = frozenset((r["entry"], r["against"]))
        if key not in seen:
            seen.add(key)
            out.append(_text(r))
    return out


def blocks(out: Path, found: Sequence[Mapping]) -> list[Block]:
    """Write improvement.csv into ``out``; the report's section."""
    atomic_write_csv(Path(out) / FILE, list(COLUMNS), [[r[c] for c in COLUMNS] for r in found])
    if not found:
        return []
    return [Block("h2", "Probability of improvement"),
            Block("p", "P(X > Y): the chance that a run of X scores above a run of Y in the "
                       "same scenario (ties count half), averaged over the scenarios both "
                       "have, with its 95% stratified-bootstrap interval. Above 0.5 X tends "
                       "to beat Y; an interval that holds 0.5 cannot tell them apart. "
                       f"File: `{FILE}`."),
            Block("table", header=["X", "Y", "P(X > Y)", "scenarios"],
                  rows=[[r["entry"], r["against"],
                         stats.Estimate(r["probability"], r["low"], r["high"]).text(),
                         str(r["scenarios"])] for r in found])]
