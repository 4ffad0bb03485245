"""The benchmark's scores: each method's normalized score (0 is all valves
closed, 1 the reference) and its reward as a fraction of the oracle MPC's.

Both are taken per cell, a (scenario, seed, interval), from the method's mean
reward per step experienced in that interval, r:

* normalized score = (r - closed) / (reference - closed), where closed and
  reference are the rewards per step of ``closed`` (all valves closed) and of
  the benchmark's reference method (``--reference``, by default ``oracle-mpc``)
  in the same cell, the convention D4RL made standard. closed scores exactly 0
  and the reference exactly 1; a cell where the two earn the same reward (for
  instance an interval before any fault has grown: closed is then as good as
  the planner), or where either run is missing, has no score. Computed by
  benchmark.collect_benchmark into results.csv (``reference_reward_per_step``,
  ``closed_reward_per_step``, ``normalized_score``).
* fraction = r / oracle, oracle being ``oracle-mpc``'s reward per step (the
  planner that knows the faults) in the same cell. Rewards per step are
  positive here (r = (1 - |cg| / 3) sigma - mean(u); a full balanced plant
  earns 2.16, and interval means stay well above 0), so 1 is the oracle's
  reward; a cell whose oracle reward is missing or not positive has no
  fraction. Computed here, once, into fractions.csv.

The figure and report.md / report.html read results.csv and fractions.csv;
the report counts the cells without a score or a fraction. The report leads with
the per-run score's aggregates and their intervals (score_tables: a run is
normalized over its intervals, which no single cell can carry), the per-cell
tables follow.
"""

from __future__ import annotations

import csv
import json
import math
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ftc.common.atomic import atomic_write_csv, atomic_write_text
from ftc.control.registry import canonical
from ftc.experiments import figures, score_tables
from ftc.experiments.report import Block, to_html, to_markdown

# the fraction's denominator (and the score's 1 in benchmarks recorded without a reference)
ORACLE = "oracle-mpc"
CLOSED = "closed"  # the score's 0
REFERENCE = "reference"  # the score's default 1: whole episodes optimised on the true physics
FRACTION_COLUMNS = ("scenario", "method", "seed", "interval", "reward_per_step",
                    "oracle_reward_per_step", "fraction")
SCORE_COLUMNS = ("reference_reward_per_step", "closed_reward_per_step", "normalized_score")
FIGURE = "benchmark_score"
FLOOR = -1.5  # the figure's lowest score shown (below: counted, not drawn)


def _num(v: object) -> float | None:
    try:
        x = None if v is None or v == "" else float(v)
    except (TypeError, ValueError):
        return None
    return x if x is not None and math.isfinite(x) else None


def _cell_key(r: dict) -> tuple[str, int, int]:
    return r["scenario"], int(r["seed"]), int(r["interval"])


def normalized_score(r: float | None, reference: float | None,
                     closed: float | None) -> float | None:
    """(r - closed) / (reference - closed) of rewards per step in one cell: 0 is
    closed's reward, 1 the reference's. None when a reward is missing or the
    reference earns exactly what closed earns (no spread to measure in)."""
    if r is None or reference is None or closed is None or reference == closed:
        return None
    # + 0.0: closed's own score is -0.0 where the reference earns less than closed
    return (r - closed) / (reference - closed) + 0.0


def normalized_scores(rows: Sequence[dict], reference: str) -> list[dict]:
    """Rows of results (scenario, method, seed, interval, reward_per_step, ...) ->
    copies with ``reference_reward_per_step`` and ``closed_reward_per_step`` (the
    reference's and closed's in the same scenario, seed and interval; None if that
    run is missing) and ``normalized_score`` (None where undefined)."""
    def per_cell(method: str) -> dict:
        return {_cell_key(r): _num(r.get("reward_per_step")) for r in rows
                if r["method"] == method}

    ref, closed = per_cell(reference), per_cell(CLOSED)
    out = []
    for r in rows:
        b, c = ref.get(_cell_key(r)), closed.get(_cell_key(r))
        out.append({**r, "reference_reward_per_step": b, "closed_reward_per_step": c,
                    "normalized_score": normalized_score(_num(r.get("reward_per_step")), b, c)})
    return out


def read_scores(path: Path) -> list[dict]:
    """results.csv back, its cells and scores only: scenario, method, seed and
    interval (ints), reward_per_step and SCORE_COLUMNS (floats or None)."""
    with open(path, newline="") as f:
        return [{"scenario": r["scenario"], "method": canonical(r["method"]), "seed": int(r["seed"]),
                 "interval": int(r["interval"]), "reward_per_step": _num(r["reward_per_step"]),
                 **{c: _num(r.get(c)) for c in SCORE_COLUMNS}} for r in csv.DictReader(f)]


