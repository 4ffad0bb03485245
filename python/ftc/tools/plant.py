"""``ftc-plant``: the plant process, the C++ program built with the package
(its options: ``ftc-plant --help``; a checkout runs it as ``./build/plant``).
``--scenario`` also takes a packaged scenario's name (``single``, ...)."""

from __future__ import annotations

import os
import sys
from typing import Sequence

from ftc.common.build_info import BuildMissingError, plant_binary
from ftc.common.paths import scenario_file


def with_scenario_files(args: list[str]) -> list[str]:
    """``args`` with the value of ``--scenario NAME`` (or ``--scenario=NAME``)
    made the packaged scenario's file; ValueError for an unknown name."""
    out = list(args)
    for i, word in enumerate(out):
        if word == "--scenario" and i + 1 < len(out):
            out[i + 1] = scenario_file(out[i + 1])
        elif word.startswith("--scenario="):
            out[i] = "--scenario=" + scenario_file(word.split("=", 1)[1])
    return out


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        path = plant_binary()
        args = with_scenario_files(args)
    except (BuildMissingError, ValueError) as e:
        print(f"ftc-plant: {'--scenario: ' if isinstance(e, ValueError) else ''}{e}",
              file=sys.stderr)
        return 2
    os.execv(path, [str(path), *args])  # the plant's own exit code and signals
    return 0  # not reached


if __name__ == "__main__":
    sys.exit(main())
