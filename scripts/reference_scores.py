#!/usr/bin/env python3
"""Write a reference-scores file (ftc.experiments.reference_scores) from
finished benchmark directories that ran ``reference`` and ``closed`` (scenarios
without every seed of both are left out):

    .venv/bin/python scripts/reference_scores.py runs/suite-ref [runs/other ...] \\
        --out scenarios/reference/suite.json

Run it with the code that ran the benchmark: the file is keyed by this
checkout's code (the digests a later benchmark --reference-scores compares).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "python"))

from ftc.experiments import reference_scores  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dirs", type=Path, nargs="+", help="finished benchmark directories")
    p.add_argument("--out", type=Path, required=True, help="the file to write")
    args = p.parse_args(argv)
    try:
        data = reference_scores.from_benchmarks(args.dirs, args.out)
    except (OSError, KeyError, ValueError) as e:
        raise SystemExit(f"reference_scores: {e}")
    print(f"reference_scores: {len(data['scenarios'])} scenarios -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
