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
import tempfile
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, TextIO

from ftc.common.atomic import atomic_write_csv, atomic_write_json
from ftc.common.errors import EXIT_STORAGE, StorageError
from ftc.control.agents.baselines import baseline_valves
from ftc.experiments.method_args import method_args
from ftc.experiments.methods import METHODS
from ftc.experiments.processes import (LcmLogger, RunFailed, RunHandle, die_with_parent,
                                       record_process, stop_leftover_processes)
from ftc.experiments.scenarios import ExperimentConfig, experiment_scenarios
from ftc.common.build_info import plant_binary
from ftc.plant import (LcmPlant, PlantError, PlantGoneError, private_lcm_url, private_prefix,
                       trajectory)
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


def tensorboard_dir(spec: RunSpec, config: ExperimentConfig) -> Path:
    """A run's TensorBoard directory: --tensorboard DIR / its key (EXP/tNN/METHOD/sS)."""
    return Path(config.tensorboard) / spec.key


def controller_command(spec: RunSpec, config: ExperimentConfig, scenario_path: Path,
                       out_dir: Path, url: str, prefix: str) -> list[str]:
    """The command line of a run's controller (it starts its own plant)."""
    method = METHODS[spec.method]
    cmd = [sys.executable, "-m", method.module, *method.args,
           "--scenario", str(scenario_path), "--seed", str(spec.seed), "--out", str(out_dir),
           "--intervals", str(config.intervals),
           "--steps-per-interval", str(config.steps_per_interval)]
    # link core: the physics runs in the controller's process, no LCM traffic
    cmd += (["--link", "core"] if config.link == "core"
            else ["--lcm-url", url, "--prefix", prefix])
    if config.tensorboard is not None:
        cmd += ["--tensorboard", str(tensorboard_dir(spec, config))]
    return cmd + method_args(method, config.controller_args)


def execute_run(spec: RunSpec, config: ExperimentConfig, out: Path, handle: RunHandle) -> dict:
    """Run one controller against its own plant with a logger; write its results.

    Returns the result record (also written to result.json when it succeeded).
    Raises StorageError (naming the path) when a file of the run cannot be
    written, by this process, the controller (its exit code 5) or the recorder.
    """
    try:
        return _execute_run(spec, config, out, handle)
    except OSError as e:
        raise StorageError(f"cannot write {e.filename or handle.directory}: "
                           f"{e.strerror or e}") from None


def _storage_problem(run_dir: Path, returncode: int | None) -> str | None:
    """The controller's own one-line storage error (exit 5), or None."""
    if returncode != EXIT_STORAGE:
        return None
    try:
        lines = (run_dir / "controller.log").read_text(errors="replace").strip().splitlines()
    except OSError:
        lines = []
    line = next((x for x in reversed(lines) if "error:" in x), "")
    return (line.split("error: ", 1)[1] if line else
            f"cannot write in {run_dir / 'controller'}: the controller exited with code 5 "
            "(storage)")


_recent_urls: deque[str] = deque(maxlen=1024)
_recent_lock = threading.Lock()


def run_url() -> str:
    """A private LCM URL that none of this orchestrator's last 1,024 runs or
    plants had. Independent draws of 24 runs from the 12,768 private ports
    collide with probability 2% (a CI run hit it); the prefix and the control
    session still kept such runs apart, but each run's URL is now its own."""
    with _recent_lock:
        url = private_lcm_url()
        while url in _recent_urls:
            url = private_lcm_url()
        _recent_urls.append(url)
        return url


def _execute_run(spec: RunSpec, config: ExperimentConfig, out: Path, handle: RunHandle) -> dict:
    run_dir = handle.directory
    if run_dir.exists():
        stop_leftover_processes(run_dir)
        shutil.rmtree(run_dir)
    if config.tensorboard is not None:  # a redone run starts its curves again
        shutil.rmtree(tensorboard_dir(spec, config), ignore_errors=True)
    run_dir.mkdir(parents=True)
    url, prefix = run_url(), private_prefix()
    scenario_path = (out / "scenarios" / f"{spec.scenario}.toml").resolve()
    cmd = controller_command(spec, config, scenario_path, run_dir / "controller", url, prefix)
    record = {"run": spec.key, **dataclasses.asdict(spec), "lcm_url": url, "prefix": prefix,
              "command": cmd, "status": "running"}
    handle.started = time.time()
    logger = None  # link core: no plant process, nothing to record
    if config.link != "core":
        logger = LcmLogger(url, prefix, run_dir / "plant.lcmlog", run_dir / "logger.log",
                           on_start=handle.watch)
        handle.processes.append(logger.process)
        record_process(run_dir, "recorder", logger.process)
    returncode = None
    try:
        proc = handle.launch(cmd, run_dir / "controller.log", config.nice)
        handle.watch(proc)
        handle.processes.append(proc)
        record_process(run_dir, "controller", proc)
        try:
            returncode = proc.wait(timeout=config.run_timeout or None)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            raise RunFailed(f"timed out after {config.run_timeout:.0f} s") from None
    finally:
        if logger is not None:
            logger.stop()
    wall = time.time() - handle.started
    record.update(started=handle.started, wall_time_s=wall, returncode=returncode)
    if handle.cancelled:
        raise RunFailed("cancelled")
    problem = _storage_problem(run_dir, returncode)
    if problem:
        raise StorageError(problem)
    if returncode != 0:
        raise RunFailed(f"controller exited with code {returncode}; see "
                        f"{run_dir / 'controller.log'}")
    metrics_path = run_dir / "controller" / "metrics.csv"
    if not metrics_path.is_file():
        raise RunFailed(f"controller wrote no {metrics_path}")
    if logger is not None:
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


