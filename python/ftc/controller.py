"""``python -m ftc.controller``: the adaptive controller and the baselines
(:mod:`ftc.control.controller_cli`)."""

import sys

from ftc.control.controller_cli import main

if __name__ == "__main__":
    sys.exit(main())
