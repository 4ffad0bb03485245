"""``python -m ftc.experiments``: see :mod:`ftc.experiments.cli`."""

import sys

from ftc.experiments.cli import main

sys.exit(main())
