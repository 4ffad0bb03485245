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
from typing import Any, Callable, Sequence

from ftc.common.cli import (add_dataclass_options, check_config, flag, given_options,
                            out_dir_problem)
from ftc.common.errors import CheckpointError, RunError
from ftc.common.lifetime import Stopped, stop_signals, stopped_line
from ftc.common.paths import scenario_file
from ftc.common.replacing import STASH
from ftc.common.run_lock import InUse, check_free
from ftc.control import registry
from ftc.control.config import EXTENSIBLE_FIELDS, RUN_FILES, RunConfig, run_local_fields
from ftc.control.runner import held_advice, replacement

# RunConfig's fields before and after the tool's own in --help
RUN_HEAD = ("scenario", "seed", "out", "intervals", "steps_per_interval")


def option_order(cls: type) -> list[str]:
    """method, the run's head options, the tool's own, then the link options."""
    run = [f.name for f in fields(RunConfig)]
    own = [f.name for f in fields(cls) if f.name not in run and f.name != "method"]
    method = ["method"] if any(f.name == "method" for f in fields(cls)) else []
    return [*method, *RUN_HEAD, *own, *[n for n in run if n not in RUN_HEAD]]


def add_run_options(parser: argparse.ArgumentParser, cls: type) -> None:
    add_dataclass_options(parser, cls, order=option_order(cls))


def method_argv(parser: argparse.ArgumentParser, argv: Sequence[str] | None,
                tool: str) -> list[str]:
    """The command line with ``--method NAME`` spelled as ``tool`` reads it
    (:func:`ftc.control.registry.expand_method`); exit 2 on a method of another
    tool or a flag the method fixes."""
    try:
        return registry.expand_method(sys.argv[1:] if argv is None else argv, tool)
    except ValueError as e:
        parser.error(str(e))


def refuse_ignored(parser: argparse.ArgumentParser, cfg: Any, named: set[str],
                   prefix: str = "") -> None:
    """Exit 2 on the first option given that ``cfg.ignored()`` says has no effect."""
    for name, why in cfg.ignored().items():
        if prefix.replace("-", "_") + name in named:
            parser.error(f"{flag(name, prefix)} has no effect {why}")


def check_or_exit(parser: argparse.ArgumentParser, cfg: RunConfig,
                  parts: dict[str, Any] | None = None) -> None:
    """Every declared constraint, the cross-field rules, the scenario file and
    the output directory; bad input exits 2 with one line before anything exists.
    parts: other configs by option prefix (e.g. {"ppo-": PPOConfig(...)})."""
    try:
        if cfg.scenario:  # a packaged scenario's name: its file
            try:
                cfg.scenario = scenario_file(cfg.scenario)
            except ValueError as e:
                raise ValueError(f"--scenario: {e}") from None
        check_config(cfg)
        for prefix, part in (parts or {}).items():
            check_config(part, prefix)
            if not cfg.resume and hasattr(part, "validate"):
                part.validate()
        if not cfg.resume:  # a resumed run's cross-field rules: on its own config
            cfg.validate()
        elif cfg.overwrite:
            raise ValueError("--overwrite replaces a run, --resume continues it: give one")
    except ValueError as e:
        parser.error(str(e))
    if cfg.scenario and not cfg.resume:  # a resumed run's own: checked by resume_configs
        check_scenario(parser, cfg.scenario)
    if cfg.resume and not (Path(cfg.resume) / "config.json").is_file():
        parser.error(f"--resume {cfg.resume}: config.json missing (is it a run directory?)")
    problem = out_dir_problem(cfg.resume or cfg.out)
    if problem:
        parser.error(f"--out {cfg.resume or cfg.out}: cannot write there ({problem})")
    try:  # a live writer first: the run it holds is not finished
        check_free(cfg.resume or cfg.out)
    except InUse as e:
        parser.error(str(e))
    held = run_held(cfg.out)
    if not cfg.resume and held and not cfg.overwrite:
        parser.error(f"--out {held_advice(Path(cfg.out), held)}")
    problem = out_dir_problem(cfg.tensorboard) if cfg.tensorboard else None
    if problem:
        parser.error(f"--tensorboard {cfg.tensorboard}: cannot write there ({problem})")


def check_scenario(parser: argparse.ArgumentParser, scenario: str, what: str = "--scenario"
                   ) -> None:
    """The plant's own parser reads the file (it would refuse it too, but only
    after --out exists): a bad one exits 2 with one line naming file and key."""
    from ftc import _core  # native: the plant's scenario parser

    try:
        _core.load_scenario(scenario)
    except _core.ScenarioError as e:
        parser.error(f"{what}: {e}")


def run_held(out: str | Path) -> str | None:
    """What run ``out`` holds ("finished, 10 intervals", "stopped after 2 of 10
    intervals"), or None when it holds none."""
    out = Path(out)
    present = [n for n in RUN_FILES if (out / n).exists()]
    if replacement(out).pending():
        return f"an --overwrite that never finished; the run it replaced is in {out / STASH}"
    if not present:
        return None
    try:
        done = json.loads((out / "done.json").read_text())
        return f"finished, {done['intervals']} intervals"
    except (OSError, ValueError, KeyError, TypeError):
        pass
    try:
        rows = max(len((out / "metrics.csv").read_text().splitlines()) - 1, 0)
    except OSError:
        rows = 0
    return f"stopped after {rows} finished intervals" if rows else f"started: {', '.join(present)}"


