"""Command lines generated from typed config dataclasses, with the
constraints declared next to the help text.

A field is an option: ``--<prefix><field-name>``, its help text from
``metadata["help"]``, its type from the annotation, its allowed values from
``metadata["choices"]`` and its constraint from ``metadata["check"]`` (a
:class:`Check`). :func:`check_config` checks every field of a parsed config in
one place, so each entry point refuses bad input with one line naming the
flag (exit 2) before it starts or writes anything.
"""

from __future__ import annotations

import argparse
import math
import os
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Callable, Sequence

from ftc.common.run_lock import InUse, check_free


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line on stderr (``prog: error: ...``,
    exit 2) instead of the usage text and the error: the line names the flag,
    and ``--help`` shows the usage."""

    def error(self, message: str) -> None:  # type: ignore[override]
        # the same prefix as the tool's run-time errors ("ftc.controller: error: ...")
        self.exit(2, f"{self.prog.removeprefix('python -m ')}: error: {message}\n")


def given_options(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> set[str]:
    """The dests of the options given on the command line ``argv`` (already
    parsed once, so it is known to be valid), told apart from defaults even
    where a value equals its default."""
    actions = [a for a in parser._actions if a.dest != "help"]
    saved = [a.default for a in actions]
    try:
        for a in actions:
            a.default = argparse.SUPPRESS
        return set(vars(parser.parse_args(argv)))
    finally:
        for a, default in zip(actions, saved):
            a.default = default


def flag(name: str, prefix: str = "") -> str:
    """The command-line option of config field ``name``."""
    return "--" + prefix + name.replace("_", "-")


@dataclass(frozen=True)
class Check:
    """A numeric constraint: finite, and within [low, high] (None: unbounded);
    ``integer`` also requires an int. ``None`` values pass (optional fields)."""

    low: float | None = None
    high: float | None = None
    integer: bool = False
    low_open: bool = False  # low itself excluded

    def problem(self, value: Any) -> str | None:
        """Why ``value`` breaks the constraint, or None."""
        if value is None:
            return None
        values = value if isinstance(value, (tuple, list)) else (value,)
        for v in values:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                return f"must be a number, got {v!r}"
            if self.integer and not isinstance(v, int):
                return f"must be an integer, got {v!r}"
            if not math.isfinite(v):
                return f"must be a finite number, got {v}"
            if self.low is not None and (v < self.low or (self.low_open and v == self.low)):
                return f"must be {'>' if self.low_open else '>='} {_number(self.low)}, got {v}"
            if self.high is not None and v > self.high:
                return f"must be <= {_number(self.high)}, got {v}"
        return None


def _number(x: float) -> str:
    """A bound as written: whole numbers in full (2147483647, not 2.14748e+09)."""
    return str(int(x)) if float(x).is_integer() else f"{x:g}"


def at_least(n: int, high: float | None = None) -> Check:
    """An integer >= n (and <= high)."""
    return Check(low=n, high=high, integer=True)


def positive(high: float | None = None) -> Check:
    """A finite number > 0."""
    return Check(low=0.0, high=high, low_open=True)


def between(low: float, high: float) -> Check:
    """A finite number in [low, high]."""
    return Check(low=low, high=high)


FINITE = Check()


def add_dataclass_options(parser: Any, cls: type, prefix: str = "",
                          choices: dict[str, Sequence[str]] | None = None,
                          skip: Sequence[str] = (), order: Sequence[str] = ()) -> None:
    """Add ``--<prefix><field-name>`` for every field of ``cls`` to ``parser``
    (an ArgumentParser or argument group); dest is ``<prefix>_<field_name>``
    with dashes as underscores. bool fields get --x/--no-x, ``tuple[int, ...]``
    fields take one or more ints, int and float (also optional float) fields
    are parsed as such, everything else as a string. ``order``: field names to
    add first, in that order (the rest follow in declaration order)."""
    choices = choices or {}
    by_name = {f.name: f for f in fields(cls)}
    ordered = [by_name[n] for n in order] + [f for f in fields(cls) if f.name not in order]
    for f in ordered:
        if f.name in skip:
            continue
        kwargs: dict[str, Any] = {
            "dest": prefix.replace("-", "_") + f.name,
            "default": f.default,
            "help": f.metadata.get("help", "").replace("%", "%%") + " (default: %(default)s)",
        }
        kind = str(f.type)
        if kind == "bool" or f.type is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        elif kind.startswith("tuple[int"):
            kwargs.update(type=int, nargs="+")
        else:
            kwargs["type"] = int if kind == "int" else float if "float" in kind else str
            kwargs["choices"] = choices.get(f.name, f.metadata.get("choices"))
        parser.add_argument(flag(f.name, prefix), **kwargs)


def config_from_namespace(cls: type, ns: dict[str, Any], prefix: str = "") -> Any:
    """An instance of ``cls`` from the parsed options of :func:`add_dataclass_options`."""
    values = {}
    for f in fields(cls):
        key = prefix.replace("-", "_") + f.name
        if key in ns:
            v = ns[key]
            values[f.name] = tuple(v) if isinstance(v, list) else v
    return cls(**values)


def check_config(cfg: Any, prefix: str = "") -> None:
    """Every declared constraint of ``cfg``'s fields; raises ValueError naming the flag."""
    for f in fields(cfg):
        value = getattr(cfg, f.name)
        allowed = f.metadata.get("choices")
        if allowed is not None and value not in allowed:
            raise ValueError(f"{flag(f.name, prefix)} must be one of {', '.join(allowed)}, "
                             f"got {value!r}")
        check = f.metadata.get("check")
        problem = check.problem(value) if check is not None else None
        if problem:
            raise ValueError(f"{flag(f.name, prefix)} {problem}")


