"""The benchmark suite: every method on every scenario file and seed, then
results.csv and a report of each method's normalized score (0: all valves
closed, 1: the reference method) beside its reward as a fraction of the oracle MPC.

    python -m ftc.experiments benchmark --out runs/bench --jobs 2
    python -m ftc.experiments benchmark --scenarios scenarios/single.toml \\
        --methods closed balance --seeds 0 --intervals 2 --steps-per-interval 128 --out DIR

The reference (--reference, default oracle-mpc) and closed always run beside
the methods asked for: in every scenario, seed and interval a method's
normalized score is (r - closed) / (reference - closed) of the rewards per
step, empty where the reference earns exactly what closed earns.

Without --scenarios the suite's default scenarios (ftc.experiments.suite: the
paper's single and multiple faults and 20 random ones) are written and run.
Every (scenario, method, seed) is one run of the experiments' machinery
(runs.execute_run on the orchestrator's thread pool, with its progress line,
failure handling and --resume), by default on the in-process physics
(--link core: no plant process and no recorder).

Run directory (--out):
  benchmark.json        resolved config, git revision, methods, scenarios
  scenarios/STEM.toml   the scenario files, as the runs read them
  runs/STEM/t00/METHOD/sS/  one run (controller/, controller.log, metrics.csv, result.json)
  results.csv, results.json  every finished run's per-interval metrics, with the
                        reference's and closed's reward per step and the normalized score
  fractions.csv         reward per step as a fraction of the oracle's, per cell
  aggregates.csv, tracks.csv  the per-run score's IQM, mean, median and optimality gap
                        with 95% intervals, overall and per track (score_tables)
  figures/benchmark_score.png, figures/benchmark_profile.png, report.md, report.html
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import os
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence, TextIO

from ftc.common.atomic import atomic_write_csv, atomic_write_json, atomic_write_text
from ftc.common.cli import Check, OneLineParser, at_least, checked, out_dir_problem
from ftc.common.errors import RunError, StorageError
from ftc.control.config import MAX_INTERVALS, MAX_STEPS_PER_INTERVAL
from ftc.experiments import benchmark_report, reference_scores, run_cache
from ftc.experiments.method_args import PARSERS, method_args, untaken
from ftc.experiments.methods import METHODS, resolve_methods
from ftc.experiments.orchestrator import executor_line, provenance, run_on_pool
from ftc.experiments.processes import (Guardian, OrchestratorLock, OrchestratorReplacement,
                                      OutInUse, check_out_free)
from ftc.experiments.progress import Progress
from ftc.experiments.ray_executor import (RaySession, add_executor_options,
                                         check_executor_options, connect, run_on_ray)
from ftc.experiments.run_cache import RunCache, cache_groups, default_dir, reuse_after, reuse_before
from ftc.experiments.runs import RunSpec, is_finished
from ftc.experiments.scenarios import ExperimentConfig, Scenario, scenario_texts
from ftc.experiments.suite import default_suite

TOOL = "ftc.experiments benchmark"
ORACLE = benchmark_report.ORACLE
CLOSED = benchmark_report.CLOSED
REFERENCE = benchmark_report.REFERENCE
MAX_JOBS = 256
MAX_RUN_TIMEOUT = 1e6  # seconds; 0 means no timeout
SEED = at_least(0, 2**31 - 1)  # the controller's --seed range


def default_methods(reference: str = REFERENCE) -> tuple[str, ...]:
    """Every registered method not marked ``benchmark=False``, the reference and
    closed included."""
    names = [m for m, spec in METHODS.items() if spec.benchmark]
    return tuple(dict.fromkeys((*names, reference, CLOSED)))


@dataclass(frozen=True)
class BenchmarkConfig:
    """Everything that determines a benchmark's results (jobs does not).

    scenarios: scenario stems, files scenarios/STEM.toml of the run directory
    methods: registered method names; the reference and closed are always among them
    seeds: controller (and plant) seeds; every scenario and method runs each
    intervals: degradation intervals per run
    steps_per_interval: real control steps per interval (overrides the files' value)
    link: core (physics in the controller's process) or lcm (a plant process, recorded)
    controller_args: extra controller arguments, each to the methods it acts on (method_args)
    run_timeout: seconds after which a run is killed and counted failed (0: never)
    nice: niceness added to each controller
    reference: the method whose normalized score is 1 (closed's is 0), in every cell
    reference_scores: '' (the reference and closed run) or the file their rewards come from
    """

    scenarios: tuple[str, ...]
    methods: tuple[str, ...]
    seeds: tuple[int, ...] = (0, 1, 2)
    intervals: int = 10
    steps_per_interval: int = 512
    link: str = "core"
    controller_args: tuple[str, ...] = ()
    run_timeout: float = 0.0
    nice: int = 5
    reference: str = REFERENCE
    reference_scores: str = ""

    def run_config(self) -> ExperimentConfig:
        """What runs.execute_run reads of a run's settings."""
        return ExperimentConfig(experiments=(), methods=self.methods, seeds=self.seeds,
                                intervals=self.intervals,
                                steps_per_interval=self.steps_per_interval,
                                controller_args=self.controller_args,
                                run_timeout=self.run_timeout, nice=self.nice, link=self.link)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> "BenchmarkConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        d = {"reference": ORACLE, **d}  # recorded before the field existed: the oracle was 1
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()
                      if k in names})


def plan_benchmark(config: BenchmarkConfig) -> list[RunSpec]:
    """Every run, most expensive first. A run is keyed by its scenario's stem
    (runs/STEM/t00/METHOD/sS), so adding scenarios on --resume moves no run."""
    runs = [RunSpec(stem, 0, m, int(s), stem) for stem in config.scenarios
            for m in config.methods for s in config.seeds]
    return sorted(runs, key=lambda r: -METHODS[r.method].cost)


# ---------------------------------------------------------------------------
# The command line: every input checked before anything is written
# ---------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="python -m ftc.experiments benchmark",
                           description=__doc__.split("\n\n")[0],
                           formatter_class=argparse.RawDescriptionHelpFormatter,
                           epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("--scenarios", type=checked(Path, nonempty=True), nargs="+",
                        default=None, metavar="SCENARIO",
                        help="scenario TOML files or packaged scenarios' names (single, "
                             "multiple, nominal, abrupt), named in the results by their stem "
                             "(default: the suite's 22, see ftc.experiments.suite)")
    parser.add_argument("--methods", nargs="+", default=None, metavar="NAME",
                        help="methods to run, or plug-ins, NAME=SPEC with SPEC "
                             "module.path:factory, sb3:PATH.zip or onnx:PATH.onnx; the "
                             "--reference method and closed are always added, as the "
                             "normalized score's 1 and 0 (default: every registered method "
                             f"for benchmarks: {', '.join(default_methods())})")
    parser.add_argument("--reference", default=None, metavar="METHOD",
                        help=f"the method whose normalized score is 1 (default: {REFERENCE}); a "
                             "cheaper one makes a quick run. The fraction of the oracle is "
                             f"taken of {ORACLE} whenever it runs")
    reference_scores.add_option(parser)
    parser.add_argument("--seeds", type=checked(int, SEED), nargs="+", default=None,
                        help="controller seeds; every scenario and method runs each "
                             "(default: 0 1 2)")
    parser.add_argument("--jobs", type=checked(int, at_least(1, MAX_JOBS)), default=None,
                        help="runs in parallel (default: number of cores; with --executor ray: "
                             "at most this many runs in flight, default as many as the "
                             "cluster's CPUs, one per run)")
    add_executor_options(parser)
    parser.add_argument("--out", type=checked(Path, nonempty=True), default=None,
                        help="run directory (default: runs/benchmark-<date-time>)")
    parser.add_argument("--intervals", type=checked(int, at_least(1, MAX_INTERVALS)),
                        default=None, help="degradation intervals per run (default: 10)")
    parser.add_argument("--steps-per-interval",
                        type=checked(int, at_least(1, MAX_STEPS_PER_INTERVAL)), default=None,
                        help="real control steps per interval (default: 512)")
    parser.add_argument("--link", choices=("core", "lcm"), default=None,
                        help="core: the physics in each controller's process (default, fast); "
                             "lcm: a plant process per run, its traffic recorded and checked")
    parser.add_argument("--controller-args", default=None,
                        help="extra arguments for the methods' controllers, one string (e.g. "
                             "\"--update-every 32\" for intervals shorter than PPO's 128 steps); "
                             "each option goes to the methods it acts on")
    parser.add_argument("--run-timeout", type=checked(float, Check(low=0.0, high=MAX_RUN_TIMEOUT)),
                        default=None,
                        help="kill a run after this many seconds and count it failed (0: never)")
    parser.add_argument("--run-cache", default=None, metavar="DIR",
                        help="where the runs of the methods that depend on the scenario only "
                             f"({', '.join(m for m, s in METHODS.items() if s.cached)}) are "
                             "kept and looked up, by the scenario's bytes and the planning "
                             f"code's (default: ${run_cache.ENV}, else "
                             f"{run_cache.DEFAULT_DIR}; '' disables)")
    parser.add_argument("--resume", action="store_true",
                        help="complete an interrupted run directory: finished runs are kept, "
                             "unfinished ones redone; scenarios, methods and seeds given are "
                             "added to the stored ones")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the benchmark already in --out: it is moved aside when "
                             "this one starts, deleted once one of its runs has finished, and "
                             "moved back if none does")
    return parser


