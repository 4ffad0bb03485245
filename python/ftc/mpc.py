"""``python -m ftc.mpc``: the MPC reference controllers (:mod:`ftc.tools.mpc`)."""

import sys

# parse_args: ftc.experiments checks its runs' command lines with it
from ftc.tools.mpc import main, parse_args  # noqa: F401

if __name__ == "__main__":
    sys.exit(main())
