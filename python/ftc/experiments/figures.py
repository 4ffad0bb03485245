"""The paper's figures, drawn from saved results only (never recomputed).

One function per figure; each writes ``<stem>.png`` and ``<stem>.svg`` and
returns the paths:

(a) :func:`reward_episodes`: reward per step over one episode, nominal vs
    degraded, valves all closed vs all open (``baselines/*.csv``);
(b) :func:`reward_per_interval`: mean reward per step in each interval for
    every method, single and multiple faults (``results.csv``);
(c) :func:`tank_control`: the six tank levels over one episode with each
    valve's open periods shaded (``trajectories/*.csv`` or ``ftc.tools.replay``);
(d) :func:`aggregate`: mean and one-standard-deviation band over the
    aggregate trials, per method and interval (``results.csv``).

:func:`draw_all` draws every figure whose data a run directory holds.
"""

from __future__ import annotations

import csv
import io
import json
from collections import defaultdict
from pathlib import Path
from typing import Sequence

import numpy as np

from ftc.control import registry
from ftc.common.atomic import atomic_write_bytes
from ftc.experiments.methods import METHODS


def pyplot():
    """matplotlib.pyplot on the Agg backend, imported on the first figure (a
    tool that only reads results does not pay for matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt

FORMATS = ("png", "svg")
#: Single-column paper figures: about 3.5 in wide; full width 7 in. Fonts of
#: 8-9 pt stay readable when the figure is printed at that width.
STYLE = {"font.size": 8, "axes.titlesize": 9, "axes.labelsize": 8, "legend.fontsize": 7,
         "xtick.labelsize": 7, "ytick.labelsize": 7, "lines.linewidth": 1.2,
         "savefig.dpi": 200, "axes.grid": True, "grid.alpha": 0.3}
METHOD_COLORS = registry.colors()  # one colour per method, from its registry entry
TANK_COLORS = ["#1b9e77", "#d95f02", "#7570b3", "#e7298a", "#66a61e", "#e6ab02"]


def _read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _float(v: str | None) -> float:
    try:
        return float(v) if v not in (None, "") else float("nan")
    except ValueError:
        return float("nan")


def _save(fig: "matplotlib.figure.Figure", stem: Path,
          formats: Sequence[str] = FORMATS) -> list[Path]:
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    paths = []
    try:
        for fmt in formats:
            path = stem.with_name(stem.name + "." + fmt)
            buf = io.BytesIO()
            fig.savefig(buf, format=fmt, bbox_inches="tight")
            atomic_write_bytes(path, buf.getvalue())
            paths.append(path)
    finally:
        pyplot().close(fig)
    return paths


def _labels(labels: dict[str, str] | None) -> dict[str, str]:
    out = {name: spec.label for name, spec in METHODS.items()}
    out.update(labels or {})
    return out


def _color(method: str, i: int) -> str:
    return METHOD_COLORS.get(method, f"C{(i + 4) % 10}")


# ---------------------------------------------------------------------------
# (a) reward over one episode
# ---------------------------------------------------------------------------

def reward_episodes(episodes: Sequence[tuple[str, str, Path]], stem: Path,
                    formats: Sequence[str] = FORMATS) -> list[Path]:
    """Figure (a). episodes: (condition label, policy 'closed'|'open', CSV with
    columns step, reward) per curve. Conditions are distinguished by line
    style, policies by colour; the legend gives each curve's mean."""
    plt = pyplot()
    with plt.rc_context(STYLE):
        fig, ax = plt.subplots(figsize=(3.5, 2.6))
        styles = ["-", "--", ":", "-."]
        conditions = list(dict.fromkeys(c for c, _, _ in episodes))
        for condition, policy, path in episodes:
            rows = _read_csv(path)
            step = np.array([_float(r["step"]) for r in rows])
            rew = np.array([_float(r["reward"]) for r in rows])
            ax.plot(step, rew, styles[conditions.index(condition) % len(styles)],
                    color=METHOD_COLORS[policy],
                    label=f"{condition}, all {policy} (mean {np.mean(rew):.2f})")
        ax.set_xlabel("time step in episode (s)")
        ax.set_ylabel("reward per step (-)")
        ax.set_title("Reward over one episode")
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), frameon=False, ncol=1)
        return _save(fig, stem, formats)


# ---------------------------------------------------------------------------
# (b) and (d): per-interval means from results.csv
# ---------------------------------------------------------------------------

def _per_interval(rows: list[dict], experiment: str, column: str
                  ) -> dict[str, dict[int, dict[int, float]]]:
    """method -> trial -> interval -> value averaged over seeds."""
    acc: dict = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    for r in rows:
        if r["experiment"] != experiment:
            continue
        v = _float(r.get(column))
        if np.isfinite(v):
            acc[r["method"]][int(r["trial"])][int(float(r["interval"]))].append(v)
    return {m: {t: {k: float(np.mean(v)) for k, v in iv.items()} for t, iv in tr.items()}
            for m, tr in acc.items()}


