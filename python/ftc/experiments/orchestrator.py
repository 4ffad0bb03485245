"""Reproduce the paper's experiments on the real plant process, in parallel.

    python -m ftc.experiments all                       # short default (minutes)
    python -m ftc.experiments all --full                # the paper's protocol
    python -m ftc.experiments single|multiple|aggregate [--trials 20] [--seeds 0 1 2]
    python -m ftc.experiments model-search [--quick]    # the world-model grid
    python -m ftc.experiments report --out runs/NAME    # figures and report again

Experiments (../shared/design/plant-model.md, "The paper's experiments"):
single (engine E1, D_E = 20), multiple (E1 D_E = 20, tanks 5 and 6 D_T = 20)
and aggregate (N trials, each one random tank and one random engine with
factors uniform in [10, 30], drawn from --scenario-seed). Every
(experiment, trial, method, seed) is one *run*: one ``ftc.controller``
subprocess driving its own plant process on a private LCM URL (ttl=0) and
channel prefix, with an ``lcm-logger`` recording that plant's traffic.

Run directory (--out):
  experiment.json        resolved config, seeds, git revision, every trial's scenario
  scenarios/*.toml       the scenario file of every trial, as given to the plant
  baselines/*.csv        single episodes, valves all closed / all open (figure a)
  runs/EXP/tNN/METHOD/sS/  one run: controller/ (its own outputs), plant.lcmlog,
                         controller.log, metrics.csv, metrics.json, result.json
  results.csv, results.json  every run's per-interval metrics in one table
  trajectories/*.csv     one episode at the highest degradation, from the logs (figure c)
  model_search.csv       the ranked world-model grid (model-search)
  figures/*.png|svg, report.md, report.html

A run counts as finished only once its result.json is written (atomically,
last). --resume skips finished runs and redoes unfinished ones from scratch.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from ftc.atomic import atomic_write_text
from ftc.plant import private_lcm_url, private_prefix

EXPERIMENTS = ("single", "multiple", "aggregate")
INF = math.inf


# ---------------------------------------------------------------------------
# Methods: how each compared controller is started. Add one with register_method.
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class MethodSpec:
    """A compared method: a module run with ``python -m`` and its method arguments.

    The module must accept the controller's common options (--scenario, --seed,
    --out, --intervals, --steps-per-interval, --lcm-url, --prefix) and write
    OUT/metrics.csv (one row per interval) like ``ftc.controller`` does.

    name: identifier used on the command line and in paths
    label: legend text in figures and tables
    args: method-specific arguments
    module: the Python module to run
    cost: relative wall time (for scheduling longest first and the ETA)
    learns: whether it has a learned policy (deterministic evaluation, model R^2)
    """

    name: str
    label: str
    args: tuple[str, ...]
    module: str = "ftc.controller"
    cost: float = 1.0
    learns: bool = False


METHODS: dict[str, MethodSpec] = {}


def register_method(spec: MethodSpec) -> MethodSpec:
    """Make a method available by name (e.g. an MPC oracle, a learned-model MPC)."""
    if spec.name in METHODS and METHODS[spec.name] != spec:
        raise ValueError(f"method '{spec.name}' is already registered differently")
    METHODS[spec.name] = spec
    return spec


register_method(MethodSpec("closed", "all valves closed", ("--method", "closed"), cost=1.0))
register_method(MethodSpec("open", "all valves open", ("--method", "open"), cost=1.0))
register_method(MethodSpec("ppo-online", "PPO online", ("--method", "ppo", "--no-offline"),
                           cost=3.0, learns=True))
register_method(MethodSpec("ppo-offline", "PPO online + offline",
                           ("--method", "ppo", "--offline"), cost=8.0, learns=True))
register_method(MethodSpec("oracle-mpc", "MPC, faults known (oracle)", ("--method", "oracle"),
                           module="ftc.mpc", cost=1.5))
register_method(MethodSpec("model-mpc", "MPC on the learned model", ("--method", "model"),
                           module="ftc.mpc", cost=3.0, learns=True))
PAPER_METHODS = ("closed", "open", "ppo-online", "ppo-offline")
DEFAULT_METHODS = (*PAPER_METHODS, "oracle-mpc", "model-mpc")


# ---------------------------------------------------------------------------
# Configuration and scenarios
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class ExperimentConfig:
    """Everything that determines an experiment's results (jobs does not).

    experiments: which of single, multiple, aggregate to run
    methods: registered method names
    seeds: controller (and plant) seeds; every trial and method runs each
    trials: aggregate trials
    scenario_seed: seed of the aggregate trials' random faults
    intervals: degradation intervals per run (paper: 10)
    steps_per_interval: real control steps per interval, t_online (paper: 512)
    controller_args: extra arguments given to every method's controller (e.g. --pretrain)
    run_timeout: seconds after which a run is killed and counted as failed (0: none)
    nice: niceness added to each controller and its plant (the recorder keeps the
        normal priority, so that it keeps up on a loaded machine)
    """

    experiments: tuple[str, ...] = EXPERIMENTS
    methods: tuple[str, ...] = DEFAULT_METHODS
    seeds: tuple[int, ...] = (0,)
    trials: int = 20
    scenario_seed: int = 2020
    intervals: int = 10
    steps_per_interval: int = 512
    controller_args: tuple[str, ...] = ()
    run_timeout: float = 0.0
    nice: int = 5

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> "ExperimentConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()
                      if k in names})


#: Presets: the short default and the paper's protocol (--full).
PRESETS: dict[str, dict] = {
    "quick": dict(trials=2, intervals=10, steps_per_interval=512, seeds=(0,)),
    "full": dict(trials=20, intervals=10, steps_per_interval=512, seeds=(0,)),
}


@dataclass(frozen=True)
class Scenario:
    """A fault scenario: degradation factors (inf = healthy) of the 6 tanks and 2 engines."""

    name: str
    tank_factor: tuple[float, ...] = (INF,) * 6
    engine_factor: tuple[float, ...] = (INF,) * 2

    def toml(self, steps_per_interval: int) -> str:
        def fmt(v: float) -> str:
            return "inf" if math.isinf(v) else repr(float(v))

        return (f'# Written by ftc.experiments; the plant reads it with --scenario.\n'
                f'name = "{self.name}"\n'
                f'tank_factor = [{", ".join(fmt(v) for v in self.tank_factor)}]\n'
                f'engine_factor = [{", ".join(fmt(v) for v in self.engine_factor)}]\n'
                f'degradation = "stepwise"\n'
                f'steps_per_interval = {int(steps_per_interval)}\n')

    def describe(self) -> str:
        parts = [f"tank {i + 1} D_T={v:.2f}" for i, v in enumerate(self.tank_factor)
                 if not math.isinf(v)]
        parts += [f"engine E{j + 1} D_E={v:.2f}" for j, v in enumerate(self.engine_factor)
                  if not math.isinf(v)]
        return ", ".join(parts) or "nominal"

    def to_json(self) -> dict:
        return {"name": self.name,
                "tank_factor": [None if math.isinf(v) else v for v in self.tank_factor],
                "engine_factor": [None if math.isinf(v) else v for v in self.engine_factor],
                "description": self.describe()}


def aggregate_scenarios(trials: int, seed: int) -> list[Scenario]:
    """The aggregate experiment's trials: one random tank and one random engine each,
    factors uniform in [10, 30], all drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    out = []
    for t in range(trials):
        tank, engine = int(rng.integers(0, 6)), int(rng.integers(0, 2))
        d_t, d_e = float(rng.uniform(10.0, 30.0)), float(rng.uniform(10.0, 30.0))
        tanks = [INF] * 6
        tanks[tank] = d_t
        engines = [INF] * 2
        engines[engine] = d_e
        out.append(Scenario(f"aggregate-{t:02d}", tuple(tanks), tuple(engines)))
    return out


