"""One run of an experiment: a method's controller on one trial's scenario
with one seed, driving its own plant process on a private LCM URL (ttl=0) and
channel prefix, with a recorder logging that plant's traffic; and the
baseline episodes of figure (a).

A run directory (runs/EXP/tNN/METHOD/sS/) holds controller/ (the controller's
own outputs), plant.lcmlog, controller.log, metrics.csv, metrics.json and
result.json. A run counts as finished only once its result.json is written
(atomically, last).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from ftc.common.atomic import atomic_write_csv, atomic_write_json
from ftc.control.baselines import baseline_valves
from ftc.experiments.methods import METHODS
from ftc.experiments.processes import (LcmLogger, RunFailed, RunHandle, record_process,
                                       stop_leftover_processes)
from ftc.experiments.scenarios import ExperimentConfig, experiment_scenarios
from ftc.plant import launch, private_lcm_url, private_prefix, trajectory
from ftc.plant.log import read_log
from ftc.plant.reward import reward


class IncompleteLog(RunFailed):
    """The recorder missed messages; the run is redone (its results would not
    be reproducible from its log)."""


@dataclass(frozen=True)
class RunSpec:
    """One controller run: a method on one trial's scenario with one seed."""

    experiment: str
    trial: int
    method: str
    seed: int
    scenario: str  # scenario name, file scenarios/<name>.toml

    @property
    def key(self) -> str:
        return f"{self.experiment}/t{self.trial:02d}/{self.method}/s{self.seed}"

    def directory(self, out: Path) -> Path:
        return out / "runs" / self.key


def plan_runs(config: ExperimentConfig) -> list[RunSpec]:
    """Every run of the configured experiments, most expensive first."""
    runs = []
    for exp, scenarios in experiment_scenarios(config).items():
        for t, sc in enumerate(scenarios):
            for m in config.methods:
                for s in config.seeds:
                    runs.append(RunSpec(exp, t, m, int(s), sc.name))
    return sorted(runs, key=lambda r: -METHODS[r.method].cost)


def is_finished(run_dir: Path) -> bool:
    """A run is finished when its result.json says so (it is written last)."""
    try:
        return json.loads((run_dir / "result.json").read_text()).get("status") == "ok"
    except (OSError, ValueError):
        return False


def read_metrics_csv(path: Path) -> list[dict]:
    """Rows of a controller metrics.csv; numbers as floats, empty cells as None."""
    rows = []
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            rows.append({k: _number(v) for k, v in row.items()})
    return rows


def _number(v: str | None) -> int | float | str | None:
    if v is None or v == "":
        return None
    try:
        x = float(v)
    except ValueError:
        return v
    return int(x) if x.is_integer() and "." not in v and "e" not in v.lower() else x


def check_log(path: Path) -> dict:
    """Read a run's log back: it must hold every state the plant published."""
    traj = read_log(path)
    if traj.missing:
        raise IncompleteLog(f"{path}: {traj.missing} plant states missing from the log")
    return {"log_events": traj.events, "log_steps": len(traj), "log_repeats": traj.repeats}


def controller_command(spec: RunSpec, config: ExperimentConfig, scenario_path: Path,
                       out_dir: Path, url: str, prefix: str) -> list[str]:
    """The command line of a run's controller (it starts its own plant)."""
    method = METHODS[spec.method]
    cmd = [sys.executable, "-m", method.module, *method.args,
           "--scenario", str(scenario_path), "--seed", str(spec.seed), "--out", str(out_dir),
           "--intervals", str(config.intervals),
           "--steps-per-interval", str(config.steps_per_interval),
           "--lcm-url", url, "--prefix", prefix]
    return cmd + list(config.controller_args)