def _method_order(rows: list[dict], methods: Sequence[str] | None) -> list[str]:
    seen = list(dict.fromkeys(r["method"] for r in rows))
    return [m for m in methods if m in seen] if methods else seen


def reward_per_interval(results_csv: Path, stem: Path, experiments: Sequence[str] = ("single",
                        "multiple"), methods: Sequence[str] | None = None,
                        labels: dict[str, str] | None = None,
                        formats: Sequence[str] = FORMATS) -> list[Path]:
    """Figure (b): mean reward per step actually experienced in each interval
    (solid; the paper's metric) and the deterministic evaluation (dotted, for
    methods that have one), one panel per experiment, mean over seeds."""
    rows = _read_csv(results_csv)
    names = _labels(labels)
    experiments = [e for e in experiments if any(r["experiment"] == e for r in rows)]
    if not experiments:
        raise ValueError(f"{results_csv} has no rows for experiments {list(experiments)}")
    order = _method_order(rows, methods)
    plt = pyplot()
    import matplotlib  # loaded by pyplot()
    with plt.rc_context(STYLE):
        fig, axes = plt.subplots(1, len(experiments), figsize=(3.5 * len(experiments), 2.8),
                                 sharey=True, squeeze=False)
        for ax, exp in zip(axes[0], experiments):
            exp_data = _per_interval(rows, exp, "reward_per_step")
            eval_data = _per_interval(rows, exp, "eval_reward_per_step")
            for i, m in enumerate(order):
                if m not in exp_data:
                    continue
                iv = exp_data[m][min(exp_data[m])]
                k = sorted(iv)
                ax.plot(k, [iv[j] for j in k], "-o", ms=3, color=_color(m, i), label=names.get(m, m))
                if m in eval_data:
                    ev = eval_data[m][min(eval_data[m])]
                    ke = sorted(ev)
                    ax.plot(ke, [ev[j] for j in ke], ":", color=_color(m, i),
                            label=f"{names.get(m, m)} (evaluation)")
            ax.set_title(f"{exp.capitalize()} fault{'s' if exp == 'multiple' else ''}")
            ax.set_xlabel("degradation interval (-)")
            ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
        axes[0][0].set_ylabel("mean reward per step (-)")
        handles, names_ = axes[0][0].get_legend_handles_labels()
        for ax in axes[0][1:]:
            for h, n in zip(*ax.get_legend_handles_labels()):
                if n not in names_:
                    handles.append(h)
                    names_.append(n)
        fig.legend(handles, names_, loc="upper center", bbox_to_anchor=(0.5, 0.0), frameon=False,
                   ncol=min(4, len(names_)))
        return _save(fig, stem, formats)


def aggregate(results_csv: Path, stem: Path, methods: Sequence[str] | None = None,
              labels: dict[str, str] | None = None, experiment: str = "aggregate",
              formats: Sequence[str] = FORMATS) -> list[Path]:
    """Figure (d): mean over trials (each trial first averaged over seeds) of
    the reward per step experienced in each interval, with a band of +-1
    standard deviation over trials."""
    rows = _read_csv(results_csv)
    names = _labels(labels)
    data = _per_interval(rows, experiment, "reward_per_step")
    if not data:
        raise ValueError(f"{results_csv} has no rows for experiment '{experiment}'")
    plt = pyplot()
    import matplotlib  # loaded by pyplot()
    with plt.rc_context(STYLE):
        fig, ax = plt.subplots(figsize=(3.5, 2.8))
        for i, m in enumerate(_method_order(rows, methods)):
            if m not in data:
                continue
            intervals = sorted(set().union(*[set(iv) for iv in data[m].values()]))
            values = np.array([[data[m][t].get(k, np.nan) for k in intervals]
                               for t in sorted(data[m])])
            mean, std = np.nanmean(values, axis=0), np.nanstd(values, axis=0)
            ax.plot(intervals, mean, "-o", ms=3, color=_color(m, i),
                    label=f"{names.get(m, m)}")
            ax.fill_between(intervals, mean - std, mean + std, color=_color(m, i), alpha=0.2,
                            linewidth=0)
        n = max(len(d) for d in data.values())
        ax.set_title(f"Aggregate: {n} random fault trials (mean $\\pm$ 1 std)")
        ax.set_xlabel("degradation interval (-)")
        ax.set_ylabel("mean reward per step (-)")
        ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), frameon=False, ncol=2)
        return _save(fig, stem, formats)


# ---------------------------------------------------------------------------
# (c) tank control over one episode
# ---------------------------------------------------------------------------

def _open_periods(valve: np.ndarray, step: np.ndarray) -> list[tuple[float, float]]:
    """(start, end) times (s) where the valve was open; a valve applied during
    step k is open over (k-1, k]."""
    spans, start = [], None
    for v, k in zip(valve, step):
        if v and start is None:
            start = k - 1
        if not v and start is not None:
            spans.append((start, k - 1))
            start = None
    if start is not None:
        spans.append((start, step[-1]))
    return spans


