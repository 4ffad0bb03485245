"""``python -m ftc.controller``: the adaptive controller and the baselines
(:mod:`ftc.tools.controller`)."""

import sys

# parse_args: ftc.experiments checks its runs' command lines with it
from ftc.tools.controller import main, parse_args  # noqa: F401

if __name__ == "__main__":
    sys.exit(main())
