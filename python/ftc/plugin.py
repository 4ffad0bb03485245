"""``python -m ftc.plugin``: a controller from outside the package
(:mod:`ftc.control.plugin_cli`)."""

import sys

from ftc.control.plugin_cli import main

if __name__ == "__main__":
    sys.exit(main())
