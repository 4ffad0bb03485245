"""The report of a run directory: report.md and report.html (figures inline).

Built from saved results only (experiment.json, results.json, the runs'
result.json files, model_search.json, figures/): per-interval mean tables
(experienced and deterministic evaluation) for every method and experiment,
the world model's R^2 per refit, wall times, every trial's scenario and the
ranked world-model search. The report is a list of blocks rendered twice,
as Markdown and as self-contained HTML.
"""

from __future__ import annotations

import base64
import html
import json
import math
import re
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ftc.common.atomic import atomic_write_text
from ftc.experiments import figures


@dataclass
class Block:
    kind: str  # "h1" | "h2" | "h3" | "p" | "table" | "img"
    text: str = ""
    header: Sequence[str] = ()
    rows: Sequence[Sequence[str]] = ()
    path: str = ""  # image path relative to the run directory


def _fmt(v: float, digits: int = 3) -> str:
    return "" if v is None or not np.isfinite(v) else f"{v:.{digits}f}"


def _mean_std(values: list[float], digits: int = 3) -> str:
    vals = [v for v in values if v is not None and np.isfinite(v)]
    if not vals:
        return ""
    if len(vals) == 1:
        return _fmt(vals[0], digits)
    return f"{np.mean(vals):.{digits}f} ± {np.std(vals):.{digits}f}"


def _num(v: object) -> float | None:
    try:
        return None if v is None or v == "" else float(v)
    except (TypeError, ValueError):
        return None


def interval_table(metrics: list[dict], experiment: str, column: str, methods: Sequence[str],
                   labels: dict[str, str], intervals: int) -> Block | None:
    """Rows: methods; columns: intervals and the mean over intervals. A cell is
    the mean over trials (each trial first averaged over seeds), ± the std over
    trials when there are several (over seeds when there is one trial)."""
    per: dict = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    for r in metrics:
        v = _num(r.get(column))
        if r["experiment"] == experiment and v is not None and math.isfinite(v):
            per[r["method"]][int(r["interval"])][int(r["trial"])].append(v)
    if not per:
        return None
    rows = []
    for m in methods:
        if m not in per:
            continue
        cells, overall = [], []
        for k in range(intervals):
            trials = per[m].get(k, {})
            if len(trials) == 1:
                seeds = next(iter(trials.values()))
                cells.append(_mean_std(seeds))
                overall.append(float(np.mean(seeds)))
            elif trials:
                means = [float(np.mean(s)) for s in trials.values()]
                cells.append(_mean_std(means))
                overall.append(float(np.mean(means)))
            else:
                cells.append("")
        rows.append([labels.get(m, m), *cells, _fmt(float(np.mean(overall))) if overall else ""])
    return Block("table", header=["method", *[str(k) for k in range(intervals)], "mean"], rows=rows)


ORACLE = "oracle-mpc"


def oracle_fraction_table(metrics: list[dict], experiment: str, methods: Sequence[str],
                          labels: dict[str, str], intervals: int) -> Block | None:
    """Every method's experienced reward per step as a fraction of the oracle
    MPC's in the same interval (means over trials and seeds first)."""
    per: dict = defaultdict(lambda: defaultdict(list))
    for r in metrics:
        v = _num(r.get("reward_per_step"))
        if r["experiment"] == experiment and v is not None and math.isfinite(v):
            per[r["method"]][int(r["interval"])].append(v)
    if ORACLE not in per:
        return None
    oracle = {k: float(np.mean(v)) for k, v in per[ORACLE].items()}
    rows = []
    for m in methods:
        if m not in per or m == ORACLE:
            continue
        cells, fractions = [], []
        for k in range(intervals):
            if k in per[m] and oracle.get(k):
                f = float(np.mean(per[m][k])) / oracle[k]
                fractions.append(f)
                cells.append(f"{f:.3f}")
            else:
                cells.append("")
        rows.append([labels.get(m, m), *cells, f"{np.mean(fractions):.3f}" if fractions else ""])
    return Block("table", header=["method", *[str(k) for k in range(intervals)], "mean"], rows=rows)


