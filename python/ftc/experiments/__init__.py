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

import importlib
from typing import Any

# The package's names, each from its module, imported on first use (PEP 562):
# a tool that needs one submodule (replay its figures, the controller its
# suite) does not pay for the others (matplotlib, scipy, torch). The functions
# collect and model_search are reached through their modules of the same name.
_NAMES = {
    "build_parser": "cli", "main": "cli",
    "DEFAULT_METHODS": "methods", "METHODS": "methods", "PAPER_METHODS": "methods",
    "MethodSpec": "methods", "register_method": "methods",
    "QUICK_MODEL_SEARCH": "model_search", "ModelSearchConfig": "model_search",
    "run_experiments": "orchestrator",
    "RunSpec": "runs", "is_finished": "runs", "plan_runs": "runs",
    "EXPERIMENTS": "scenarios", "PRESETS": "scenarios", "ExperimentConfig": "scenarios",
    "Scenario": "scenarios", "aggregate_scenarios": "scenarios",
    "experiment_scenarios": "scenarios",
}

__all__ = sorted(_NAMES)


def __getattr__(name: str) -> Any:
    if name not in _NAMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_NAMES[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_NAMES})
