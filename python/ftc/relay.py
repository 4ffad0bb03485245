"""``python -m ftc.relay``: kept for the command line; the tool is :mod:`ftc.tools.relay`."""

import sys

from ftc.tools.relay import main

if __name__ == "__main__":
    sys.exit(main())