def oracle_fractions(rows: Sequence[dict], oracle: str = ORACLE) -> list[dict]:
    """Rows of results (scenario, method, seed, interval, reward_per_step) ->
    the same cells with the oracle's reward per step and the fraction (None
    where the oracle's reward is missing or not positive)."""
    base = {_cell_key(r): _num(r.get("reward_per_step")) for r in rows if r["method"] == oracle}
    out = []
    for r in rows:
        key = _cell_key(r)
        v, b = _num(r.get("reward_per_step")), base.get(key)
        out.append({"scenario": key[0], "method": r["method"], "seed": key[1],
                    "interval": key[2], "reward_per_step": v, "oracle_reward_per_step": b,
                    "fraction": v / b if v is not None and b is not None and b > 0 else None})
    return out


def read_fractions(path: Path) -> list[dict]:
    """fractions.csv back: seed and interval as ints, numbers as floats or None."""
    with open(path, newline="") as f:
        return [{"scenario": r["scenario"], "method": canonical(r["method"]), "seed": int(r["seed"]),
                 "interval": int(r["interval"]), "reward_per_step": _num(r["reward_per_step"]),
                 "oracle_reward_per_step": _num(r["oracle_reward_per_step"]),
                 "fraction": _num(r["fraction"])} for r in csv.DictReader(f)]


@dataclass
class MethodSummary:
    """One method's values of one measure (normalized score or fraction):
    per-interval means (over scenarios and seeds), the mean over every cell that
    has a value, and the worst interval, seed and scenario (lowest mean over that
    interval's, seed's or scenario's cells); the worst cell is the lowest
    (scenario, interval), mean over seeds."""

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


def summarise(rows: Sequence[dict], methods: Sequence[str],
              measure: str = "fraction") -> list[MethodSummary]:
    """A summary of column ``measure`` (``fraction`` or ``normalized_score``) per
    method that has a value in at least one cell, in ``methods`` order."""
    out = []
    for m in methods:
        cells = [r for r in rows if r["method"] == m and r.get(measure) is not None]
        if not cells:
            continue
        by: dict[str, dict] = {"interval": defaultdict(list), "seed": defaultdict(list),
                               "scenario": defaultdict(list)}
        by_cell: dict = defaultdict(list)
        for r in cells:
            for k in by:
                by[k][r[k]].append(r[measure])
            by_cell[(r["scenario"], r["interval"])].append(r[measure])
        out.append(MethodSummary(
            m, {k: float(np.mean(v)) for k, v in sorted(by["interval"].items())},
            float(np.mean([r[measure] for r in cells])), _worst(by["interval"]),
            _worst(by["seed"]), _worst(by["scenario"]), _worst(by_cell), len(cells)))
    return out


def per_scenario(rows: Sequence[dict], scenario: str,
                 measure: str = "fraction") -> dict[str, dict[int, float]]:
    """method -> interval -> mean of ``measure`` over seeds, in one scenario."""
    per: dict = defaultdict(lambda: defaultdict(list))
    for r in rows:
        if r["scenario"] == scenario and r.get(measure) is not None:
            per[r["method"]][r["interval"]].append(r[measure])
    return {m: {k: float(np.mean(v)) for k, v in iv.items()} for m, iv in per.items()}


# ---------------------------------------------------------------------------
# The figure (reads results.csv)
# ---------------------------------------------------------------------------

