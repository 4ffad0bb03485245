"""``python -m ftc.export``: kept for the command line; the tool is :mod:`ftc.tools.export`."""

import sys

from ftc.tools.export import main

if __name__ == "__main__":
    sys.exit(main())