def _suite_texts(steps_per_interval: int) -> dict[str, tuple[str, str]]:
    return {sc.name: ("ftc.experiments.suite", sc.toml(steps_per_interval))
            for sc in default_suite()}


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line, checked (exit 2 with one line naming the flag, nothing
    written). Returns the options with ``out``, ``config`` (BenchmarkConfig) and
    ``texts`` (stem -> (source, TOML) of the scenario files to write) resolved."""
    parser = build_parser()
    args = parser.parse_args(argv)
    check_executor_options(parser, args)
    try:  # plug-ins (NAME=module:factory, sb3:..., onnx:...): registered, checked
        args.methods = resolve_methods(args.methods, args.out and args.out / "benchmark.json")
    except ValueError as e:
        parser.error(f"--methods: {e}")
    unknown = [m for m in args.methods or () if m not in METHODS]
    if unknown:
        parser.error(f"--methods: unknown methods {unknown}; registered: {', '.join(METHODS)}")
    if args.reference is not None and args.reference not in METHODS:
        parser.error(f"--reference: unknown method '{args.reference}'; registered: "
                     f"{', '.join(METHODS)}")
    if args.reference == CLOSED:
        parser.error(f"--reference: {CLOSED} is the normalized score's 0; choose another method")
    out = args.out or Path("runs") / f"benchmark-{time.strftime('%Y%m%d-%H%M%S')}"
    problem = out_dir_problem(out)
    if problem:
        parser.error(f"--out {out}: cannot write there ({problem})")
    if args.overwrite and args.resume:
        parser.error("--overwrite replaces a benchmark, --resume completes it: give one")
    if args.overwrite and not (out / "benchmark.json").is_file():
        parser.error(f"--overwrite: {out} holds no benchmark (benchmark.json) to replace")
    try:  # a live writer first: the benchmark it holds is not finished
        check_out_free(out)
    except OutInUse as e:
        parser.error(f"--out: {e}")
    stored = None if args.overwrite else _stored_config(parser, out, args.resume)
    given = {k: getattr(args, k) for k in ("intervals", "steps_per_interval", "link",
                                             "reference") if getattr(args, k) is not None}
    if args.controller_args is not None:
        try:
            given["controller_args"] = tuple(shlex.split(args.controller_args))
        except ValueError as e:
            parser.error(f"--controller-args: {e}")
    if stored is not None:  # the finished runs fix what determines results
        changed = [k for k, v in given.items() if getattr(stored, k) != v]
        if changed:
            parser.error(f"--resume: --{changed[0].replace('_', '-')} differs from the stored "
                         f"{getattr(stored, changed[0])} of {out / 'benchmark.json'}")
        base = stored
    else:
        base = BenchmarkConfig(scenarios=(), methods=(), seeds=(), **given)
    if args.run_timeout is not None:
        base = dataclasses.replace(base, run_timeout=args.run_timeout)
    try:
        texts = (scenario_texts(args.scenarios) if args.scenarios
                 else {} if stored is not None else _suite_texts(base.steps_per_interval))
    except ValueError as e:
        parser.error(f"--scenarios: {e}")
    for stem, (source, text) in texts.items():
        old = out / "scenarios" / f"{stem}.toml"
        if stored is not None and stem in stored.scenarios and old.is_file() \
                and old.read_text() != text:
            parser.error(f"--scenarios: {source} differs from {old}, which the stored runs "
                         f"of scenario {stem} used; rename the file or choose another --out")
    methods = args.methods or (() if stored is not None else default_methods(base.reference))
    seeds = args.seeds or (() if stored is not None else (0, 1, 2))
    base = reference_scores.from_args(parser, args, base, texts, seeds)
    config = dataclasses.replace(
        base, scenarios=tuple(dict.fromkeys((*base.scenarios, *texts))),
        methods=tuple(m for m in dict.fromkeys((*base.methods, *methods, base.reference, CLOSED))
                      if not base.reference_scores or m not in (base.reference, CLOSED)),
        seeds=tuple(dict.fromkeys((*base.seeds, *(int(s) for s in seeds)))))
    problem = _run_options_problem(config, out)
    if problem:  # e.g. --steps-per-interval not a multiple of PPO's --update-every
        parser.error(problem)
    cache_dir = (default_dir() if args.run_cache is None
                 else Path(args.run_cache).expanduser() if args.run_cache else None)
    return argparse.Namespace(**vars(args), out_dir=out, config=config, texts=texts,
                              run_cache_dir=cache_dir)


def _run_options_problem(config: BenchmarkConfig, out: Path) -> str | None:
    """Why a method's module would refuse its runs' command line, or None: its own
    parser reads the command line (writing nothing), so a run option it refuses
    is an error here instead of a failure of every run."""
    unused = untaken(config.methods, config.controller_args)
    if unused:
        return (f"--controller-args {' '.join(unused)}: no method here takes it (each option "
                "goes to the methods whose runs it acts on)")
    for name in config.methods:
        method = METHODS[name]
        module = PARSERS.get(method.module)
        if module is None:  # a registered module of another kind: its runs will tell
            continue
        argv = [*method.args, "--scenario", "", "--seed", str(config.seeds[0]),
                "--intervals", str(config.intervals),
                "--steps-per-interval", str(config.steps_per_interval), "--link", config.link,
                f"--out={out / 'runs' / 'check'}",  # --out=: a path may start with '-'
                *method_args(method, config.controller_args)]
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                module.parse_args(argv)
        except SystemExit as e:
            line = (err.getvalue().strip().splitlines() or [f"exit {e.code}"])[-1]
            what = line.split(": error: ", 1)[-1] if e.code else "--help is not a run option"
            return (f"method {name}: {what}" + ("" if config.controller_args else
                    " (a method's own options go in --controller-args)"))
    return None


def _stored_config(parser: argparse.ArgumentParser, out: Path,
                   resume: bool) -> BenchmarkConfig | None:
    meta = out / "benchmark.json"
    if not meta.is_file():
        return None
    if not resume:
        parser.error(f"--out {out} already holds a benchmark: --resume completes it, "
                     "--overwrite replaces it")
    try:
        return BenchmarkConfig.from_json(json.loads(meta.read_text())["config"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        parser.error(f"--resume: {meta} is not a readable benchmark ({type(e).__name__}: {e})")


# ---------------------------------------------------------------------------
# Running
# ---------------------------------------------------------------------------

def prepare_directory(out: Path, config: BenchmarkConfig,
                      texts: dict[str, tuple[str, str]]) -> None:
    """Write the scenario files and benchmark.json (keeping what a resumed
    directory already records)."""
    from ftc import _core  # the bindings: the plant's scenario parser

    for stem, (_, text) in texts.items():
        atomic_write_text(out / "scenarios" / f"{stem}.toml", text)
    config = reference_scores.copy_into(out, config)
    meta_path = out / "benchmark.json"
    previous = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    scenarios = dict(previous.get("scenarios", {}))
    for stem in config.scenarios:
        sc = _core.load_scenario(str(out / "scenarios" / f"{stem}.toml"))
        described = Scenario(stem, tuple(sc.tank_factor), tuple(sc.engine_factor)).describe()
        scenarios[stem] = {"file": f"scenarios/{stem}.toml", "description": described,
                           "source": texts[stem][0] if stem in texts
                           else scenarios.get(stem, {}).get("source", "?")}
    atomic_write_json(meta_path, {
        **provenance(config, (*config.methods, *reference_scores.given(config)), previous),
        "scenarios": scenarios,
        **{k: previous[k] for k in ("wall_time_s", "jobs", "executor") if k in previous},
    })


def run_benchmark(out: Path, config: BenchmarkConfig, jobs: int | None,
                  texts: dict[str, tuple[str, str]], stream: TextIO = sys.stderr,
                  ray: RaySession | None = None, fork_server: bool = True,
                  overwrite: bool = False, cache: RunCache | None = None) -> int:
    """Run (or complete) the benchmark in ``out``, then write results.csv (with
    the normalized scores), fractions.csv, the figure and the report. Returns
    the number of failed runs.
    ``ray``: run them as tasks of that Ray session (else on the local pool, each
    run forked from a fork server unless ``fork_server`` is false).
    ``overwrite``: replace the benchmark already in ``out``
    (:class:`OrchestratorReplacement`). ``cache``: where the cached methods'
    runs are looked up and kept (None: nowhere; :mod:`ftc.experiments.run_cache`).

    Raises OutInUse if an orchestrator is running on ``out``, StorageError if a
    file cannot be written."""
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise StorageError(f"cannot write {out}: {e.strerror or e}") from None
    lock = OrchestratorLock(out, TOOL).acquire()
    lock.announce_takeover(stream)
    guardian = Guardian()
    replacing = OrchestratorReplacement(out, overwrite)
    try:
        with replacing:
            prepare_directory(out, config, texts)
            failed = _run_all(out, config, jobs, stream, guardian, ray, fork_server, cache)
            collect_benchmark(out)  # with the lock held: no one else writes meanwhile
            benchmark_report.write_report(out)
    finally:
        guardian.close()
        lock.release()
        if replacing.restored:
            print(f"{TOOL}: no run finished; the benchmark that was in {out} is back in "
                  "place", file=stream)
    if replacing.restored:
        return len(failed)
    print(f"{TOOL}: results in {out / 'results.csv'}, report at {out / 'report.md'}"
          + (f"; {len(failed)} runs failed: {', '.join(sorted(failed))}" if failed else ""),
          file=stream)
    return len(failed)


def _run_all(out: Path, config: BenchmarkConfig, jobs: int | None, stream: TextIO,
             guardian: Guardian, ray: RaySession | None, fork_server: bool = True,
             cache: RunCache | None = None) -> list[str]:
    """The unfinished runs on the orchestrator's pool, those of a cached method
    once per group (:func:`ftc.experiments.run_cache.cache_groups`) or not at all
    on a hit; returns the failed keys."""
    cache = cache if cache is not None else RunCache(None)
    runs = plan_benchmark(config)
    finished = {r.key for r in runs if is_finished(r.directory(out))}
    groups = cache_groups(out, runs, config.intervals, config.steps_per_interval, config.link,
                          config.controller_args)
    sources: dict[str, dict] = {}
    waiting = reuse_before(out, groups, finished, cache, sources)
    todo = [r for r in runs if r.key not in finished and r.key not in waiting]
    print(f"{TOOL}: {len(runs)} runs ({len(config.scenarios)} scenarios x "
          f"{len(config.methods)} methods x {len(config.seeds)} seeds) in {out} "
          f"({len(finished)} already finished), link {config.link}, {executor_line(jobs, ray)}",
          file=stream)
    progress = Progress([r for r in runs if r.key not in waiting], finished, config.intervals,
                        stream)
    if ray is None:
        results = run_on_pool(out, config.run_config(), todo, [], progress, jobs, guardian,
                              stream, TOOL, fork_server)
    else:
        results = run_on_ray(ray, out, config.run_config(), todo, [], progress, stream, TOOL)
    reuse_after(out, groups, cache, sources, stream, TOOL)
    meta = json.loads((out / "benchmark.json").read_text())
    if groups:
        previous = meta.get("run_cache", {})
        meta["run_cache"] = {
            "dir": None if cache.root is None else str(cache.root),
            "code": dict(next(iter(groups)).code),
            "keys": {**previous.get("keys", {}),
                     **{r.key: key.digest for key, group in groups.items() for r in group}},
            "sources": {**previous.get("sources", {}), **sources}}
    meta["wall_time_s"] = time.time() - progress.start
    meta["jobs"] = jobs
    meta["executor"] = ray.describe() if ray is not None else {"kind": "local", "jobs": jobs}
    atomic_write_json(out / "benchmark.json", meta)
    return [k for k, v in results.items() if v["status"] != "ok"]


FIRST_COLUMNS = ("scenario", "method", "seed", "interval", "reward_per_step",
                 "eval_reward_per_step", *benchmark_report.SCORE_COLUMNS)


def collect_benchmark(out: Path) -> None:
    """Every finished run's per-interval metrics into results.csv and results.json
    (columns scenario, method, seed, interval, reward_per_step,
    eval_reward_per_step, reference_reward_per_step, closed_reward_per_step,
    normalized_score (benchmark_report.normalized_scores), then the controllers'
    other metrics)."""
    out = Path(out)
    config = BenchmarkConfig.from_json(json.loads((out / "benchmark.json").read_text())["config"])
    rows, runs = [], []
    columns = list(FIRST_COLUMNS)
    for stem in config.scenarios:
        for method in config.methods:
            for seed in config.seeds:
                d = RunSpec(stem, 0, method, int(seed), stem).directory(out)
                if not is_finished(d):
                    continue
                result = json.loads((d / "result.json").read_text())
                runs.append({"run": result.get("run"), "scenario": stem, "method": method,
                             "seed": seed, "wall_time_s": result.get("wall_time_s")})
                for m in json.loads((d / "metrics.json").read_text()):
                    row = {"scenario": stem, "method": method, "seed": seed, **m}
                    columns += [k for k in row if k not in columns]
                    rows.append(row)
    rows += reference_scores.cells_of(out, config)  # with --reference-scores
    rows = benchmark_report.normalized_scores(rows, config.reference)
    atomic_write_csv(out / "results.csv", columns,
                     [["" if r.get(c) is None else r.get(c) for c in columns] for r in rows])
    atomic_write_json(out / "results.json", {"runs": runs, "metrics": rows})


def main(argv: Sequence[str] | None = None) -> int:
    """Exit codes: 0 done; 1 some runs failed (named on the last line); 2 bad
    input, or --out in use; 5 a file could not be written."""
    args = parse_args(argv)
    ray = None
    try:
        # connected (and every node's code checked) before anything is written
        ray = connect(args.ray_address, args.jobs) if args.executor == "ray" else None
        return 1 if run_benchmark(args.out_dir, args.config, args.jobs, args.texts,
                                  ray=ray, fork_server=args.fork_server,
                                  overwrite=args.overwrite,
                                  cache=RunCache(args.run_cache_dir)) else 0
    except RunError as e:
        print(f"{TOOL}: error: {e}", file=sys.stderr, flush=True)
        return e.exit_code
    finally:
        if ray is not None:
            ray.close()
