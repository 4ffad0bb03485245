"""Run an experiment directory's runs in parallel: plan them, write the
scenario files and experiment.json, run every unfinished run (and the
baseline episodes) on a thread pool with a progress line, stop every child
process group on SIGINT/SIGTERM, then collect the results and write the
figures and the report.

--resume re-opens a directory: finished runs are kept, unfinished ones are
redone from scratch. While an orchestrator runs it holds OUT/orchestrator.lock
(a second one on the same OUT refuses), and its children die with it, even
when it is killed with SIGKILL (processes.Guardian). A file that cannot be
written (disk full) stops every run and raises StorageError naming it.
"""

from __future__ import annotations

import dataclasses
import json
import signal
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Callable, TextIO

from ftc.common.atomic import atomic_write_json, atomic_write_text
from ftc.common.build_info import ftc_version, git_revision
from ftc.common.errors import StorageError
from ftc.experiments import report
from ftc.experiments.collect import collect
from ftc.experiments.fork_server import ForkServer, ForkServerGone
from ftc.experiments.methods import METHODS
from ftc.experiments.processes import (Guardian, OrchestratorLock, OrchestratorReplacement,
                                      RunFailed, RunHandle)
from ftc.experiments.progress import Progress
from ftc.experiments.ray_executor import RaySession, run_on_ray
from ftc.experiments.runs import (RunSpec, baseline_specs, execute_with_retries, is_finished,
                                  plan_runs, run_baseline_episode)
from ftc.experiments.scenarios import ExperimentConfig, experiment_scenarios


class Orchestrator:
    """Runs tasks on a thread pool (each task waits on its own subprocesses) and
    stops every child process group on SIGINT/SIGTERM.

    jobs: runs at a time; attempts: tries of a run whose log misses messages
    before it counts as failed
    """

    def __init__(self, jobs: int, attempts: int = 3, guardian: Guardian | None = None,
                 fork_server: ForkServer | None = None) -> None:
        if jobs < 1:
            raise ValueError(f"jobs must be >= 1, got {jobs}")
        self.jobs = jobs
        self.attempts = attempts
        self.guardian = guardian
        self.fork_server = fork_server
        self.handles: dict[str, RunHandle] = {}
        self._lock = threading.Lock()
        self.stopping = False
        self.storage_error: StorageError | None = None

    def stop_all(self) -> None:
        self.stopping = True
        with self._lock:
            for h in self.handles.values():
                h.stop()

    def _run_one(self, spec: RunSpec, config: ExperimentConfig, out: Path,
                 progress: Progress) -> dict:
        """One run, redone (up to ``attempts`` times) when its log misses messages."""
        handle = RunHandle(spec.key, spec.directory(out), guardian=self.guardian,
                           fork_server=self.fork_server)
        with self._lock:
            if self.stopping:
                raise RunFailed("cancelled")
            self.handles[spec.key] = handle
        try:
            return execute_with_retries(spec, config, out, handle, self.attempts,
                                        progress.stream, lambda: self.stopping)
        finally:
            handle.release()
            with self._lock:
                self.handles.pop(spec.key, None)

    def run(self, out: Path, config: ExperimentConfig, runs: list[RunSpec],
            extra_tasks: list[tuple[str, Callable[[], object]]], progress: Progress) -> dict:
        """Run the extra tasks and the runs; returns key -> {"status", "result" or "error"}."""
        results: dict[str, dict] = {}
        with ThreadPoolExecutor(max_workers=self.jobs) as pool:
            futures: dict[Future, str] = {}
            for name, fn in extra_tasks:
                futures[pool.submit(fn)] = name
            for spec in runs:
                futures[pool.submit(self._run_one, spec, config, out, progress)] = spec.key
            pending = set(futures)
            while pending:
                done, pending = wait(pending, timeout=1.0, return_when=FIRST_COMPLETED)
                for f in done:
                    key = futures[f]
                    try:
                        results[key] = {"status": "ok", "result": f.result()}
                        if key in progress.runs_keys:
                            progress.done.add(key)
                    except StorageError as e:  # the disk is full for every run: stop
                        results[key] = {"status": "failed", "error": str(e)}
                        progress.failed.add(key)
                        if self.storage_error is None:
                            self.storage_error = e
                            self.stop_all()
                    except Exception as e:  # noqa: BLE001 - reported per run, the rest go on
                        results[key] = {"status": "failed", "error": str(e)}
                        progress.failed.add(key)
                        if not self.stopping:
                            progress.stream.write(f"\n{key}: FAILED: {e}\n")
                with self._lock:
                    running = {k: h for k, h in self.handles.items() if h.started}
                progress.show(running)
        progress.show({}, final=True)
        if self.storage_error is not None:
            raise self.storage_error
        return results


def prepare_directory(out: Path, config: ExperimentConfig, resume: bool) -> ExperimentConfig:
    """Create (or, with resume, re-open) a run directory; returns the config to use."""
    meta = out / "experiment.json"
    if meta.is_file():
        if not resume:
            raise SystemExit(f"ftc.experiments: error: {out} already holds an experiment: "
                             "--resume completes it, --overwrite replaces it")
        stored = ExperimentConfig.from_json(json.loads(meta.read_text())["config"])
        merged = dataclasses.replace(
            stored,
            experiments=tuple(dict.fromkeys(stored.experiments + config.experiments)),
            methods=tuple(dict.fromkeys(stored.methods + config.methods)))
        if merged != stored:
            print(f"resume: adding {sorted(set(merged.experiments) - set(stored.experiments))} "
                  f"experiments and {sorted(set(merged.methods) - set(stored.methods))} methods",
                  file=sys.stderr)
        config = dataclasses.replace(merged, tensorboard=config.tensorboard)  # this run's
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
        **provenance(config, config.methods, previous),
        "scenarios": {exp: [sc.to_json() for sc in trials] for exp, trials in scenarios.items()},
        "seeds": {"controller": list(config.seeds), "scenario": config.scenario_seed},
    })
    return config


