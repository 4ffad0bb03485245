"""Shared fixtures: paths, and skipping nothing: the build must exist
(scripts/test.sh builds it first)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCENARIOS = REPO / "scenarios"
sys.path.insert(0, str(Path(__file__).resolve().parent))  # reference_sim for the tests


@pytest.fixture
def repo() -> Path:
    return REPO


@pytest.fixture
def scenarios() -> Path:
    return SCENARIOS
