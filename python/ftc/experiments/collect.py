"""Gather a run directory's finished runs into the tables the figures and the
report read: results.csv and results.json (every run's per-interval metrics),
and trajectories/*.csv (figure c: one episode at the highest degradation,
extracted from the recorded LCM logs)."""

from __future__ import annotations

import json
from pathlib import Path

from ftc.common.atomic import atomic_write_csv, atomic_write_json
from ftc.experiments.methods import METHODS
from ftc.experiments.runs import RunSpec, is_finished, plan_runs
from ftc.experiments.scenarios import EXPERIMENTS, ExperimentConfig
from ftc.plant.log import control_episode, read_log, write_trajectory_csv


def collect(out: Path) -> None:
    """Gather every finished run's metrics into results.csv/json and extract the
    tank-control episodes (figure c) from the recorded logs."""
    out = Path(out)
    meta = json.loads((out / "experiment.json").read_text())
    config = ExperimentConfig.from_json(meta["config"])
    rows, runs = [], []
    columns: list[str] = []
    for spec in plan_runs(config):
        d = spec.directory(out)
        if not is_finished(d):
            continue
        result = json.loads((d / "result.json").read_text())
        runs.append({k: result.get(k) for k in ("run", "experiment", "trial", "scenario",
                                                "method", "seed", "wall_time_s", "lcm_url",
                                                "prefix")})
        for m in json.loads((d / "metrics.json").read_text()):
            row = {"experiment": spec.experiment, "trial": spec.trial, "scenario": spec.scenario,
                   "method": spec.method, "seed": spec.seed, **m}
            columns += [k for k in row if k not in columns]
            rows.append(row)
    order = {m: i for i, m in enumerate(config.methods)}
    rows.sort(key=lambda r: (EXPERIMENTS.index(r["experiment"]), r["trial"],
                             order.get(r["method"], 99), r["seed"], r.get("interval", 0)))
    atomic_write_csv(out / "results.csv", columns,
                     [["" if r.get(c) is None else r.get(c) for c in columns] for r in rows])
    atomic_write_json(out / "results.json", {"runs": runs, "metrics": rows})
    _extract_tank_control(out, config)


def _extract_tank_control(out: Path, config: ExperimentConfig) -> None:
    """Figure (c): one episode at the highest degradation, from the paper's
    controller (PPO online + offline) when it ran, else another learner."""
    learners = [m for m in config.methods if METHODS[m].learns] or list(config.methods)
    preferred = [m for m in ("ppo-offline", "ppo-online") if m in learners]
    candidates = preferred + [m for m in reversed(learners) if m not in preferred]
    for exp in ("single", "multiple"):
        if exp not in config.experiments:
            continue
        for method in candidates:
            spec = RunSpec(exp, 0, method, int(config.seeds[0]), exp)
            log = spec.directory(out) / "plant.lcmlog"
            if not (is_finished(spec.directory(out)) and log.is_file()):
                continue
            traj = read_log(log)
            episode = control_episode(traj)
            write_trajectory_csv(traj.episode_rows(episode),
                                 out / "trajectories" / f"{exp}-tank-control.csv")
            atomic_write_json(out / "trajectories" / f"{exp}-tank-control.json",
                              {"run": spec.key, "method": method, "episode": episode,
                               "log": str(log.relative_to(out))})
            break