def draw_figure(run_dir: Path, methods: Sequence[str], labels: dict[str, str],
                reference: str = ORACLE, intervals: int | None = None) -> Path | None:
    """figures/benchmark_score.png: left, each method's normalized score per
    interval (mean over scenarios and seeds; closed is the line at 0, the reference
    the line at 1; ``intervals``: the x axis spans them all, so an interval without
    a score is a visible gap); right, its spread over scenarios (one point per
    scenario: the mean over seeds and intervals; box: quartiles)."""
    plt = figures.pyplot()

    scores = read_scores(Path(run_dir) / "results.csv")
    shown = [s for s in summarise(scores, methods, "normalized_score")
             if s.method not in (reference, CLOSED)]
    if not shown:
        (Path(run_dir) / "figures" / f"{FIGURE}.png").unlink(missing_ok=True)
        return None
    color = lambda i, m: figures.METHOD_COLORS.get(m, f"C{(i + 4) % 10}")  # noqa: E731
    with plt.rc_context(figures.STYLE):
        fig, (left, right) = plt.subplots(1, 2, figsize=(7.5, 4.6),
                                          gridspec_kw={"width_ratios": [3, 2]})
        for ax in (left, right):
            ax.axhline(1.0, color="black", ls="--", lw=0.8)
            ax.axhline(0.0, color=color(0, CLOSED), ls=":", lw=0.8)
        left.lines[0].set_label(f"{labels.get(reference, reference)} (1)")
        left.lines[1].set_label(f"{labels.get(CLOSED, CLOSED)} (0)")
        spread = []
        for i, s in enumerate(shown):
            k = sorted(s.per_interval)
            left.plot(k, [s.per_interval[j] for j in k], "-o", ms=3, color=color(i, s.method),
                      label=labels.get(s.method, s.method))
            by_scenario = defaultdict(list)
            for r in scores:
                if r["method"] == s.method and r["normalized_score"] is not None:
                    by_scenario[r["scenario"]].append(r["normalized_score"])
            spread.append([float(np.mean(v)) for v in by_scenario.values()])
        left.set_xlabel("interval")
        left.set_ylabel("(r - closed) / (reference - closed)")
        left.set_title("Normalized score (mean over scenarios and seeds)")
        left.xaxis.set_major_locator(plt.MaxNLocator(integer=True))
        if intervals:
            left.set_xlim(-0.5, intervals - 0.5)
        left.legend(loc="upper center", bbox_to_anchor=(0.5, -0.3), frameon=False, ncol=2)
        right.boxplot(spread, showfliers=False, widths=0.5)
        rng = np.random.default_rng(0)  # jitter only
        for i, values in enumerate(spread):
            right.plot(i + 1 + rng.uniform(-0.15, 0.15, len(values)), values, "o", ms=2.5,
                       alpha=0.7, color=color(i, shown[i].method))
        right.set_xticks(range(1, len(shown) + 1), [s.method for s in shown], rotation=30,
                         ha="right")
        right.set_title("Per scenario (mean over seeds, intervals)")
        # a cell where the reference earns barely more than closed divides by almost 0:
        # the axes show [FLOOR, 1.1] and say how many points lie below
        values = [v for s in shown for v in s.per_interval.values()] + \
            [v for vs in spread for v in vs]
        if values and min(values) < FLOOR:
            for ax in (left, right):
                ax.set_ylim(FLOOR, 1.15)
            below = sum(v < FLOOR for v in values)
            fig.text(0.99, 0.01, f"{below} points below {FLOOR} not shown", ha="right",
                     va="bottom", fontsize=7)
        fig.tight_layout()
        return figures._save(fig, Path(run_dir) / "figures" / FIGURE, ("png",))[0]


# ---------------------------------------------------------------------------
# The report
# ---------------------------------------------------------------------------

def fmt(v: float | None) -> str:
    """A score as the tables show it: three decimals, empty where undefined."""
    return "" if v is None else f"{v:.3f}"


def worst_columns(s: MethodSummary) -> list[str]:
    """The worst interval, seed, scenario and scenario-interval of a summary,
    each as "score (where)": the report's and the suite result file's columns."""
    return [f"{fmt(s.worst_interval[1])} (interval {s.worst_interval[0]})",
            f"{fmt(s.worst_seed[1])} (seed {s.worst_seed[0]})",
            f"{fmt(s.worst_scenario[1])} ({s.worst_scenario[0]})",
            f"{fmt(s.worst_cell[1])} ({s.worst_cell[0][0]}, interval {s.worst_cell[0][1]})"]


WORST_HEADER = ["worst interval", "worst seed", "worst scenario", "worst scenario-interval"]


def _per_interval_table(summaries: Sequence[MethodSummary], name: Callable[[str], str],
                        intervals: int) -> Block:
    return Block("table", header=["method", *[str(k) for k in range(intervals)], "mean"],
                 rows=[[name(s.method), *[fmt(s.per_interval.get(k)) for k in range(intervals)],
                        fmt(s.mean)] for s in summaries])


