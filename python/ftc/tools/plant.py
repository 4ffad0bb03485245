"""``ftc-plant``: the plant process, the C++ program built with the package
(its options: ``ftc-plant --help``; a checkout runs it as ``./build/plant``)."""

from __future__ import annotations

import os
import sys
from typing import Sequence

from ftc.common.build_info import BuildMissingError, plant_binary


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        path = plant_binary()
    except BuildMissingError as e:
        print(f"ftc-plant: {e}", file=sys.stderr)
        return 2
    os.execv(path, [str(path), *args])  # the plant's own exit code and signals
    return 0  # not reached


if __name__ == "__main__":
    sys.exit(main())