def experiment_scenarios(config: ExperimentConfig) -> dict[str, list[Scenario]]:
    """Trials of each configured experiment (single and multiple have one trial)."""
    table = {
        "single": [Scenario("single", engine_factor=(20.0, INF))],
        "multiple": [Scenario("multiple", tank_factor=(INF, INF, INF, INF, 20.0, 20.0),
                              engine_factor=(20.0, INF))],
        "aggregate": aggregate_scenarios(config.trials, config.scenario_seed),
    }
    return {e: table[e] for e in config.experiments}


# ---------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------

def atomic_write_json(path: Path, obj) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=_json_default)
                      + "\n")


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


def atomic_write_rows(path: Path, header: Sequence[str], rows: Iterable[Sequence]) -> None:
    from ftc.atomic import atomic_write_csv

    atomic_write_csv(Path(path), list(header), [list(r) for r in rows])


def read_metrics_csv(path: Path) -> list[dict]:
    """Rows of a controller metrics.csv; numbers as floats, empty cells as None."""
    rows = []
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            rows.append({k: _number(v) for k, v in row.items()})
    return rows


def _number(v: str | None):
    if v is None or v == "":
        return None
    try:
        x = float(v)
    except ValueError:
        return v
    return int(x) if x.is_integer() and "." not in v and "e" not in v.lower() else x


