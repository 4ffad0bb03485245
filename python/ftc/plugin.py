"""``python -m ftc.plugin``: a controller from outside the package
(:mod:`ftc.tools.plugin`)."""

import sys

# parse_args: ftc.experiments checks its runs' command lines with it
from ftc.tools.plugin import main, parse_args  # noqa: F401

if __name__ == "__main__":
    sys.exit(main())