def resume_configs(parser: argparse.ArgumentParser, argv: Sequence[str] | None,
                   given: dict[str, tuple[Any, str]], classes: dict[str, type],
                   check_given: Callable[[dict[str, Any], set[str]], None] | None = None
                   ) -> dict[str, Any]:
    """The configs of the run ``--resume DIR`` continues, read from its
    config.json, with every option given on this command line honoured or
    refused (exit 2, one line): the run-local ones (link, console, TensorBoard)
    are this command line's; --intervals beyond the run's extends it; any other
    option given must equal the run's value, since it fixes the results.

    given: the configs parsed from this command line by part, with their
    option prefix ({"controller": (cfg, ""), "ppo": (ppo, "ppo-")}); classes:
    the config class of each part; check_given(stored configs, options given)
    refuses options first on the tool's own grounds (exit 2)."""
    here = next(iter(given.values()))[0]
    out = here.resume
    try:
        stored = read_run_configs(out, classes)
    except CheckpointError as e:
        parser.error(str(e))
    named = given_options(parser, argv)
    if check_given is not None:
        check_given(stored, named)
    if "out" in named and Path(here.out).resolve() != Path(out).resolve():
        parser.error(f"--out {here.out} with --resume {out}: a resumed run stays in its "
                     "directory (give only --resume)")
    for part, (cfg, prefix) in given.items():
        run = stored[part]
        local = run_local_fields(run)
        for f in fields(run):
            value, theirs = getattr(cfg, f.name), getattr(run, f.name)
            dest = prefix.replace("-", "_") + f.name
            if f.name in local:
                setattr(run, f.name, value)
            elif dest not in named or value == theirs or _same_file(f.name, value, theirs):
                continue
            elif f.name in EXTENSIBLE_FIELDS and value > theirs:
                setattr(run, f.name, value)
            elif f.name in EXTENSIBLE_FIELDS:
                parser.error(f"--resume {out}: {flag(f.name, prefix)} {value} is below the "
                             f"run's {theirs}; a run can be extended, not shortened")
            else:
                shown = " ".join(map(str, value)) if isinstance(value, tuple) else value
                parser.error(f"--resume {out}: {flag(f.name, prefix)} {shown} differs from "
                             f"the run's {theirs!r}, which fixes its results (start a new "
                             "run with another --out)")
        run.resume, run.out, run.overwrite = out, out, False
    for run in stored.values():
        try:
            if hasattr(run, "validate"):
                run.validate()
        except ValueError as e:
            parser.error(f"--resume {out}: {e}")
    scenario = next(iter(stored.values())).scenario
    if scenario:
        check_scenario(parser, scenario, f"--resume {out}: the run's scenario")
    return stored


def _same_file(name: str, a: Any, b: Any) -> bool:
    return name == "scenario" and bool(a) and bool(b) and Path(a).resolve() == Path(b).resolve()


def read_run_configs(out: str, parts: dict[str, type]) -> dict[str, Any]:
    """The configs a stopped run was started with, from its config.json (one
    dataclass per entry of ``parts``, or a function of the entry's values that
    builds it); raises CheckpointError when missing or
    malformed."""
    path = Path(out) / "config.json"
    try:
        doc = json.loads(path.read_text())
        configs = {}
        for name, cls in parts.items():
            values = {k: tuple(v) if isinstance(v, list) else v for k, v in doc[name].items()}
            if "method" in values:  # a run written under a former name of its method
                values["method"] = registry.canonical(values["method"])
            values = _without_retired(cls, values, path)
            configs[name] = cls(**values) if isinstance(cls, type) else cls(values)
    except FileNotFoundError:
        raise CheckpointError(f"{path}: missing (is {out} a run directory?)") from None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise CheckpointError(f"{path}: malformed run configuration "
                              f"({type(e).__name__}: {e})") from None
    return configs


def _without_retired(cls: type, values: dict[str, Any], path: Path) -> dict[str, Any]:
    """``values`` without the fields ``cls.RETIRED_FIELDS`` (a class's, or a
    config factory's attribute) names when they hold
    the value that does what the code does now; any other value of such a
    field: CheckpointError (the run cannot be continued as it was started)."""
    retired = getattr(cls, "RETIRED_FIELDS", {})
    for name in retired.keys() & values.keys():
        if values[name] != retired[name]:
            raise CheckpointError(f"{path}: the run was started with {flag(name)} "
                                  f"{values[name]!r}, which this controller no longer offers; "
                                  f"it cannot be resumed (start a new run)")
    return {k: v for k, v in values.items() if k not in retired}


def _kept(out: str | None) -> str:
    """What a stopped run left in ``out``, said after the stop: its finished
    intervals (a checkpoint) and how to go on, or that none finished."""
    if not out:
        return ""
    if (Path(out) / "checkpoint.pt").is_file():
        return f"; the finished intervals are in {out}, --resume {out} continues"
    return f"; no interval had finished, so nothing was kept in {out} (run it again)"


def run_or_report(tool: str, run: Callable[[], Any], out: str | None = None) -> int:
    """Run; a RunError is one line on stderr and its exit code. SIGINT, SIGTERM
    and SIGHUP stop the run through its clean-up: one line ("stopped by
    SIGTERM", and with ``out``, the run directory, where the finished
    intervals are and how to go on) and exit 128 + the signal's number (130,
    143, 129), as a shell reports it."""
    try:
        with stop_signals():
            run()
    except RunError as e:
        print(f"{tool}: error: {e}", file=sys.stderr, flush=True)
        return e.exit_code
    except (KeyboardInterrupt, Stopped) as e:
        line, code = stopped_line(tool, e, _kept(out))
        print(f"\n{line}", file=sys.stderr, flush=True)
        return code
    return 0
