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
# Three workers (pytest-xdist) on the two cores, a test file per worker at a
# time: the module fixtures (a benchmark, an experiment) run once, and while a
# file waits on a real-time plant or a subprocess, the other two compute.
.venv/bin/python -m pytest -q --durations=20 -n 3 --dist loadfile "$@" || status=$?
exit $status