def build_blocks(run_dir: Path) -> list[Block]:
    run_dir = Path(run_dir)
    meta = json.loads((run_dir / "experiment.json").read_text())
    config = meta["config"]
    methods = config["methods"]
    labels = {m: spec["label"] for m, spec in meta.get("methods", {}).items()}
    results_path = run_dir / "results.json"
    results = json.loads(results_path.read_text()) if results_path.is_file() else {
        "runs": [], "metrics": []}
    metrics, runs = results["metrics"], results["runs"]
    n_int = int(config["intervals"])

    blocks = [Block("h1", f"Fault-tolerant fuel transfer: experiment report ({run_dir.name})"),
              Block("p", f"Created {meta.get('created', '?')}; git revision "
                         f"`{meta.get('git_revision', '?')}`"
                         + (f" (runs made at {', '.join(meta['git_revisions'])})"
                            if len(meta.get("git_revisions", [])) > 1 else "") + "."),
              Block("table", header=["setting", "value"], rows=[
                  ["experiments", ", ".join(config["experiments"])],
                  ["methods", ", ".join(f"{m} ({labels.get(m, m)})" for m in methods)],
                  ["intervals x steps per interval", f"{n_int} x {config['steps_per_interval']}"],
                  ["controller seeds", ", ".join(str(s) for s in config["seeds"])],
                  ["aggregate trials (scenario seed)",
                   f"{config['trials']} ({config['scenario_seed']})"],
                  ["extra controller arguments", " ".join(config["controller_args"]) or "none"],
                  ["finished runs", str(len(runs))],
              ])]
    expected = 0
    for exp in config["experiments"]:
        trials = 1 if exp != "aggregate" else int(config["trials"])
        expected += trials * len(methods) * len(config["seeds"])
    if len(runs) < expected:
        blocks.append(Block("p", f"**Incomplete:** {expected - len(runs)} of {expected} runs "
                                 "have no results (failed or not run); complete them with "
                                 "`--resume`."))

    figures = [("a_reward_episode", "(a) Reward per step over one episode: nominal plant and "
                                    "the most degraded plant, valves all closed and all open."),
               ("b_reward_per_interval", "(b) Mean reward per step in each interval (solid: "
                                         "experienced, the paper's metric; dotted: deterministic "
                                         "evaluation)."),
               ("c_tank_control", "(c) Tank levels over one episode at the highest degradation; "
                                  "grey: valve open."),
               ("d_aggregate", "(d) Aggregate over random fault trials: mean and ±1 std.")]
    present = [(f, c) for f, c in figures if (run_dir / "figures" / f"{f}.png").is_file()]
    if present:
        blocks.append(Block("h2", "Figures"))
        for f, caption in present:
            blocks.append(Block("img", caption, path=f"figures/{f}.png"))

    names = {"single": "Single fault (E1, D_E = 20)",
             "multiple": "Multiple faults (E1 D_E = 20; tanks 5, 6 D_T = 20)",
             "aggregate": f"Aggregate ({config['trials']} random trials)"}
    for exp in config["experiments"]:
        blocks.append(Block("h2", names.get(exp, exp)))
        for column, what in (("reward_per_step", "Mean reward per step experienced on the plant "
                                                 "(exploration included; the paper's metric)"),
                             ("eval_reward_per_step", "Mean reward per step of a deterministic "
                                                      "evaluation episode of the current policy")):
            table = interval_table(metrics, exp, column, methods, labels, n_int)
            if table:
                spread = ("mean ± std over trials" if exp == "aggregate"
                          else "mean ± std over seeds" if len(config["seeds"]) > 1 else "")
                blocks.append(Block("p", f"{what}, per interval{'; ' + spread if spread else ''}."))
                blocks.append(table)
        table = oracle_fraction_table(metrics, exp, methods, labels, n_int)
        if table:
            blocks.append(Block("p", "Experienced reward per step as a fraction of the oracle "
                                     "MPC's (which knows the faults), per interval."))
            blocks.append(table)
        table = interval_table(metrics, exp, "model_r2", methods, labels, n_int)
        if table:
            table.rows = [r for r in table.rows if any(c for c in r[1:-1])]
            if table.rows:
                blocks.append(Block("p", "World model R^2 after each refit (on recent real data "
                                         "it did not train on, as reported by the controller)."))
                blocks.append(table)

    scenarios = meta.get("scenarios", {})
    if scenarios:
        blocks.append(Block("h2", "Scenarios"))
        rows = []
        for exp, trials in scenarios.items():
            for t, sc in enumerate(trials):
                rows.append([exp, str(t), sc["name"], sc["description"],
                             f"scenarios/{sc['name']}.toml"])
        blocks.append(Block("table", header=["experiment", "trial", "name", "faults", "file"],
                            rows=rows))

    if runs:
        blocks.append(Block("h2", "Wall times"))
        per: dict = defaultdict(list)
        for r in runs:
            per[(r["experiment"], r["method"])].append(float(r["wall_time_s"]))
        rows = [[exp, labels.get(m, m), str(len(v)), f"{np.mean(v):.1f}", f"{np.max(v):.1f}",
                 f"{np.sum(v):.1f}"] for (exp, m), v in sorted(per.items())]
        blocks.append(Block("table", header=["experiment", "method", "runs", "mean (s)",
                                             "max (s)", "total (s)"], rows=rows))
        wall = meta.get("wall_time_s")
        total = sum(float(r["wall_time_s"]) for r in runs)
        blocks.append(Block("p", f"Sum of run wall times {total:.0f} s"
                                 + (f"; the orchestrator's last session took {wall:.0f} s"
                                    if wall else "") + "."))

    ms = run_dir / "model_search.json"
    if ms.is_file():
        search = json.loads(ms.read_text())
        cfg = search["config"]
        blocks.append(Block("h2", "World-model search"))
        blocks.append(Block("p", f"{len(search['results'])} models, {cfg['folds']}-fold "
                                 f"cross-validated R^2 of the one-step change of level on "
                                 f"{cfg['episodes']} nominal episodes of random persistent valve "
                                 f"settings (folds split by episode), ranked; "
                                 f"{search['wall_time_s']:.0f} s in all."))
        blocks.append(Block("table", header=["rank", "hidden", "activation", "learning rate",
                                             "CV R^2", "fit time (s)"],
                            rows=[[str(r["rank"]), f"{r['layers']} x {r['width']}", r["activation"],
                                   f"{r['lr']:g}", f"{r['r2_mean']:.4f}",
                                   f"{r['fit_seconds']:.1f}"] for r in search["results"]]))
    return blocks


