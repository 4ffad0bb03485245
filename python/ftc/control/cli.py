"""What the command lines of interval runs share (``python -m ftc.controller``,
``python -m ftc.mpc``): options from the config dataclasses in a stable order,
every check before anything starts or is written, and one-line errors with
the documented exit codes (:mod:`ftc.common.errors`)."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import fields
from pathlib import Path
from typing import Any, Callable

from ftc.common.cli import add_dataclass_options, check_config, out_dir_problem
from ftc.common.errors import CheckpointError, RunError
from ftc.common.lifetime import Stopped, stop_signals, stopped_line
from ftc.control.config import RunConfig

# RunConfig's fields before and after the tool's own in --help
RUN_HEAD = ("scenario", "seed", "out", "intervals", "steps_per_interval")


def option_order(cls: type) -> list[str]:
    """method, the run's head options, the tool's own, then the link options."""
    run = [f.name for f in fields(RunConfig)]
    own = [f.name for f in fields(cls) if f.name not in run and f.name != "method"]
    return ["method", *RUN_HEAD, *own, *[n for n in run if n not in RUN_HEAD]]


def add_run_options(parser: argparse.ArgumentParser, cls: type) -> None:
    add_dataclass_options(parser, cls, order=option_order(cls))


def check_or_exit(parser: argparse.ArgumentParser, cfg: RunConfig,
                  parts: dict[str, Any] | None = None) -> None:
    """Every declared constraint, the cross-field rules, the scenario file and
    the output directory; bad input exits 2 with one line before anything exists.
    parts: other configs by option prefix (e.g. {"ppo-": PPOConfig(...)})."""
    try:
        check_config(cfg)
        for prefix, part in (parts or {}).items():
            check_config(part, prefix)
        cfg.validate()
    except ValueError as e:
        parser.error(str(e))
    if cfg.scenario:  # the plant would refuse it too, but only after --out exists
        from ftc import _core  # native: the plant's own scenario parser

        try:
            _core.load_scenario(cfg.scenario)
        except _core.ScenarioError as e:  # names the file and the key: one line
            parser.error(f"--scenario: {e}")
    if cfg.resume and not (Path(cfg.resume) / "config.json").is_file():
        parser.error(f"--resume {cfg.resume}: config.json missing (is it a run directory?)")
    problem = out_dir_problem(cfg.resume or cfg.out)
    if problem:
        parser.error(f"--out {cfg.resume or cfg.out}: cannot write there ({problem})")
    problem = out_dir_problem(cfg.tensorboard) if cfg.tensorboard else None
    if problem:
        parser.error(f"--tensorboard {cfg.tensorboard}: cannot write there ({problem})")


def read_run_configs(out: str, parts: dict[str, type]) -> dict[str, Any]:
    """The configs a stopped run was started with, from its config.json (one
    dataclass per entry of ``parts``); raises CheckpointError when missing or
    malformed."""
    path = Path(out) / "config.json"
    try:
        doc = json.loads(path.read_text())
        configs = {}
        for name, cls in parts.items():
            values = {k: tuple(v) if isinstance(v, list) else v for k, v in doc[name].items()}
            configs[name] = cls(**values)
    except FileNotFoundError:
        raise CheckpointError(f"{path}: missing (is {out} a run directory?)") from None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise CheckpointError(f"{path}: malformed run configuration "
                              f"({type(e).__name__}: {e})") from None
    return configs


def run_or_report(tool: str, run: Callable[[], Any], out: str | None = None) -> int:
    """Run; a RunError is one line on stderr and its exit code. SIGINT, SIGTERM
    and SIGHUP stop the run through its clean-up: one line ("stopped by
    SIGTERM", and with ``out``, the run directory, where the finished
    intervals are and how to go on) and exit 128 + the signal's number (130,
    143, 129), as a shell reports it."""
    kept = f"; the finished intervals are in {out}, --resume {out} continues" if out else ""
    try:
        with stop_signals():
            run()
    except RunError as e:
        print(f"{tool}: error: {e}", file=sys.stderr, flush=True)
        return e.exit_code
    except (KeyboardInterrupt, Stopped) as e:
        line, code = stopped_line(tool, e, kept)
        print(f"\n{line}", file=sys.stderr, flush=True)
        return code
    return 0
