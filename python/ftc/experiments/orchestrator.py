"""Run an experiment directory's runs in parallel: plan them, write the
scenario files and experiment.json, run every unfinished run (and the
baseline episodes) on a thread pool with a progress line, stop every child
process group on SIGINT/SIGTERM, then collect the results and write the
figures and the report.

--resume re-opens a directory: finished runs are kept, unfinished ones are
redone from scratch.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import signal
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Callable, TextIO

from ftc.common.atomic import atomic_write_json, atomic_write_text
from ftc.common.build_info import git_revision
from ftc.experiments import report
from ftc.experiments.collect import collect
from ftc.experiments.methods import METHODS
from ftc.experiments.processes import RunFailed, RunHandle
from ftc.experiments.progress import Progress
from ftc.experiments.runs import (IncompleteLog, RunSpec, baseline_specs, execute_run,
                                  is_finished, plan_runs, run_baseline_episode)
from ftc.experiments.scenarios import ExperimentConfig, experiment_scenarios


class Orchestrator:
    """Runs tasks on a thread pool (each task waits on its own subprocesses) and
    stops every child process group on SIGINT/SIGTERM.

    jobs: runs at a time; attempts: tries of a run whose log misses messages
    before it counts as failed
    """

    def __init__(self, jobs: int, attempts: int = 3) -> None:
        self.jobs = max(1, jobs)
        self.attempts = attempts
        self.handles: dict[str, RunHandle] = {}
        self._lock = threading.Lock()
        self.stopping = False

    def stop_all(self) -> None:
        self.stopping = True
        with self._lock:
            for h in self.handles.values():
                h.stop()

    def _run_one(self, spec: RunSpec, config: ExperimentConfig, out: Path,
                 progress: Progress) -> dict:
        """One run, redone (up to ``attempts`` times) when its log misses messages."""
        handle = RunHandle(spec.key, spec.directory(out))
        with self._lock:
            if self.stopping:
                raise RunFailed("cancelled")
            self.handles[spec.key] = handle
        try:
            attempt = 1
            while True:
                try:
                    return execute_run(spec, config, out, handle)
                except IncompleteLog as e:
                    if attempt >= self.attempts or self.stopping:
                        raise
                    # Kept for diagnosis, outside the results tree.
                    keep = out / "failed_attempts" / f"{spec.key.replace('/', '_')}-{attempt}"
                    keep.parent.mkdir(parents=True, exist_ok=True)
                    shutil.rmtree(keep, ignore_errors=True)
                    handle.directory.rename(keep)
                    progress.stream.write(f"\n{spec.key}: {e}; running it again "
                                          f"(attempt kept in {keep})\n")
                    attempt += 1
        finally:
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
                    stream: TextIO = sys.stderr) -> int:
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

    def on_signal(signum: int, frame: object) -> None:
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
    report.write_report(out)
    print(f"ftc.experiments: report at {out / 'report.md'} and {out / 'report.html'}"
          + (f"; {len(failed)} runs failed: {', '.join(failed)}" if failed else ""), file=stream)
    return len(failed)