def run_experiments(out: Path, config: ExperimentConfig, jobs: int | None, resume: bool,
                    stream: TextIO = sys.stderr, ray: RaySession | None = None,
                    fork_server: bool = True, overwrite: bool = False) -> int:
    """Run (or complete) the configured experiments into ``out``; then collect and
    write the figures and report. Returns the number of failed runs. ``ray``: run
    them as tasks of that Ray session (else on the local pool of ``jobs``, each
    run forked from a fork server unless ``fork_server`` is false).

    Raises OutInUse if another orchestrator is running on ``out``, StorageError
    if a file cannot be written."""
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise StorageError(f"cannot write {out}: {e.strerror or e}") from None
    lock = OrchestratorLock(out).acquire()
    lock.announce_takeover(stream)
    guardian = Guardian()
    replacing = OrchestratorReplacement(out, overwrite)
    try:
        with replacing:  # --overwrite: the old experiment aside until a run has finished
            return _run_locked(out, config, jobs, resume, stream, guardian, ray, fork_server)
    finally:
        guardian.close()
        lock.release()
        if replacing.restored:
            print(f"ftc.experiments: no run finished; the experiment that was in {out} is "
                  "back in place", file=stream)


def provenance(config, methods, previous: dict) -> dict:
    """The record of what a run directory was made with (its JSON's first keys);
    ``previous``: the record already there, whose creation time and revisions are kept."""
    return {"config": config.to_json(), "git_revision": git_revision(),
            "ftc_version": ftc_version(),
            "git_revisions": sorted(set(previous.get("git_revisions", [])) | {git_revision()}),
            "created": previous.get("created", time.strftime("%Y-%m-%dT%H:%M:%S%z")),
            "python": sys.version.split()[0],
            "methods": {m: dataclasses.asdict(METHODS[m]) for m in methods}}


def run_on_pool(out: Path, config: ExperimentConfig, todo: list, baselines: list,
                progress: Progress, jobs: int, guardian: Guardian, stream: TextIO,
                tool: str, fork_server: bool = True) -> dict:
    """Run ``todo`` (and ``baselines``) on the orchestrator's pool; SIGINT or
    SIGTERM stops every run and exits 130 with the finished runs kept.
    ``fork_server``: fork the runs' controllers from a :class:`ForkServer`
    (started here, on the main thread, which outlives every run)."""
    server = None
    if fork_server and todo:
        try:
            server = ForkServer(sorted({METHODS[r.method].module for r in todo}))
        except (ForkServerGone, OSError) as e:
            print(f"{tool}: no fork server ({e}); each run starts a fresh python", file=stream)
    orchestrator = Orchestrator(jobs, guardian=guardian, fork_server=server)

    def on_signal(signum: int, frame: object) -> None:
        orchestrator.stop_all()
        raise KeyboardInterrupt

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        return orchestrator.run(out, config, todo, baselines, progress)
    except KeyboardInterrupt:
        orchestrator.stop_all()
        print(f"\n{tool}: interrupted; finished runs are kept, --resume completes the rest",
              file=stream)
        raise SystemExit(130)
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        if server is not None:
            server.close()


def executor_line(jobs: int | None, ray: RaySession | None) -> str:
    """How the runs are executed, for the first line of output."""
    if ray is None:
        return f"jobs {jobs}"
    d = ray.describe()
    nodes = len(d["nodes"])
    return (f"executor ray at {d['address']} ({nodes} node{'s' * (nodes != 1)}, "
            f"{d['cpus']:g} CPUs"
            + (f", at most {ray.jobs} runs at a time)" if ray.jobs else ")"))


def _run_locked(out: Path, config: ExperimentConfig, jobs: int | None, resume: bool,
                stream: TextIO, guardian: Guardian, ray: RaySession | None,
                fork_server: bool = True) -> int:
    config = prepare_directory(out, config, resume)
    runs = plan_runs(config)
    finished = {r.key for r in runs if is_finished(r.directory(out))}
    todo = [r for r in runs if r.key not in finished]
    baselines = [s for s in baseline_specs(config)
                 if not (out / "baselines" / f"{s[0]}.csv").is_file()]
    print(f"ftc.experiments: {len(runs)} runs in {out} ({len(finished)} already finished), "
          f"{len(baselines)} baseline episodes, {executor_line(jobs, ray)}", file=stream)
    progress = Progress(runs, finished, config.intervals, stream)
    if ray is None:
        tasks = [(f"baseline {s[0]}", (lambda s=s: run_baseline_episode(out, *s)))
                 for s in baselines]
        results = run_on_pool(out, config, todo, tasks, progress, jobs, guardian, stream,
                              "ftc.experiments", fork_server)
    else:
        results = run_on_ray(ray, out, config, todo, baselines, progress, stream,
                             "ftc.experiments")
    failed = [k for k, v in results.items() if v["status"] != "ok"]
    meta = json.loads((out / "experiment.json").read_text())
    meta["wall_time_s"] = time.time() - progress.start
    meta["jobs"] = jobs
    meta["executor"] = ray.describe() if ray is not None else {"kind": "local", "jobs": jobs}
    atomic_write_json(out / "experiment.json", meta)
    collect(out)
    report.write_report(out)
    print(f"ftc.experiments: report at {out / 'report.md'} and {out / 'report.html'}"
          + (f"; {len(failed)} runs failed: {', '.join(failed)}" if failed else ""), file=stream)
    return len(failed)
