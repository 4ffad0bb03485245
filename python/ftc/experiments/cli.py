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
import os
import shlex
import time
from pathlib import Path

from ftc.common.cli import out_dir_problem
from ftc.experiments import report
from ftc.experiments.collect import collect
from ftc.experiments.methods import DEFAULT_METHODS, METHODS
from ftc.experiments.model_search import QUICK_MODEL_SEARCH, ModelSearchConfig, model_search
from ftc.experiments.orchestrator import run_experiments
from ftc.experiments.scenarios import EXPERIMENTS, PRESETS, ExperimentConfig


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
        collect(out)
        report.write_report(out)
        print(f"report at {out / 'report.md'}")
        return 0
    if args.command == "model-search":
        out.mkdir(parents=True, exist_ok=True)
        model_search(out, QUICK_MODEL_SEARCH if args.quick else ModelSearchConfig(),
                     max(1, args.jobs))
        if (out / "experiment.json").is_file():
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
    # An unwritable --out is an error before any run starts.
    problem = out_dir_problem(out)
    if problem:
        parser.error(f"--out {out}: cannot write there ({problem})")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        parser.error(f"--out {out}: cannot write there: {e.strerror or e}")
    if args.command == "all" and args.model_search:
        model_search(out, ModelSearchConfig(), max(1, args.jobs))
    failed = run_experiments(out, config, max(1, args.jobs), args.resume)
    return 1 if failed else 0