def count_rows(path: Path) -> int:
    """Data rows in a CSV being written by another process (0 if absent)."""
    try:
        with open(path) as f:
            return max(0, sum(1 for line in f if line.strip()) - 1)
    except OSError:
        return 0


# ---------------------------------------------------------------------------
# Runs
# ---------------------------------------------------------------------------

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


def recorder_binary() -> Path:
    """build/lcm_recorder: records a run's traffic in lcm-logger's file format
    without lcm-logger's 30-message subscription queue, which dropped plant
    states whenever the recorder was briefly descheduled (measured: 2 to 752
    of ~5,000 per run on a loaded 2-core machine). See cpp/plant/recorder.cpp."""
    from ftc import BUILD_DIR

    path = BUILD_DIR / "lcm_recorder"
    if not path.is_file():
        raise FileNotFoundError(f"lcm_recorder not found at {path}; run scripts/setup.sh")
    return path


def is_finished(run_dir: Path) -> bool:
    """A run is finished when its result.json says so (it is written last)."""
    try:
        return json.loads((run_dir / "result.json").read_text()).get("status") == "ok"
    except (OSError, ValueError):
        return False


def _proc_start_time(pid: int) -> str | None:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _record_process(run_dir: Path, name: str, proc: subprocess.Popen) -> None:
    """Note a started process group (pid and start time) so --resume can stop a
    leftover of a killed orchestrator, and nothing else."""
    path = run_dir / "processes.json"
    try:
        procs = json.loads(path.read_text())
    except (OSError, ValueError):
        procs = {}
    procs[name] = {"pid": proc.pid, "start": _proc_start_time(proc.pid)}
    atomic_write_json(path, procs)


def stop_leftover_processes(run_dir: Path) -> None:
    """Stop process groups a killed earlier orchestrator left running for this run."""
    try:
        procs = json.loads((run_dir / "processes.json").read_text())
    except (OSError, ValueError):
        return
    for info in procs.values():
        pid, start = info.get("pid"), info.get("start")
        if pid and start and _proc_start_time(pid) == start:
            try:
                os.killpg(pid, signal.SIGKILL)  # its own session: pgid == pid
            except OSError:
                pass


class RunFailed(RuntimeError):
    pass


class IncompleteLog(RunFailed):
    """The recorder missed messages; the run is redone (its results would not
    be reproducible from its log)."""


@dataclass
class RunHandle:
    """A run in progress: its processes, so the orchestrator can stop them."""

    spec: RunSpec
    directory: Path
    started: float = 0.0
    processes: list = field(default_factory=list)
    cancelled: bool = False

    def stop(self) -> None:
        self.cancelled = True
        for p in self.processes:
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except OSError:
                    pass