def score_blocks(scores: Sequence[MethodSummary], fractions: Sequence[MethodSummary],
                 labels: dict[str, str], intervals: int) -> list[Block]:
    """The lead table (normalized score: mean, the mean fraction beside it, the
    worst interval, seed, scenario and scenario-interval) and the score per interval."""
    name = lambda m: f"{m} ({labels.get(m, m)})"  # noqa: E731
    fraction = {s.method: s.mean for s in fractions}
    return [
        Block("table", header=["method", "normalized score", "fraction of the oracle",
                               *WORST_HEADER, "cells"],
              rows=[[name(s.method), fmt(s.mean), fmt(fraction.get(s.method)),
                     *worst_columns(s), str(s.cells)] for s in scores]),
        Block("p", "Normalized score per interval (mean over scenarios and seeds)."),
        _per_interval_table(scores, name, intervals),
    ]


def summary_blocks(summaries: Sequence[MethodSummary], labels: dict[str, str],
                   intervals: int) -> list[Block]:
    """The fraction's summary table (mean, worst interval, worst seed, worst
    scenario, worst scenario-interval) and its per-interval table."""
    name = lambda m: f"{m} ({labels.get(m, m)})"  # noqa: E731
    return [
        Block("table", header=["method", "mean fraction", *WORST_HEADER, "cells"],
              rows=[[name(s.method), fmt(s.mean), *worst_columns(s), str(s.cells)]
                    for s in summaries]),
        Block("p", "Fraction of the oracle per interval (mean over scenarios and seeds)."),
        _per_interval_table(summaries, name, intervals),
    ]


def _no_score_line(scores: Sequence[dict]) -> str:
    """How many cells have no normalized score, and why; and how many have a
    reference that earns less than closed (the score's scale reversed there)."""
    cells = {(r["scenario"], r["seed"], r["interval"]): r for r in scores}.values()
    tied = sum(1 for r in cells if r["reference_reward_per_step"] is not None
               and r["reference_reward_per_step"] == r["closed_reward_per_step"])
    missing = sum(1 for r in cells if r["reference_reward_per_step"] is None
                  or r["closed_reward_per_step"] is None)
    below = sum(1 for r in cells if r["reference_reward_per_step"] is not None
                and r["closed_reward_per_step"] is not None
                and r["reference_reward_per_step"] < r["closed_reward_per_step"])
    parts = []
    if tied or missing:
        parts.append(f" {tied + missing} of {len(cells)} (scenario, seed, interval) cells have no "
                     f"score: {tied} where the reference earns exactly what closed earns, "
                     f"{missing} where the reference's or closed's run is missing.")
    if below:
        parts.append(f" In {below} cells the reference earns less than closed: there a method "
                     "that beats closed scores below 0.")
    return "".join(parts)


def build_blocks(run_dir: Path) -> list[Block]:
    run_dir = Path(run_dir)
    meta = json.loads((run_dir / "benchmark.json").read_text())
    config = meta["config"]
    methods, n_int = config["methods"], int(config["intervals"])
    reference = config.get("reference", ORACLE)
    labels = {m: spec["label"] for m, spec in meta.get("methods", {}).items()}
    results = json.loads((run_dir / "results.json").read_text())
    fractions = read_fractions(run_dir / "fractions.csv")
    scores = read_scores(run_dir / "results.csv")
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
            ["normalized score 0 and 1", f"{CLOSED} ({labels.get(CLOSED, CLOSED)}) and "
                                         f"{reference} ({labels.get(reference, reference)})"],
            ["controller seeds", ", ".join(str(s) for s in config["seeds"])],
            ["intervals x steps per interval", f"{n_int} x {config['steps_per_interval']}"],
            ["plant link", config["link"]],
            ["finished runs", f"{len(results['runs'])} of {expected}"],
        ])]
    if len(results["runs"]) < expected:
        blocks.append(Block("p", f"**Incomplete:** {expected - len(results['runs'])} of "
                                 f"{expected} runs have no results (failed or not run); "
                                 "complete them with `--resume`."))
    fraction_summaries = summarise(fractions, methods)
    score_summaries = summarise(scores, methods, "normalized_score")
    blocks += score_tables.score_blocks(run_dir, scores, methods, labels,
                                        run_dir / "scenarios", n_int, (reference, CLOSED))
    blocks += [
        Block("h2", "Normalized score per cell"),
        Block("p", "In every scenario, seed and interval, a method's *normalized score* is "
                   "(r - closed) / (reference - closed), where r is its mean reward per step "
                   "experienced in that interval (`reward_per_step`, exploration included), "
                   f"closed is all valves closed's (`{CLOSED}`) and reference is "
                   f"`{reference}`'s in the same scenario, seed and interval: closed scores "
                   "exactly 0 and the reference exactly 1, the convention D4RL made standard. "
                   "The *fraction of the oracle* beside it is r / `oracle-mpc`'s (next "
                   "section). *Mean*: over every cell with a score; *worst interval*: the "
                   "lowest per-interval mean (over scenarios and seeds); *worst seed*: the "
                   "lowest mean over one seed's cells; *worst scenario*: the lowest mean over "
                   "one scenario's cells; *worst scenario-interval*: the lowest mean over "
                   "seeds of one scenario's interval; *cells*: those with a score."
                   + _no_score_line(scores))]
    if score_summaries:
        blocks += score_blocks(score_summaries, fraction_summaries, labels, n_int)
    if (run_dir / "figures" / f"{FIGURE}.png").is_file():
        blocks.append(Block("img", "Normalized score (0: all valves closed, 1: the reference): "
                                   "per interval (left, mean over scenarios and seeds) and per "
                                   "scenario (right, one point per scenario)",
                            path=f"figures/{FIGURE}.png"))
    missing = sum(1 for r in fractions if r["fraction"] is None)
    blocks += [
        Block("h2", "Fraction of the oracle"),
        Block("p", "A method's *fraction* is its `reward_per_step` divided by the oracle "
                   "MPC's (`oracle-mpc`, which knows the faults) in the same scenario, seed "
                   "and interval. Rewards per step are positive here, so 1 is the oracle's "
                   "reward and the oracle's own fraction is exactly 1; closed's is well above "
                   "0, which is why the score above leads. Mean and worst as above, over the "
                   "cells with a fraction."
                   + (f" {missing} cells have no fraction (oracle run missing or its reward "
                      "not positive)." if missing else ""))]
    if fraction_summaries:
        blocks += summary_blocks(fraction_summaries, labels, n_int)
    blocks += _scenario_blocks(meta, scores, fractions, methods, labels, n_int)
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


