"""The architecture refactor changed no result: six reference commands
(scenarios/single.toml, seed 0, 3 intervals) give the metrics saved before it
(tests/data/same_results/*.csv, written by the pre-refactor controller and
MPC), in every column except those that measure time.

The saved files came from the LCM link and equal the in-process link's
(checked when they were saved), so the in-process link is used here for speed.
The comparison is on metrics.csv's 6-significant-digit text: any change of
arithmetic (an RNG draw moved, an update reordered) changes some digit of the
rewards, losses or R^2 over 3 x 512 steps.
"""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

from ftc.control.metrics import TIMING_COLUMNS

REPO = Path(__file__).resolve().parents[2]
SAVED = REPO / "tests" / "data" / "same_results"
COMMON = ["--scenario", "scenarios/single.toml", "--seed", "0", "--intervals", "3",
          "--link", "core", "--quiet"]
COMMANDS = {
    "closed": ["ftc.controller", "--method", "closed"],
    "random": ["ftc.controller", "--method", "random"],
    "ppo-offline": ["ftc.controller", "--method", "ppo"],
    "ppo-offline-pretrain": ["ftc.controller", "--method", "ppo", "--pretrain",
                             "--pretrain-cache", ""],
    "oracle-mpc": ["ftc.mpc", "--method", "oracle"],
    "model-mpc": ["ftc.mpc", "--method", "model"],
}


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.parametrize("name", list(COMMANDS))
def test_same_metrics_as_before_the_refactor(name, tmp_path):
    out = tmp_path / name
    module, *args = COMMANDS[name]
    proc = subprocess.run([sys.executable, "-m", module, *args, *COMMON, "--out", str(out)],
                          cwd=REPO, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr
    saved, now = _rows(SAVED / f"{name}.csv"), _rows(out / "metrics.csv")
    assert len(now) == len(saved) == 3
    compared = 0
    for k, (before, after) in enumerate(zip(saved, now)):
        for column, value in before.items():
            if column in TIMING_COLUMNS:
                continue
            assert after.get(column) == value, f"interval {k}, {column}"
            compared += value != ""
    assert compared >= 3 * 3  # at least interval, reward and episodes in every row
