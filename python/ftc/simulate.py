"""``python -m ftc.simulate``: kept for the command line; the tool is :mod:`ftc.tools.simulate`."""

import sys

from ftc.tools.simulate import main

if __name__ == "__main__":
    sys.exit(main())