def _raise_priority() -> None:
    """Run the recorder ahead of the runs it records: lcm-logger dispatches from
    a bounded subscription queue, so a recorder starved of CPU on a busy machine
    drops messages (measured: 2-49 plant states per run at load 8 on 2 cores).
    Raising priority needs privileges; without them the niceness of the runs
    (RunnerConfig.nice) still favours the recorder."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, -10)
    except OSError:
        pass


class LcmLogger:
    """The recorder (build/lcm_recorder, lcm-logger's format) of one run's channels
    on its private URL.

    Started before the plant and confirmed ready by seeing a probe message of
    ours in its file; stopped after the run with an end marker seen in the file
    (so every message the plant sent before it is on disk) and SIGINT.
    """

    def __init__(self, url: str, prefix: str, path: Path, stderr_path: Path,
                 timeout: float = 10.0) -> None:
        import lcm

        self.url, self.prefix, self.path, self.timeout = url, prefix, path, timeout
        self._lc = lcm.LCM(url)
        self._stderr = open(stderr_path, "wb")
        # A large receive buffer: in lockstep the plant and controller exchange
        # thousands of messages a second, and a logger descheduled for a few
        # tens of ms on a busy machine would otherwise lose some (measured: 5 of
        # 400 with the default 208 KiB, two runs on two cores).
        self.process = subprocess.Popen(
            [str(recorder_binary()), "--flush-interval", "100",
             "--channel", f"{prefix}.*", "--lcm-url", _with_recv_buffer(url), str(path)],
            stdin=subprocess.DEVNULL, stdout=self._stderr, stderr=self._stderr,
            start_new_session=True, preexec_fn=_raise_priority)
        self._wait_for(f"{prefix}LOGGER_START")

    def _wait_for(self, channel: str) -> None:
        needle = channel.encode()
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RunFailed(f"recorder exited with code {self.process.returncode} "
                                f"(see {self._stderr.name})")
            self._lc.publish(channel, b"probe")
            # Waiting on an observable event (our probe reaching the file), not a
            # fixed delay; the poll period only bounds the cost of checking.
            self._lc.handle_timeout(20)
            try:
                with open(self.path, "rb") as f:
                    f.seek(max(0, self.path.stat().st_size - 4096))
                    if needle in f.read():
                        return
            except OSError:
                pass
        raise RunFailed(f"recorder on {self.url} did not record {channel} within "
                        f"{self.timeout:.0f} s")

    def stop(self) -> None:
        try:
            if self.process.poll() is None:
                self._wait_for(f"{self.prefix}LOGGER_END")
        finally:
            if self.process.poll() is None:
                self.process.send_signal(signal.SIGINT)
                try:
                    self.process.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    self.process.kill()
                    self.process.wait()
            self._stderr.close()


def _with_recv_buffer(url: str) -> str:
    """url with the largest UDP receive buffer the kernel allows (up to 64 MiB;
    scripts/setup.sh raises net.core.rmem_max to that where it may)."""
    if not url.startswith("udpm://") or "recv_buf_size" in url:
        return url
    try:
        limit = int(Path("/proc/sys/net/core/rmem_max").read_text())
    except (OSError, ValueError):
        limit = 1 << 21
    size = max(1 << 18, min(limit, 1 << 26))
    return url + ("&" if "?" in url else "?") + f"recv_buf_size={size}"


def check_log(path: Path) -> dict:
    """Read a run's log back: it must hold every state the plant published."""
    from ftc import replay

    traj = replay.read_log(path)
    if traj.missing:
        raise IncompleteLog(f"{path}: {traj.missing} plant states missing from the log")
    return {"log_events": traj.events, "log_steps": len(traj), "log_repeats": traj.repeats}


def controller_command(spec: RunSpec, config: ExperimentConfig, scenario_path: Path,
                       out_dir: Path, url: str, prefix: str) -> list[str]:
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
    _record_process(run_dir, "recorder", logger.process)
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
            _record_process(run_dir, "controller", proc)
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
    atomic_write_rows(run_dir / "metrics.csv", header,
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

BASELINE_HEADER = ["episode", "step", "age", *[f"u{i}" for i in range(1, 7)],
                   *[f"x{i}" for i in range(1, 7)], "reward"]


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
    """One episode with all valves closed or open at a given age, on the real plant.

    The plant starts at operating step age * K with a long interval K, so the
    whole episode runs at that age.
    """
    from ftc.plant import launch
    from ftc.reward import reward

    path = out / "baselines" / f"{stem}.csv"
    long_interval = 100_000
    scenario_path = str(out / "scenarios" / f"{scenario}.toml") if scenario else None
    u = np.full(6, 1 if policy == "open" else 0, dtype=np.int8)
    rows = []
    with launch(scenario_path, 0, extra_args=["--steps-per-interval", str(long_interval),
                                              "--start-step", str(age * long_interval)]) as plant:
        plant.reset()
        while True:
            o = plant.step(u)
            rows.append([o.episode, o.step, f"{o.age:.6g}", *u.tolist(),
                         *[repr(float(x)) for x in o.level], repr(float(reward(o.level, u)))])
            if o.done:
                break
    atomic_write_rows(path, BASELINE_HEADER, rows)
    return path


# ---------------------------------------------------------------------------
# The orchestrator: plan, run in parallel with progress, collect
# ---------------------------------------------------------------------------

def _fmt_time(s: float) -> str:
    if not math.isfinite(s):
        return "?"
    s = int(round(s))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


class Progress:
    """Runs done/total, each running run's current interval, elapsed time and ETA.

    The ETA weighs each run's intervals by its method's cost and extrapolates
    the rate of this session's progress.
    """

    def __init__(self, runs: list[RunSpec], finished: set[str], intervals: int,
                 stream=sys.stderr) -> None:
        self.runs, self.intervals, self.stream = runs, intervals, stream
        self.done = set(finished)
        self.runs_keys = {r.key for r in runs}
        self.failed: set[str] = set()
        self.start = time.time()
        self.done_at_start = self._work(self.done)
        self.total = self._work(r.key for r in runs)
        self.tty = stream.isatty()
        self._last_line = 0.0

    def _cost(self, key: str) -> float:
        return METHODS[key.split("/")[2]].cost

    def _work(self, keys: Iterable[str]) -> float:
        return sum(self._cost(k) * self.intervals for k in keys)

    def show(self, running: dict[str, RunHandle], final: bool = False) -> None:
        now = time.time()
        if not (self.tty or final or now - self._last_line >= 10.0):
            return
        self._last_line = now
        partial = {k: count_rows(h.directory / "controller" / "metrics.csv")
                   for k, h in running.items()}
        work = self._work(self.done) + sum(self._cost(k) * n for k, n in partial.items())
        rate = (work - self.done_at_start) / max(now - self.start, 1e-9)
        eta = (self.total - work) / rate if rate > 0 else math.inf
        parts = [f"{k} int {min(n + 1, self.intervals)}/{self.intervals}"
                 for k, n in sorted(partial.items())]
        line = (f"[{len(self.done)}/{len(self.runs)} runs done"
                + (f", {len(self.failed)} failed" if self.failed else "")
                + f"] elapsed {_fmt_time(now - self.start)}, ETA {_fmt_time(eta)}"
                + (f" | {'; '.join(parts)}" if parts else ""))
        if self.tty:
            width = shutil.get_terminal_size((120, 20)).columns
            self.stream.write("\r" + line[:width - 1].ljust(width - 1) + ("\n" if final else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()


class Orchestrator:
    """Runs tasks on a thread pool (each task waits on its own subprocesses) and
    stops every child process group on SIGINT/SIGTERM."""

    def __init__(self, jobs: int) -> None:
        self.jobs = max(1, jobs)
        self.handles: dict[str, RunHandle] = {}
        self._lock = threading.Lock()
        self.stopping = False

    def stop_all(self) -> None:
        self.stopping = True
        with self._lock:
            for h in self.handles.values():
                h.stop()

    def run(self, out: Path, config: ExperimentConfig, runs: list[RunSpec],
            extra_tasks: list[tuple[str, Callable[[], object]]], progress: Progress) -> dict:
        results: dict[str, dict] = {}

        def task(spec: RunSpec) -> dict:
            handle = RunHandle(spec, spec.directory(out))
            with self._lock:
                if self.stopping:
                    raise RunFailed("cancelled")
                self.handles[spec.key] = handle
            try:
                for attempt in range(1, 4):
                    try:
                        return execute_run(spec, config, out, handle)
                    except IncompleteLog as e:
                        if attempt == 3 or self.stopping:
                            raise
                        # Kept for diagnosis, outside the results tree.
                        keep = out / "failed_attempts" / f"{spec.key.replace('/', '_')}-{attempt}"
                        keep.parent.mkdir(parents=True, exist_ok=True)
                        shutil.rmtree(keep, ignore_errors=True)
                        handle.directory.rename(keep)
                        progress.stream.write(f"\n{spec.key}: {e}; running it again "
                                              f"(attempt kept in {keep})\n")
            finally:
                with self._lock:
                    self.handles.pop(spec.key, None)

        with ThreadPoolExecutor(max_workers=self.jobs) as pool:
            futures: dict[Future, str] = {}
            for name, fn in extra_tasks:
                futures[pool.submit(fn)] = name
            for spec in runs:
                futures[pool.submit(task, spec)] = spec.key
            pending = set(futures)
            while pending:
                done, pending = wait(pending, timeout=1.0, return_when=FIRST_COMPLETED)
                for f in done:
                    key = futures[f]
                    try:
                        results[key] = {"status": "ok", "result": f.result()}
                        if key in progress.runs_keys:
                            progress.done.add(key)
                    except Exception as e:  # noqa: BLE001 - reported per run, the rest go on
                        results[key] = {"status": "failed", "error": str(e)}
                        progress.failed.add(key)
                        if not self.stopping:
                            progress.stream.write(f"\n{key}: FAILED: {e}\n")
                with self._lock:
                    running = {k: h for k, h in self.handles.items() if h.started}
                progress.show(running)
        progress.show({}, final=True)
        return results


def prepare_directory(out: Path, config: ExperimentConfig, resume: bool) -> ExperimentConfig:
    """Create (or, with resume, re-open) a run directory; returns the config to use."""
    from ftc.build_info import git_revision

    meta = out / "experiment.json"
    if meta.is_file():
        if not resume:
            raise SystemExit(f"ftc.experiments: error: {out} already holds an experiment; "
                             "use --resume to complete it or choose another --out")
        stored = ExperimentConfig.from_json(json.loads(meta.read_text())["config"])
        merged = dataclasses.replace(
            stored,
            experiments=tuple(dict.fromkeys(stored.experiments + config.experiments)),
            methods=tuple(dict.fromkeys(stored.methods + config.methods)))
        if merged != stored:
            print(f"resume: adding {sorted(set(merged.experiments) - set(stored.experiments))} "
                  f"experiments and {sorted(set(merged.methods) - set(stored.methods))} methods",
                  file=sys.stderr)
        config = merged
    scenarios = experiment_scenarios(config)
    for exp, trials in scenarios.items():
        for sc in trials:
            atomic_write_text(out / "scenarios" / f"{sc.name}.toml",
                              sc.toml(config.steps_per_interval))
    # Scenarios of figure (a) also need the single and multiple files.
    for name in ("single", "multiple"):
        if name not in scenarios:
            sc = experiment_scenarios(dataclasses.replace(config, experiments=(name,)))[name][0]
            atomic_write_text(out / "scenarios" / f"{name}.toml", sc.toml(config.steps_per_interval))
    previous = json.loads(meta.read_text()) if meta.is_file() else {}
    atomic_write_json(meta, {
        "config": config.to_json(),
        "git_revision": git_revision(),
        "git_revisions": sorted(set(previous.get("git_revisions", [])) | {git_revision()}),
        "created": previous.get("created", time.strftime("%Y-%m-%dT%H:%M:%S%z")),
        "python": sys.version.split()[0],
        "methods": {m: dataclasses.asdict(METHODS[m]) for m in config.methods},
        "scenarios": {exp: [sc.to_json() for sc in trials] for exp, trials in scenarios.items()},
        "seeds": {"controller": list(config.seeds), "scenario": config.scenario_seed},
    })
    return config


def run_experiments(out: Path, config: ExperimentConfig, jobs: int, resume: bool,
                    stream=sys.stderr) -> int:
    """Run (or complete) the configured experiments into ``out``; then collect and
    write the figures and report. Returns the number of failed runs."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    config = prepare_directory(out, config, resume)
    runs = plan_runs(config)
    finished = {r.key for r in runs if is_finished(r.directory(out))}
    todo = [r for r in runs if r.key not in finished]
    baselines = [(f"baseline {s[0]}", (lambda s=s: run_baseline_episode(out, *s)))
                 for s in baseline_specs(config)
                 if not (out / "baselines" / f"{s[0]}.csv").is_file()]
    print(f"ftc.experiments: {len(runs)} runs in {out} ({len(finished)} already finished), "
          f"{len(baselines)} baseline episodes, jobs {jobs}", file=stream)
    progress = Progress(runs, finished, config.intervals, stream)
    orchestrator = Orchestrator(jobs)

    def on_signal(signum, frame):
        orchestrator.stop_all()
        raise KeyboardInterrupt

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        results = orchestrator.run(out, config, todo, baselines, progress)
    except KeyboardInterrupt:
        orchestrator.stop_all()
        print("\nftc.experiments: interrupted; finished runs are kept, --resume completes "
              "the rest", file=stream)
        raise SystemExit(130)
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
    failed = [k for k, v in results.items() if v["status"] != "ok"]
    meta = json.loads((out / "experiment.json").read_text())
    meta["wall_time_s"] = time.time() - progress.start
    meta["jobs"] = jobs
    atomic_write_json(out / "experiment.json", meta)
    collect(out)
    from ftc import report

    report.write_report(out)
    print(f"ftc.experiments: report at {out / 'report.md'} and {out / 'report.html'}"
          + (f"; {len(failed)} runs failed: {', '.join(failed)}" if failed else ""), file=stream)
    return len(failed)


# ---------------------------------------------------------------------------
# Collecting results for figures and the report
# ---------------------------------------------------------------------------

RESULT_ID_COLUMNS = ["experiment", "trial", "scenario", "method", "seed"]


def collect(out: Path) -> None:
    """Gather every finished run's metrics into results.csv/json and extract the
    tank-control episodes (figure c) from the recorded logs."""
    from ftc import replay

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
    atomic_write_rows(out / "results.csv", columns,
                      [["" if r.get(c) is None else r.get(c) for c in columns] for r in rows])
    atomic_write_json(out / "results.json", {"runs": runs, "metrics": rows})

    # Figure (c): one episode at the highest degradation, from the paper's
    # controller (PPO online + offline) when it ran, else another learner.
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
            traj = replay.read_log(log)
            episode = replay.control_episode(traj)
            replay.write_trajectory_csv(traj.episode_rows(episode),
                                        out / "trajectories" / f"{exp}-tank-control.csv")
            atomic_write_json(out / "trajectories" / f"{exp}-tank-control.json",
                              {"run": spec.key, "method": method, "episode": episode,
                               "log": str(log.relative_to(out))})
            break


# ---------------------------------------------------------------------------
# World-model search (the paper's grid)
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class ModelSearchConfig:
    """The paper's grid of world models, scored by k-fold cross-validated R^2.

    widths: hidden units per layer; layers: hidden layers; activations; lrs: Adam rates
    episodes: nominal episodes of random persistent valve settings in the data set
    folds: cross-validation folds; seed: data and initialisation seed
    """

    widths: tuple[int, ...] = (32, 64, 128, 256, 512)
    layers: tuple[int, ...] = (2, 3)
    activations: tuple[str, ...] = ("relu", "tanh")
    lrs: tuple[float, ...] = (1e-2, 5e-3, 1e-3)
    episodes: int = 50
    folds: int = 3
    seed: int = 0

    def grid(self) -> list[dict]:
        return [dict(width=w, layers=n, activation=a, lr=lr) for w in self.widths
                for n in self.layers for a in self.activations for lr in self.lrs]


QUICK_MODEL_SEARCH = ModelSearchConfig(widths=(32,), layers=(2,), activations=("relu", "tanh"),
                                       lrs=(1e-2,), episodes=6, folds=3)


def _model_search_point(data, point: dict, folds: int, seed: int) -> dict:
    import torch

    from ftc import world_model as wm

    torch.set_num_threads(1)
    torch.manual_seed(seed)
    start = time.time()
    cfg = _world_model_config(wm, point, seed)
    r2 = wm.cross_validated_r2(data, cfg, folds=folds)
    scores = np.atleast_1d(np.asarray(r2, dtype=np.float64))
    return {**point, "r2_mean": float(scores.mean()), "fit_seconds": time.time() - start}


def _world_model_config(wm, point: dict, seed: int):
    """WorldModelConfig for a grid point, whatever the config names its fields."""
    fields = {f.name for f in dataclasses.fields(wm.WorldModelConfig)}
    kwargs = {}
    hidden = tuple([point["width"]] * point["layers"])
    if "hidden" in fields:
        kwargs["hidden"] = hidden
    else:
        kwargs.update(width=point["width"], layers=point["layers"])
    kwargs["activation"] = point["activation"]
    kwargs["lr"] = point["lr"]
    if "seed" in fields:
        kwargs["seed"] = seed
    return wm.WorldModelConfig(**{k: v for k, v in kwargs.items() if k in fields})


def model_search(out: Path, config: ModelSearchConfig, jobs: int, stream=sys.stderr) -> list[dict]:
    """Score every grid point in parallel processes; write model_search.csv/json ranked."""
    from concurrent.futures import ProcessPoolExecutor

    from ftc import world_model as wm

    out = Path(out)
    start = time.time()
    data = wm.collect_nominal_dataset(episodes=config.episodes, seed=config.seed)
    grid = config.grid()
    print(f"model-search: {len(grid)} models, {config.folds}-fold CV on "
          f"{config.episodes} nominal episodes, jobs {jobs}", file=stream)
    results = []
    import multiprocessing

    def report_point(i: int) -> None:
        r, el = results[-1], time.time() - start
        print(f"  [{i + 1}/{len(grid)}] {r['layers']}x{r['width']} {r['activation']} "
              f"lr {r['lr']:g}: R^2 {r['r2_mean']:.4f}  (elapsed {_fmt_time(el)}, ETA "
              f"{_fmt_time(el / (i + 1) * (len(grid) - i - 1))})", file=stream)

    if jobs <= 1:
        for i, p in enumerate(grid):
            results.append(_model_search_point(data, p, config.folds, config.seed))
            report_point(i)
    else:
        with ProcessPoolExecutor(max_workers=jobs,
                                 mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = [pool.submit(_model_search_point, data, p, config.folds, config.seed)
                       for p in grid]
            for i, f in enumerate(futures):
                results.append(f.result())
                report_point(i)
    results.sort(key=lambda r: -r["r2_mean"])
    for rank, r in enumerate(results, 1):
        r["rank"] = rank
    header = ["rank", "width", "layers", "activation", "lr", "r2_mean", "fit_seconds"]
    atomic_write_rows(out / "model_search.csv", header, [[r[h] for h in header] for r in results])
    atomic_write_json(out / "model_search.json", {"config": dataclasses.asdict(config),
                                                  "wall_time_s": time.time() - start,
                                                  "results": results})
    return results


# ---------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m ftc.experiments", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("command", choices=(*EXPERIMENTS, "all", "model-search", "report"),
                        help="which experiment(s) to run; model-search: the world-model grid; "
                             "report: redo results, figures and report from saved runs")
    parser.add_argument("--out", type=Path, default=None,
                        help="run directory (default: runs/<command>-<date-time>)")
    parser.add_argument("--resume", action="store_true",
                        help="complete an interrupted run directory: finished runs are kept, "
                             "unfinished ones redone")
    parser.add_argument("--full", action="store_true",
                        help="the paper's protocol (20 aggregate trials); default: a short run "
                             f"({PRESETS['quick']['trials']} aggregate trials)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                        help="runs in parallel (default: number of cores)")
    parser.add_argument("--trials", type=int, default=None, help="aggregate trials")
    parser.add_argument("--seeds", type=int, nargs="+", default=None,
                        help="controller seeds; every trial and method runs each (default: 0)")
    parser.add_argument("--scenario-seed", type=int, default=ExperimentConfig.scenario_seed,
                        help="seed of the aggregate trials' random faults")
    parser.add_argument("--intervals", type=int, default=None,
                        help="degradation intervals per run (paper: 10)")
    parser.add_argument("--steps-per-interval", type=int, default=None,
                        help="real control steps per interval, t_online (paper: 512)")
    parser.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS),
                        help=f"methods to compare (registered: {', '.join(METHODS)})")
    parser.add_argument("--pretrain", action="store_true",
                        help="pass --pretrain to the controller (PPO methods: nominal pretraining in "
                             "simulation; default: from scratch as in the paper)")
    parser.add_argument("--controller-args", default="",
                        help="extra arguments for every run's controller, one string "
                             "(e.g. \"--model-episodes 10 --offline-steps 512\")")
    parser.add_argument("--run-timeout", type=float, default=0.0,
                        help="kill a run after this many seconds and count it failed (0: never)")
    parser.add_argument("--model-search", action="store_true",
                        help="with 'all': also run the world-model grid")
    parser.add_argument("--quick", action="store_true",
                        help="model-search: a 2-model subset on a small data set (for tests)")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    unknown = [m for m in args.methods if m not in METHODS]
    if unknown:
        parser.error(f"unknown methods {unknown}; registered: {', '.join(METHODS)}")
    out = args.out or Path("runs") / f"{args.command}-{time.strftime('%Y%m%d-%H%M%S')}"
    if args.command == "report":
        if not (out / "experiment.json").is_file():
            parser.error(f"--out {out} holds no experiment.json")
        from ftc import report

        collect(out)
        report.write_report(out)
        print(f"report at {out / 'report.md'}")
        return 0
    if args.command == "model-search":
        out.mkdir(parents=True, exist_ok=True)
        model_search(out, QUICK_MODEL_SEARCH if args.quick else ModelSearchConfig(),
                     max(1, args.jobs))
        if (out / "experiment.json").is_file():
            from ftc import report

            report.write_report(out)
        print(f"model search table at {out / 'model_search.csv'}")
        return 0
    preset = PRESETS["full" if args.full else "quick"]
    config = ExperimentConfig(
        experiments=EXPERIMENTS if args.command == "all" else (args.command,),
        methods=tuple(args.methods),
        seeds=tuple(args.seeds) if args.seeds else preset["seeds"],
        trials=args.trials if args.trials is not None else preset["trials"],
        scenario_seed=args.scenario_seed,
        # "is None", not "or": an explicit 0 must be refused below, not replaced
        intervals=args.intervals if args.intervals is not None else preset["intervals"],
        steps_per_interval=(args.steps_per_interval if args.steps_per_interval is not None
                            else preset["steps_per_interval"]),
        controller_args=(("--pretrain",) if args.pretrain else ())
        + tuple(shlex.split(args.controller_args)),
        run_timeout=args.run_timeout)
    for name in ("trials", "intervals", "steps_per_interval"):
        if getattr(config, name) <= 0:
            parser.error(f"--{name.replace('_', '-')} must be positive")
    try:  # an unwritable --out is an error before any run starts
        out.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=out).close()
    except OSError as e:
        parser.error(f"--out {out}: cannot write there: {e.strerror or e}")
    if args.command == "all" and args.model_search:
        model_search(out, ModelSearchConfig(), max(1, args.jobs))
    failed = run_experiments(out, config, max(1, args.jobs), args.resume)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