def execute_run(spec: RunSpec, config: ExperimentConfig, out: Path, handle: RunHandle) -> dict:
    """Run one controller against its own plant with a logger; write its results.

    Returns the result record (also written to result.json when it succeeded).
    """
    run_dir = handle.directory
    if run_dir.exists():
        stop_leftover_processes(run_dir)
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    url, prefix = private_lcm_url(), private_prefix()
    scenario_path = (out / "scenarios" / f"{spec.scenario}.toml").resolve()
    cmd = controller_command(spec, config, scenario_path, run_dir / "controller", url, prefix)
    record = {"run": spec.key, **dataclasses.asdict(spec), "lcm_url": url, "prefix": prefix,
              "command": cmd, "status": "running"}
    handle.started = time.time()
    logger = LcmLogger(url, prefix, run_dir / "plant.lcmlog", run_dir / "logger.log")
    handle.processes.append(logger.process)
    record_process(run_dir, "recorder", logger.process)
    returncode = None
    try:
        with open(run_dir / "controller.log", "wb") as log:
            # The controller (and the plant it starts) run at a lower priority
            # than the recorder, so a busy machine slows the run down instead of
            # making the recorder drop messages (lcm-logger's subscription queue
            # is bounded and it missed states under load at equal priority).
            proc = subprocess.Popen(["nice", "-n", str(config.nice), *cmd],
                                    stdin=subprocess.DEVNULL, stdout=log,
                                    stderr=subprocess.STDOUT, start_new_session=True)
            handle.processes.append(proc)
            record_process(run_dir, "controller", proc)
            try:
                returncode = proc.wait(timeout=config.run_timeout or None)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
                raise RunFailed(f"timed out after {config.run_timeout:.0f} s") from None
    finally:
        logger.stop()
    wall = time.time() - handle.started
    record.update(started=handle.started, wall_time_s=wall, returncode=returncode)
    if handle.cancelled:
        raise RunFailed("cancelled")
    if returncode != 0:
        raise RunFailed(f"controller exited with code {returncode}; see "
                        f"{run_dir / 'controller.log'}")
    metrics_path = run_dir / "controller" / "metrics.csv"
    if not metrics_path.is_file():
        raise RunFailed(f"controller wrote no {metrics_path}")
    record.update(check_log(run_dir / "plant.lcmlog"))
    rows = read_metrics_csv(metrics_path)
    if len(rows) != config.intervals:
        raise RunFailed(f"{metrics_path} has {len(rows)} intervals, expected {config.intervals}")
    header = list(rows[0].keys())
    atomic_write_csv(run_dir / "metrics.csv", header,
                     [["" if r[k] is None else r[k] for k in header] for r in rows])
    atomic_write_json(run_dir / "metrics.json", rows)
    record["status"] = "ok"
    record["finished"] = time.time()
    atomic_write_json(run_dir / "result.json", record)  # last: marks the run finished
    (run_dir / "processes.json").unlink(missing_ok=True)
    return record


# ---------------------------------------------------------------------------
# Baseline episodes (figure a): one episode each, nominal and most degraded
# ---------------------------------------------------------------------------

def baseline_specs(config: ExperimentConfig) -> list[tuple[str, str | None, int, str]]:
    """(file stem, scenario name or None for nominal, age, policy) of figure (a)'s episodes."""
    top = config.intervals - 1
    specs = []
    for policy in ("closed", "open"):
        specs.append((f"nominal-{policy}", None, 0, policy))
        for exp in ("single", "multiple"):
            if exp in config.experiments:
                specs.append((f"{exp}-age{top}-{policy}", exp, top, policy))
    return specs


def run_baseline_episode(out: Path, stem: str, scenario: str | None, age: int,
                         policy: str) -> Path:
    """One episode with all valves closed or open at a given age, on the real plant;
    written to baselines/<stem>.csv (episode, step, age, u1..u6, x1..x6, reward).

    The plant starts at operating step age * K with a long interval K, so the
    whole episode runs at that age.
    """
    path = out / "baselines" / f"{stem}.csv"
    long_interval = 100_000
    scenario_path = str(out / "scenarios" / f"{scenario}.toml") if scenario else None
    u = baseline_valves(policy)
    rows = []
    with launch(scenario_path, 0, extra_args=["--steps-per-interval", str(long_interval),
                                              "--start-step", str(age * long_interval)]) as plant:
        plant.reset()
        while True:
            o = plant.step(u)
            rows.append(trajectory.row(o.episode, o.step, o.age, u, o.level,
                                       reward=float(reward(o.level, u))))
            if o.done:
                break
    atomic_write_csv(path, trajectory.header(reward=True), rows)
    return path