def _mean(values: Sequence[float]) -> float | None:
    return float(np.mean(values)) if len(values) else None


def _scenario_blocks(meta: dict, scores: Sequence[dict], fractions: Sequence[dict],
                     methods: Sequence[str], labels: dict[str, str],
                     intervals: int) -> list[Block]:
    """Per scenario: its faults, and every method's normalized score per interval
    (mean over seeds), its mean, the mean fraction and the mean reward per step."""
    blocks = [Block("h2", "Per scenario")]
    for stem in meta["config"]["scenarios"]:
        info = meta.get("scenarios", {}).get(stem, {})
        score = per_scenario(scores, stem, "normalized_score")
        fraction = per_scenario(fractions, stem)
        rps: dict = defaultdict(list)
        for r in scores:
            if r["scenario"] == stem and r["reward_per_step"] is not None:
                rps[r["method"]].append(r["reward_per_step"])
        blocks.append(Block("h3", f"{stem}: {info.get('description', '?')}"))
        rows = [[m, *[fmt(score.get(m, {}).get(k)) for k in range(intervals)],
                 fmt(_mean(list(score.get(m, {}).values()))),
                 fmt(_mean(list(fraction.get(m, {}).values()))), fmt(_mean(rps[m]))]
                for m in methods if m in rps]
        if rows:
            blocks.append(Block("table", header=["method", *[str(k) for k in range(intervals)],
                                                 "mean score", "mean fraction", "reward/step"],
                                rows=rows))
        else:
            blocks.append(Block("p", "No finished run."))
    return blocks


def write_report(run_dir: Path) -> tuple[Path, Path]:
    """fractions.csv from results.json, the figure from results.csv (its
    normalized scores), then report.md and report.html."""
    run_dir = Path(run_dir)
    meta = json.loads((run_dir / "benchmark.json").read_text())
    rows = json.loads((run_dir / "results.json").read_text())["metrics"]
    fractions = oracle_fractions(rows)
    atomic_write_csv(run_dir / "fractions.csv", list(FRACTION_COLUMNS),
                     [["" if r[c] is None else r[c] for c in FRACTION_COLUMNS]
                      for r in fractions])
    labels = {m: spec["label"] for m, spec in meta.get("methods", {}).items()}
    draw_figure(run_dir, meta["config"]["methods"], labels,
                meta["config"].get("reference", ORACLE), int(meta["config"]["intervals"]))
    blocks = build_blocks(run_dir)
    md, page = run_dir / "report.md", run_dir / "report.html"
    atomic_write_text(md, to_markdown(blocks))
    atomic_write_text(page, to_html(blocks, run_dir))
    return md, page
