"""Reproduce the paper's experiments on the real plant process, in parallel.

    python -m ftc.experiments all                       # short default (minutes)
    python -m ftc.experiments all --full                # the paper's protocol
    python -m ftc.experiments single|multiple|aggregate [--trials 20] [--seeds 0 1 2]
    python -m ftc.experiments model-search [--quick]    # the world-model grid
    python -m ftc.experiments report --out runs/NAME    # figures and report again
    python -m ftc.experiments benchmark [--scenarios FILE...] [--methods NAME...]
                                        # the benchmark suite (benchmark --help)
    python -m ftc.experiments compare DIR... --out REPORT
                                        # benchmark directories in one report (compare --help)

Experiments (docs/plant-model.md, "The paper's experiments"):
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
With --tensorboard TB: TB/EXP/tNN/METHOD/sS/ holds each run's TensorBoard
scalars (its controller's --tensorboard; docs/ecosystem.md).

A run counts as finished only once its result.json is written (atomically,
last). --resume skips finished runs and redoes unfinished ones from scratch.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shlex
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Sequence

from ftc.common.cli import Check, OneLineParser, at_least, checked, out_dir_problem
from ftc.common.errors import RunError
from ftc.control.run.config import MAX_INTERVALS, MAX_STEPS_PER_INTERVAL
from ftc.experiments import benchmark, compare, report
from ftc.experiments.collect import collect
from ftc.experiments.method_args import method_args, tool_parser, untaken
from ftc.experiments.methods import DEFAULT_METHODS, METHODS, resolve_methods
from ftc.experiments.orchestrator import run_experiments
from ftc.experiments.processes import OrchestratorLock, OutInUse, check_out_free
from ftc.experiments.ray_executor import (RaySession, add_executor_options,
                                         check_executor_options, connect)
from ftc.experiments.scenarios import EXPERIMENTS, PRESETS, ExperimentConfig

TOOL = "ftc.experiments"
# Declared constraints of the options (checked by argparse as they are read).
MAX_JOBS = 256
MAX_TRIALS = 10_000
MAX_RUN_TIMEOUT = 1e6  # seconds (11.6 days); 0 means no timeout
SEED = at_least(0, 2**31 - 1)  # the controller's --seed range
SCENARIO_SEED = at_least(0, 2**63 - 1)  # numpy's default_rng takes any non-negative int


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="python -m ftc.experiments", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("command", choices=(*EXPERIMENTS, "all", "model-search", "report"),
                        help="which experiment(s) to run; model-search: the world-model grid; "
                             "report: redo results, figures and report from saved runs (the "
                             "benchmark suite and the comparison of benchmarks have their own "
                             "options: benchmark --help, compare --help)")
    parser.add_argument("--out", type=checked(Path, nonempty=True), default=None,
                        help="run directory (default: runs/<command>-<date-time>)")
    parser.add_argument("--resume", action="store_true",
                        help="complete an interrupted run directory: finished runs are kept, "
                             "unfinished ones redone")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the experiment already in --out: it is moved aside when "
                             "this one starts, deleted once one of its runs has finished, and "
                             "moved back if none does")
    parser.add_argument("--full", action="store_true",
                        help="the paper's protocol (20 aggregate trials); default: a short run "
                             f"({PRESETS['quick']['trials']} aggregate trials)")
    parser.add_argument("--jobs", type=checked(int, at_least(1, MAX_JOBS)), default=None,
                        help="runs in parallel (default: number of cores; with --executor ray: "
                             "at most this many runs in flight, default as many as the "
                             "cluster's CPUs, one per run)")
    add_executor_options(parser)
    parser.add_argument("--trials", type=checked(int, at_least(1, MAX_TRIALS)), default=None,
                        help="aggregate trials")
    parser.add_argument("--seeds", type=checked(int, SEED), nargs="+", default=None,
                        help="controller seeds; every trial and method runs each (default: 0)")
    parser.add_argument("--scenario-seed", type=checked(int, SCENARIO_SEED),
                        default=ExperimentConfig.scenario_seed,
                        help="seed of the aggregate trials' random faults")
    parser.add_argument("--intervals", type=checked(int, at_least(1, MAX_INTERVALS)),
                        default=None, help="degradation intervals per run (paper: 10)")
    parser.add_argument("--steps-per-interval",
                        type=checked(int, at_least(1, MAX_STEPS_PER_INTERVAL)), default=None,
                        help="real control steps per interval, t_online (paper: 512)")
    parser.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS),
                        help=f"methods to compare (registered: {', '.join(METHODS)}), or "
                             "plug-ins, NAME=SPEC with SPEC module.path:factory, sb3:PATH.zip "
                             "or onnx:PATH.onnx")
    parser.add_argument("--pretrain", action="store_true",
                        help="pass --pretrain to the PPO methods' controllers (nominal "
                             "pretraining in simulation; default: from scratch as in the paper)")
    parser.add_argument("--controller-args", default="",
                        help="extra arguments for the methods' controllers, one string (e.g. "
                             "\"--model-episodes 10 --offline-steps 512\"); each option goes to "
                             "the methods it acts on (ftc.experiments.method_args)")
    parser.add_argument("--run-timeout", type=checked(float, Check(low=0.0, high=MAX_RUN_TIMEOUT)),
                        default=0.0,
                        help="kill a run after this many seconds and count it failed (0: never)")
    parser.add_argument("--tensorboard", type=checked(Path, nonempty=True), default=None,
                        metavar="DIR",
                        help="TensorBoard scalars of every run, each in its own subdirectory "
                             "DIR/EXPERIMENT/tNN/METHOD/sSEED (the controller's --tensorboard; "
                             "docs/ecosystem.md)")
    parser.add_argument("--model-search", action="store_true",
                        help="with 'all': also run the world-model grid")
    parser.add_argument("--quick", action="store_true",
                        help="model-search: a 2-model subset on a small data set (for tests)")
    return parser


def _controller_args_problem(methods: Sequence[str], extra: Sequence[str],
                             config: ExperimentConfig, out: Path) -> str | None:
    """Why a run's controller would refuse ``extra``, or None: each method's own
    parser reads the run's command line (writing nothing), so a bad
    --controller-args is refused here instead of failing every run."""
    unused = untaken(methods, extra)
    if unused:
        return (f"{' '.join(unused)}: no method here takes it (each option goes to the "
                "methods whose runs it acts on)")
    for name in methods:
        method = METHODS[name]
        parse = tool_parser(method.module)
        if parse is None:  # a registered module of another kind: its runs will tell
            continue
        argv = [*method.args, "--scenario", "", "--seed", str(config.seeds[0]),
                "--intervals", str(config.intervals),
                "--steps-per-interval", str(config.steps_per_interval),
                f"--out={out / 'runs' / 'check'}",
                *method_args(method, extra)]
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                parse(argv)
        except SystemExit as e:
            if e.code:
                line = (err.getvalue().strip().splitlines() or [f"exit {e.code}"])[-1]
                return f"{name}: {line.split(': error: ', 1)[-1]}"
            return f"{name}: --help is not a run option"
    return None


def parse_args(argv: Sequence[str] | None = None) -> SimpleNamespace:
    """The command line, every option checked before anything is started or
    written: bad input exits 2 with one line naming the flag. Returns the
    parsed options with ``out`` resolved and, for experiment commands,
    ``config`` (the ExperimentConfig)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    check_executor_options(parser, args)
    if args.executor == "ray" and args.command in ("model-search", "report"):
        parser.error(f"--executor ray: {args.command} runs on this machine (it has no runs to "
                     "distribute)")
    try:  # plug-ins (NAME=module:factory, sb3:..., onnx:...): registered, checked
        args.methods = resolve_methods(args.methods, args.out and args.out / "experiment.json")
    except ValueError as e:
        parser.error(f"--methods: {e}")
    unknown = [m for m in args.methods if m not in METHODS]
    if unknown:
        parser.error(f"--methods: unknown methods {unknown}; registered: {', '.join(METHODS)}")
    try:
        extra = tuple(shlex.split(args.controller_args))
    except ValueError as e:
        parser.error(f"--controller-args: {e}")
    out = args.out or Path("runs") / f"{args.command}-{time.strftime('%Y%m%d-%H%M%S')}"
    ns = SimpleNamespace(**vars(args), out_dir=out, config=None)
    if args.tensorboard is not None and args.command in ("report", "model-search"):
        parser.error(f"--tensorboard: the {args.command} command runs no controller")
    if args.overwrite and (args.command in ("report", "model-search") or args.model_search):
        parser.error(f"--overwrite: replaces a whole experiment; not with "
                     f"{'--model-search' if args.model_search else args.command}")
    if args.command == "report":
        if not (out / "experiment.json").is_file():
            parser.error(f"--out {out} holds no experiment.json")
        try:
            check_out_free(out)
        except OutInUse as e:
            parser.error(str(e))
        return ns
    problem = out_dir_problem(out)
    if problem:  # an unwritable --out is an error before any run starts
        parser.error(f"--out {out}: cannot write there ({problem})")
    if args.tensorboard is not None:
        problem = out_dir_problem(args.tensorboard)
        if problem:
            parser.error(f"--tensorboard {args.tensorboard}: cannot write there ({problem})")
    try:
        check_out_free(out)
    except OutInUse as e:
        parser.error(str(e))
    if args.command == "model-search":
        return ns
    preset = PRESETS["full" if args.full else "quick"]
    ns.config = ExperimentConfig(
        experiments=EXPERIMENTS if args.command == "all" else (args.command,),
        methods=tuple(dict.fromkeys(args.methods)),
        seeds=tuple(dict.fromkeys(args.seeds)) if args.seeds else preset["seeds"],
        trials=args.trials if args.trials is not None else preset["trials"],
        scenario_seed=args.scenario_seed,
        # "is None", not "or": an explicit value is checked, never replaced
        intervals=args.intervals if args.intervals is not None else preset["intervals"],
        steps_per_interval=(args.steps_per_interval if args.steps_per_interval is not None
                            else preset["steps_per_interval"]),
        controller_args=(("--pretrain",) if args.pretrain else ()) + extra,
        run_timeout=args.run_timeout,
        tensorboard=None if args.tensorboard is None else str(args.tensorboard.resolve()))
    problem = _controller_args_problem(ns.config.methods, ns.config.controller_args, ns.config,
                                       out)
    if problem:
        parser.error(f"--controller-args: {problem}")
    if args.overwrite and args.resume:
        parser.error("--overwrite replaces an experiment, --resume completes it: give one")
    meta = out / "experiment.json"
    if args.overwrite and not meta.is_file():
        parser.error(f"--overwrite: {out} holds no experiment (experiment.json) to replace")
    if meta.is_file() and not args.overwrite:
        if not args.resume:
            parser.error(f"--out {out} already holds an experiment: --resume completes it, "
                         "--overwrite replaces it")
        try:
            ExperimentConfig.from_json(json.loads(meta.read_text())["config"])
        except (OSError, ValueError, KeyError, TypeError) as e:
            parser.error(f"--resume: {meta} is not a readable experiment "
                         f"({type(e).__name__}: {e})")
    return ns


