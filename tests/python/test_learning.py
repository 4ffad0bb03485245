"""Learning happened (Reliability item 7): on the paper's single fault, where
opening valves pays once engine E1 burns 15-25% more than E2, the paper's
controller (PPO online + offline, with nominal pretraining) beats keeping
every valve closed by a clear margin, seed fixed.

Measured (docs/controller.md, 5 seeds, seed 0 alike): intervals 3-5 earn
2.27, 2.25, 2.26 per step against all-closed's 2.06, 1.92, 1.80, a margin of
0.33 on the mean; the test asks for 0.15, so a controller that stopped
learning (it would track all-closed, or fall below it) fails it.
"""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _rewards(args: list[str], out: Path) -> list[float]:
    subprocess.run([sys.executable, "-m", "ftc.controller", *args, "--out", str(out), "--quiet"],
                   cwd=REPO, check=True, timeout=1800)
    with open(out / "metrics.csv") as f:
        return [float(r["reward_per_step"]) for r in csv.DictReader(f)]


def test_ppo_online_offline_beats_all_closed_once_opening_pays(tmp_path, scenarios):
    common = ["--scenario", str(scenarios / "single.toml"), "--intervals", "6", "--seed", "0",
              "--link", "core"]
    closed = _rewards([*common, "--method", "closed"], tmp_path / "closed")
    ppo = _rewards([*common, "--method", "ppo", "--pretrain", "--pretrain-cache",
                    str(tmp_path / "cache")], tmp_path / "ppo")
    late = slice(3, 6)
    margin = sum(ppo[late]) / 3 - sum(closed[late]) / 3
    assert margin > 0.15, (ppo, closed)
    assert ppo[0] > 0.96 * closed[0]  # pretraining kept it near the healthy optimum