def execute_with_retries(spec: RunSpec, config: ExperimentConfig, out: Path, handle: RunHandle,
                         attempts: int, stream: TextIO, stopping: Callable[[], bool]) -> dict:
    """:func:`execute_run`, redone (up to ``attempts`` times) when its log misses
    messages; each failed attempt is kept in OUT/failed_attempts/ (outside the
    results tree) and announced on ``stream``. ``stopping``: true once the
    executor is being stopped (no attempt is then started again)."""
    attempt = 1
    while True:
        try:
            return execute_run(spec, config, out, handle)
        except IncompleteLog as e:
            handle.release()
            if attempt >= attempts or stopping():
                raise
            keep = out / "failed_attempts" / f"{spec.key.replace('/', '_')}-{attempt}"
            keep.parent.mkdir(parents=True, exist_ok=True)
            shutil.rmtree(keep, ignore_errors=True)
            handle.directory.rename(keep)
            stream.write(f"\n{spec.key}: {e}; running it again (attempt kept in {keep})\n")
            attempt += 1


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


BASELINE_INTERVAL = 100_000  # steps: the plant's degradation interval in a baseline episode


def run_baseline_episode(out: Path, stem: str, scenario: str | None, age: int,
                         policy: str, max_steps: int = BASELINE_INTERVAL) -> Path:
    """One episode with all valves closed or open at a given age, on the real plant;
    written to baselines/<stem>.csv (episode, step, age, u1..u6, x1..x6, reward).

    The plant starts at operating step age * K with a long interval K, so the
    whole episode runs at that age. The episode is cut after ``max_steps``
    steps (at most K, where the plant would end it and change the age: an
    episode whose fuel never runs out, e.g. behind a dead pump, ends there);
    the cut is reported on stderr.
    """
    path = out / "baselines" / f"{stem}.csv"
    max_steps = min(max_steps, BASELINE_INTERVAL)
    scenario_path = str(out / "scenarios" / f"{scenario}.toml") if scenario else None
    u = baseline_valves(policy)
    rows = []
    done = False
    with _launch_plant(scenario_path, ["--steps-per-interval", str(BASELINE_INTERVAL),
                                       "--start-step", str(age * BASELINE_INTERVAL)]) as plant:
        plant.reset()
        for _ in range(max_steps):
            o = plant.step(u)
            rows.append(trajectory.row(o.episode, o.step, o.age, u, o.level,
                                       reward=float(reward(o.level, u))))
            if o.done:
                done = True
                break
    if not done:
        print(f"baseline {stem}: episode cut at {max_steps} steps (it had not ended)",
              file=sys.stderr)
    atomic_write_csv(path, trajectory.header(reward=True), rows)
    return path


def _launch_plant(scenario: str | None, extra: list[str]) -> LcmPlant:
    """ftc.plant.launch for the orchestrator's own plants: the same command on a
    private URL and prefix, started with a parent-death signal so that it dies
    with the orchestrator (launch() has no hook for one)."""
    url, prefix = run_url(), private_prefix()
    cmd = [str(plant_binary()), "--lcm-url", url, "--prefix", prefix, "--seed", "0",
           *(["--scenario", scenario] if scenario else []), *extra]
    fd, stderr_path = tempfile.mkstemp(prefix="ftc-plant-", suffix=".log")
    with os.fdopen(fd, "wb") as stderr:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=stderr, preexec_fn=die_with_parent())
    try:
        return LcmPlant(url, prefix, process=proc, stderr_path=stderr_path)
    except PlantGoneError as e:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        message = Path(stderr_path).read_text(errors="replace").strip()
        os.unlink(stderr_path)
        raise PlantError(f"plant failed to start ({' '.join(cmd)}): {message or e}",
                         exit_code=proc.returncode) from None
