"""The adaptive policy's result files and their summary
(``python -m ftc.experiments.adaptive summarize``, docs/adaptive.md): each
policy's per-scenario scores summarized per set, with the mean's 95% interval
over the scenarios (:func:`ftc.experiments.stats.set_mean`), or tabled per
scenario beside the reference's gain over all-closed.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from ftc.common.atomic import atomic_write_text
from ftc.common.build_info import git_revision
from ftc.common.errors import EXIT_STORAGE
from ftc.experiments import stats


def write_result(path: str, what: str, rows: list[dict[str, Any]],
                 command: str = "python -m ftc.experiments.adaptive") -> None:
    """A result file (docs/results/): '#' provenance lines (``command`` followed by
    this process's arguments), then the CSV."""
    import csv
    import io
    import platform

    buf = io.StringIO()
    for key, value in (("what", what), ("command", command + " " + " ".join(sys.argv[1:])),
                       ("commit", git_revision()), ("date", time.strftime("%Y-%m-%d")),
                       ("machine", f"{platform.processor() or platform.machine()}, "
                                   f"{os.cpu_count()} cores, load average "
                                   f"{os.getloadavg()[0]:.1f}")):
        buf.write(f"# {key}: {value}\n")
    writer = csv.DictWriter(buf, list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(path, buf.getvalue())


def _scored(path: str) -> list[dict[str, str]]:
    """The rows of one of evaluate's result files."""
    import csv

    try:
        lines = [ln for ln in Path(path).read_text().splitlines() if not ln.startswith("#")]
    except OSError as e:
        raise ValueError(f"{path}: {e}") from None
    return list(csv.DictReader(lines))


def _defined(row: dict[str, str]) -> bool:
    """A result row's score is defined (empty: the reference earns what closed earns)."""
    return row["score"] not in ("", "nan")


def _by_scenario(results: list[str]) -> list[dict[str, Any]]:
    """A row per (set, scenario): the reference's gain over closed per step
    (intervals 1-9) and each label's mean score there (empty: undefined)."""
    table: dict[tuple[str, str], dict[str, Any]] = {}
    labels: list[str] = []
    for given in results:
        label, _, path = given.rpartition("=")
        label = label or Path(path).stem
        labels.append(label)
        per: dict[tuple[str, str], list[float]] = {}
        for r in _scored(path):
            key = (r["set"], r["scenario"])
            row = table.setdefault(key, {"set": key[0], "scenario": key[1],
                                         "reference gain per step": ""})
            if r.get("reference_gain_per_step"):
                row["reference gain per step"] = r["reference_gain_per_step"]
            if _defined(r):
                per.setdefault(key, []).append(float(r["score"]))
        for key in table:
            if key in per:
                table[key][label] = round(float(np.mean(per[key])), 3)
    return [{**{k: row[k] for k in ("set", "scenario", "reference gain per step")},
             **{label: row.get(label, "") for label in dict.fromkeys(labels)}}
            for row in table.values()]


def _pool(given: str) -> tuple[str, list[str]]:
    """--pool NAME=SET,SET,...: a row per policy over those sets' scenarios together."""
    name, _, sets = given.partition("=")
    members = [x for x in sets.split(",") if x]
    if not name or len(members) < 2:
        raise ValueError(f"--pool {given!r}: expected NAME=SET,SET[,...] (two sets or more)")
    return name, members


Runs = dict[tuple[str, str], list[float]]  # (set, scenario) -> its runs' scores


def _summary_row(label: str, which: str, scored: list[dict[str, str]],
                 where: str) -> tuple[dict[str, Any], Runs]:
    """The summary of one policy's runs on a set (or a pool of sets, its scenarios
    told apart by set), and those runs per scenario: an empty score is undefined
    (the reference earns what closed earns), counted apart and not as a run."""
    cells = [r for r in scored if _defined(r)]
    if not cells:
        raise ValueError(f"{where}: no defined score in set {which}")
    per_scenario: Runs = {}
    for r in cells:
        per_scenario.setdefault((r["set"], r["scenario"]), []).append(float(r["score"]))
    means = {k: float(np.mean(v)) for k, v in per_scenario.items()}
    worst = min(means, key=means.get)
    spread = stats.set_mean(stats.tasks_of(per_scenario))
    return {"policy": label, "set": which, "runs": len(cells),
            "mean score": round(spread.point, 3),
            "95% interval": f"[{spread.low:.3f}, {spread.high:.3f}]",
            "worst scenario": f"{worst[1]} ({means[worst]:.3f})",
            "scenarios below 0.60": sum(v < 0.6 for v in means.values()),
            "undefined runs": len(scored) - len(cells)}, per_scenario


def _against(runs: Runs, others: Runs) -> str:
    """The mean's difference from another policy's on the scenarios both have
    defined, with its paired 95% interval (stats.set_difference)."""
    shared = [k for k in runs if k in others]
    if not shared:
        return ""
    d = stats.set_difference(stats.tasks_of(runs, shared), stats.tasks_of(others, shared))
    return f"{d.point:+.3f} [{d.low:+.3f}, {d.high:+.3f}]"


def cmd_summarize(a: argparse.Namespace) -> int:
    """One row per (result file, set): runs, mean score and its 95% interval
    (the scenarios drawn again, then their runs: stats.set_mean), worst score,
    scenarios below 0.60, undefined runs, and one per (policy, --pool) over the
    pool's sets together; with --versus LABEL, each row's difference from that
    policy's mean on the same scenarios and its paired interval; or with
    --by-scenario one per (set, scenario)."""
    if a.by_scenario:
        rows = _by_scenario(a.results)
        try:
            write_result(a.out, "per-scenario normalized scores (intervals 1-9, against the "
                         "reference and closed; empty: undefined) and the reference's gain "
                         "over closed per step, from " +
                         ", ".join(g.rpartition("=")[2] for g in a.results), rows)
        except OSError as e:
            print(f"adaptive: error: cannot write {a.out}: {e}", file=sys.stderr)
            return EXIT_STORAGE
        print(f"adaptive: {len(rows)} scenarios written to {a.out}")
        return 0
    pools = [_pool(given) for given in a.pool]
    summaries: list[tuple[dict[str, Any], Runs]] = []
    by_label: dict[str, list[dict[str, str]]] = {}
    for given in a.results:
        label, _, path = given.rpartition("=")
        label = label or Path(path).stem
        scored = _scored(path)
        by_label.setdefault(label, []).extend(scored)
        for which in dict.fromkeys(r["set"] for r in scored):
            summaries.append(_summary_row(label, which,
                                          [r for r in scored if r["set"] == which], path))
    named = {r["set"] for scored in by_label.values() for r in scored}
    for name, sets in pools:
        if name in named:
            raise ValueError(f"--pool {name}: a set of the results already has that name")
        pooled = [(label, [r for r in scored if r["set"] in sets])
                  for label, scored in by_label.items()
                  if set(sets) <= {r["set"] for r in scored}]
        if not pooled:
            raise ValueError(f"--pool {name}: no policy has results on every one of "
                             f"{', '.join(sets)}")
        summaries += [_summary_row(label, name, cells, name) for label, cells in pooled]
    if a.versus:
        if a.versus not in by_label:
            raise ValueError(f"--versus {a.versus!r}: no result file has that label (the "
                             f"labels: {', '.join(by_label)})")
        reference = {row["set"]: runs for row, runs in summaries if row["policy"] == a.versus}
        for row, runs in summaries:
            shared = row["set"] in reference and row["policy"] != a.versus
            row[f"against {a.versus}"] = _against(runs, reference[row["set"]]) if shared else ""
    rows = [row for row, _ in summaries]
    try:
        write_result(a.out, "per-scenario normalized scores summarized per set (intervals 1-9, "
                     "against the reference and closed), from " +
                     ", ".join(g.rpartition("=")[2] for g in a.results), rows)
    except OSError as e:
        print(f"adaptive: error: cannot write {a.out}: {e}", file=sys.stderr)
        return EXIT_STORAGE
    for r in rows:
        print(f"adaptive: {r['policy']}: {r['set']}: mean {r['mean score']:.3f} "
              f"{r['95% interval']}, worst "
              f"{r['worst scenario']}, {r['scenarios below 0.60']} below 0.60"
              + (f", {r['undefined runs']} runs undefined" if r["undefined runs"] else "")
              + (f", against {a.versus} {r[f'against {a.versus}']}"
                 if r.get(f"against {a.versus}") else ""))
    return 0