def out_dir_problem(out: str | os.PathLike) -> str | None:
    """Why a run directory cannot be written at ``out``, or None; creates nothing."""
    path = Path(out).resolve()
    if path.exists() and not path.is_dir():
        return f"{path} exists and is not a directory"
    existing = path
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        return f"{existing} is not a writable directory"
    return None


def check_out_file(parser: argparse.ArgumentParser, out: Path, overwrite: bool,
                   kind: str) -> None:
    """An --out that names one file to write (``kind``: "the CSV file"), checked
    before anything runs: not a directory, in a writable directory, not an
    existing file unless ``overwrite``, not being written by another live
    process (its lock beside it); each refusal is one line, exit 2."""
    if out.is_dir():
        parser.error(f"--out {out}: is a directory (name {kind} to write)")
    problem = out_dir_problem(out.resolve().parent)
    if problem:
        parser.error(f"--out {out}: cannot write there ({problem})")
    if out.exists() and not overwrite:
        parser.error(f"--out {out}: exists (--overwrite replaces it)")
    try:
        check_free(out, beside=True)
    except InUse as e:
        parser.error(str(e))


def checked(convert: Callable[[str], Any], check: Check | None = None,
            nonempty: bool = False) -> Callable[[str], Any]:
    """An argparse ``type`` that converts an option's text and applies ``check``
    there, so the constraint sits next to the option's help text and argparse's
    one-line error names the flag (``argument --jobs: must be >= 1, got 0``).
    nonempty: refuse the empty string (paths, prefixes)."""
    kind = {int: "an integer", float: "a number"}.get(convert, "a value")  # type: ignore[arg-type]

    def parse(text: str) -> Any:
        if nonempty and not text.strip():
            raise argparse.ArgumentTypeError(f"must not be empty, got {text!r}")
        try:
            value = convert(text)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"must be {kind}, got {text!r}") from None
        problem = check.problem(value) if check is not None else None
        if problem:
            raise argparse.ArgumentTypeError(problem)
        return value

    parse.__name__ = getattr(convert, "__name__", "value")
    return parse