def to_markdown(blocks: list[Block]) -> str:
    out = []
    for b in blocks:
        if b.kind in ("h1", "h2", "h3"):
            out.append("#" * int(b.kind[1]) + " " + b.text)
        elif b.kind == "p":
            out.append(b.text)
        elif b.kind == "img":
            out.append(f"![{b.text}]({b.path})\n\n*{b.text}*")
        elif b.kind == "table":
            out.append("| " + " | ".join(b.header) + " |")
            out.append("|" + "|".join("---" for _ in b.header) + "|")
            out.extend("| " + " | ".join(r) + " |" for r in b.rows)
        out.append("")
    return "\n".join(out)


def _inline(text: str) -> str:
    """Escape, then render `code` and **bold** spans."""
    s = html.escape(text)
    s = re.sub(r"`([^`]+)`", r"<code>\1</code>", s)
    return re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", s)


def to_html(blocks: list[Block], run_dir: Path) -> str:
    parts = ["<!DOCTYPE html><html><head><meta charset='utf-8'>",
             f"<title>{html.escape(blocks[0].text if blocks else 'report')}</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;}"
             "table{border-collapse:collapse;margin:1em 0;font-size:0.9em}"
             "td,th{border:1px solid #bbb;padding:3px 7px;text-align:right}"
             "td:first-child,th:first-child{text-align:left}"
             "img{max-width:100%}figcaption{font-style:italic}</style></head><body>"]
    for b in blocks:
        if b.kind in ("h1", "h2", "h3"):
            parts.append(f"<{b.kind}>{_inline(b.text)}</{b.kind}>")
        elif b.kind == "p":
            parts.append(f"<p>{_inline(b.text)}</p>")
        elif b.kind == "img":
            data = base64.b64encode((Path(run_dir) / b.path).read_bytes()).decode()
            parts.append(f"<figure><img alt='{html.escape(b.text)}' "
                         f"src='data:image/png;base64,{data}'>"
                         f"<figcaption>{_inline(b.text)}</figcaption></figure>")
        elif b.kind == "table":
            parts.append("<table><tr>" + "".join(f"<th>{_inline(h)}</th>" for h in b.header)
                         + "</tr>")
            parts.extend("<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in r) + "</tr>"
                         for r in b.rows)
            parts.append("</table>")
    parts.append("</body></html>")
    return "\n".join(parts)


def write_report(run_dir: Path) -> tuple[Path, Path]:
    """Draw the figures from saved data, then write report.md and report.html."""
    run_dir = Path(run_dir)
    figures.draw_all(run_dir)
    blocks = build_blocks(run_dir)
    md, page = run_dir / "report.md", run_dir / "report.html"
    atomic_write_text(md, to_markdown(blocks))
    atomic_write_text(page, to_html(blocks, run_dir))
    return md, page
