"""python -m ftc.experiments.adaptive: see ftc.experiments.adaptive.cli."""

import sys

from ftc.experiments.adaptive.cli import main

sys.exit(main())