def _run(args: SimpleNamespace, ray: RaySession | None) -> int:
    out = args.out_dir
    if args.command == "report":
        with OrchestratorLock(out) as lock:  # one writer: not beside a running experiment
            lock.announce_takeover()
            collect(out)
            report.write_report(out)
        print(f"report at {out / 'report.md'}")
        return 0
    if args.command == "model-search":
        out.mkdir(parents=True, exist_ok=True)
        with OrchestratorLock(out) as lock:
            lock.announce_takeover()
            _model_search(out, args.quick, args.jobs)
            if (out / "experiment.json").is_file():
                report.write_report(out)
        print(f"model search table at {out / 'model_search.csv'}")
        return 0
    if args.command == "all" and args.model_search:  # on this machine, also with --executor ray
        out.mkdir(parents=True, exist_ok=True)
        with OrchestratorLock(out) as lock:
            lock.announce_takeover()
            _model_search(out, False, args.jobs or os.cpu_count() or 1)
    failed = run_experiments(out, args.config, args.jobs, args.resume, ray=ray,
                             fork_server=args.fork_server, overwrite=args.overwrite)
    return 1 if failed else 0


def _model_search(out: Path, quick: bool, jobs: int) -> None:
    """The world-model grid into ``out`` (torch is imported here, not by the CLI)."""
    from ftc.experiments.model_search import QUICK_MODEL_SEARCH, ModelSearchConfig, model_search

    model_search(out, QUICK_MODEL_SEARCH if quick else ModelSearchConfig(), jobs)


def main(argv: list[str] | None = None) -> int:
    """Exit codes (:mod:`ftc.common.errors`): 0 done; 1 some runs failed (named on
    the last line); 2 bad input, or --out in use by a running orchestrator;
    5 a file could not be written (disk full, unwritable path: the line names
    it; temporary files are removed and --resume continues once space is back)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["benchmark"]:  # its own options: ftc.experiments.benchmark
        return benchmark.main(argv[1:])
    if argv[:1] == ["compare"]:  # its own options: ftc.experiments.compare
        return compare.main(argv[1:])
    args = parse_args(argv)
    ray = None
    try:
        # connected (and every node's code checked) before anything is written
        ray = connect(args.ray_address, args.jobs) if args.executor == "ray" else None
        return _run(args, ray)
    except RunError as e:
        print(f"{TOOL}: error: {e}", file=sys.stderr, flush=True)
        return e.exit_code
    finally:
        if ray is not None:
            ray.close()
