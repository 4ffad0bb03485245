"""``python -m ftc.replay``: kept for the command line; the tool is :mod:`ftc.tools.replay`."""

import sys

from ftc.tools.replay import main

if __name__ == "__main__":
    sys.exit(main())