def tank_control(episodes: Sequence[tuple[str, Path]], stem: Path,
                 formats: Sequence[str] = FORMATS) -> list[Path]:
    """Figure (c): one column per episode (title, trajectory CSV with columns
    step, u1..u6, x1..x6), one row per tank: its level (m) against time (s),
    with the periods its valve was open shaded."""
    plt = pyplot()
    import matplotlib  # loaded by pyplot()
    with plt.rc_context(STYLE):
        ncol = len(episodes)
        fig, axes = plt.subplots(6, ncol, figsize=(3.5 * ncol, 6.0), sharex="col", sharey=True,
                                 squeeze=False)
        for c, (title, path) in enumerate(episodes):
            rows = _read_csv(path)
            step = np.array([_float(r["step"]) for r in rows])
            acted = step > 0  # a step-0 row is the initial state: no valves applied yet
            for i in range(6):
                ax = axes[i][c]
                level = np.array([_float(r[f"x{i + 1}"]) for r in rows])
                valve = np.array([int(_float(r[f"u{i + 1}"])) for r in rows])
                for a, b in _open_periods(valve[acted], step[acted]):
                    ax.axvspan(a, b, color="0.75", alpha=0.6, linewidth=0)
                ax.plot(step, level, color=TANK_COLORS[i])
                ax.set_ylim(-0.05, 1.05)
                ax.set_ylabel(f"tank {i + 1}\nlevel (m)")
                if i == 0:
                    rew = np.array([_float(r.get("reward")) for r in rows])
                    extra = (f"; {np.nanmean(rew):.2f} per step"
                             if np.isfinite(rew).any() else "")
                    ax.set_title(title + extra, fontsize=7)
            axes[5][c].set_xlabel("time step in episode (s)")
        handles = [matplotlib.patches.Patch(color="0.75", alpha=0.6, label="valve open")]
        handles += [matplotlib.lines.Line2D([], [], color=TANK_COLORS[i], label=f"tank {i + 1}")
                    for i in range(6)]
        fig.legend(handles=handles, loc="lower center", ncol=7, frameon=False,
                   bbox_to_anchor=(0.5, -0.03))
        fig.tight_layout(rect=(0, 0.02, 1, 1))
        return _save(fig, stem, formats)


# ---------------------------------------------------------------------------
# Everything a run directory has data for
# ---------------------------------------------------------------------------

def draw_all(run_dir: Path) -> dict[str, list[Path]]:
    """Draw every figure whose saved data is present in run_dir; returns
    figure name -> written files."""
    run_dir = Path(run_dir)
    fig_dir = run_dir / "figures"
    meta = json.loads((run_dir / "experiment.json").read_text())
    methods = meta["config"]["methods"]
    labels = {m: spec["label"] for m, spec in meta.get("methods", {}).items()}
    top = meta["config"]["intervals"] - 1
    out: dict[str, list[Path]] = {}

    curves = []
    for stem_cond, label in (("nominal", "nominal"), ("single-age", f"single fault, interval {top}"),
                             ("multiple-age", f"multiple faults, interval {top}")):
        for policy in ("closed", "open"):
            matches = sorted((run_dir / "baselines").glob(f"{stem_cond}*-{policy}.csv"))
            if matches:
                curves.append((label, policy, matches[0]))
    if curves:
        out["a_reward_episode"] = reward_episodes(curves, fig_dir / "a_reward_episode")

    results = run_dir / "results.csv"
    if results.is_file() and results.stat().st_size > 0:
        rows = _read_csv(results)
        present = {r["experiment"] for r in rows}
        if present & {"single", "multiple"}:
            out["b_reward_per_interval"] = reward_per_interval(
                results, fig_dir / "b_reward_per_interval", methods=methods, labels=labels)
        if "aggregate" in present:
            out["d_aggregate"] = aggregate(results, fig_dir / "d_aggregate", methods=methods,
                                           labels=labels)

    episodes = []
    for exp in ("single", "multiple"):
        path = run_dir / "trajectories" / f"{exp}-tank-control.csv"
        info = run_dir / "trajectories" / f"{exp}-tank-control.json"
        if path.is_file():
            desc = json.loads(info.read_text()) if info.is_file() else {}
            rows = _read_csv(path)
            kind = "evaluation" if rows and rows[0].get("evaluation") == "1" else "online"
            age = rows[0]["age"] if rows else "?"
            episodes.append((f"{exp.capitalize()} fault{'s' if exp == 'multiple' else ''}: "
                             f"{labels.get(desc.get('method'), desc.get('method', ''))}\n"
                             f"{kind} episode at interval {age}", path))
    if episodes:
        out["c_tank_control"] = tank_control(episodes, fig_dir / "c_tank_control")
    return out
