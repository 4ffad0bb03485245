"""Command-line options generated from typed config dataclasses: one option
per field, its help text from the field's ``metadata["help"]``, its type from
the annotation. Shared by ``ftc.controller`` and ``ftc.mpc``."""

from __future__ import annotations

import argparse
from dataclasses import fields
from typing import Any, Sequence


def add_dataclass_options(parser: Any, cls: type, prefix: str = "",
                          choices: dict[str, Sequence[str]] | None = None) -> None:
    """Add ``--<prefix><field-name>`` for every field of ``cls`` to ``parser``
    (an ArgumentParser or argument group); dest is ``<prefix>_<field_name>``
    with dashes as underscores. bool fields get --x/--no-x, ``tuple[int, ...]``
    fields take one or more ints, int and float (also optional float) fields
    are parsed as such, everything else as a string."""
    choices = choices or {}
    for f in fields(cls):
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
            kwargs["choices"] = choices.get(f.name)
        parser.add_argument("--" + prefix + f.name.replace("_", "-"), **kwargs)
