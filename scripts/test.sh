#!/usr/bin/env bash
# Runs every test: sets up what a fresh clone lacks (idempotent, quick when
# done), then the C++ suite (ctest) and the Python suite (pytest).
# Extra arguments go to pytest (e.g. -k physics, -m slow; --quick: the fast tier,
# tests/python/conftest.py).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
bash scripts/setup.sh
status=0
(cd build && ctest --output-on-failure -j2) || status=$?
# Two workers (pytest-xdist), a test file per worker at a time: the module
# fixtures (a benchmark, an experiment) run once, and a subprocess-heavy file
# waits on its plant while the other worker computes.
.venv/bin/python -m pytest -q --durations=20 -n 2 --dist loadfile "$@" || status=$?
exit $status
