"""The paper's experiments, reproduced on the real plant process in parallel
(``python -m ftc.experiments``; :mod:`ftc.experiments.cli` documents the
command line and the run directory).

    methods       the compared methods (a registry; a leaf module)
    scenarios     ExperimentConfig, presets, the trials' fault scenarios
    runs          one run: its controller, plant and recorder; baseline episodes
    processes     the recorder process and process bookkeeping for --resume
    progress      the progress line
    orchestrator  a directory's runs on a thread pool, then collect and report
    collect       results.csv/json and the tank-control trajectories from the logs
    model_search  the world-model grid
    figures, report  drawn and written from saved results only
    suite         the benchmark suite's default scenarios
    benchmark, benchmark_report  the benchmark suite (``benchmark`` command) and its report
"""

from ftc.experiments.cli import build_parser, main
from ftc.experiments.collect import collect
from ftc.experiments.methods import (DEFAULT_METHODS, METHODS, PAPER_METHODS, MethodSpec,
                                     register_method)
from ftc.experiments.model_search import QUICK_MODEL_SEARCH, ModelSearchConfig, model_search
from ftc.experiments.orchestrator import run_experiments
from ftc.experiments.runs import RunSpec, is_finished, plan_runs
from ftc.experiments.scenarios import (EXPERIMENTS, PRESETS, ExperimentConfig, Scenario,
                                       aggregate_scenarios, experiment_scenarios)

__all__ = ["DEFAULT_METHODS", "EXPERIMENTS", "METHODS", "PAPER_METHODS", "PRESETS",
           "QUICK_MODEL_SEARCH", "ExperimentConfig", "MethodSpec", "ModelSearchConfig", "RunSpec",
           "Scenario", "aggregate_scenarios", "build_parser", "collect", "experiment_scenarios",
           "is_finished", "main", "model_search", "plan_runs", "register_method",
           "run_experiments"]
