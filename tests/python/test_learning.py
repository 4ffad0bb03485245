"""Learning happened: on the paper's single fault, where opening valves pays
once engine E1 burns 15-25% more than E2, the paper's controller (PPO online
+ offline, with nominal pretraining) beats keeping every valve closed by a
clear margin.

Measured (docs/controller.md, "Quality bar": 20 seeds, this test's
settings): intervals 3-5 earn 0.23 per step more than all-closed on the mean
over seeds, but 4 of the 20 seeds slide back to the all-closed level (margins
-0.03 to -0.05), and which seeds do depends on the CPU type (the pretrained
policies differ in the last bits). So the test runs seeds 0-2 and asks that
none falls clearly below all-closed (margin > -0.1) and that the best beats it
by 0.15: a controller that stopped learning (tracking all-closed, or below it)
fails, whichever seeds slide on this machine.
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
    common = ["--scenario", str(scenarios / "single.toml"), "--intervals", "6", "--link", "core"]
    late = slice(3, 6)
    margins, healthy = [], []
    for seed in (0, 1, 2):
        seeded = [*common, "--seed", str(seed)]
        closed = _rewards([*seeded, "--method", "closed"], tmp_path / f"closed{seed}")
        ppo = _rewards([*seeded, "--method", "ppo", "--pretrain", "--pretrain-cache",
                        str(tmp_path / "cache")], tmp_path / f"ppo{seed}")
        margins.append(sum(ppo[late]) / 3 - sum(closed[late]) / 3)
        healthy.append(ppo[0] / closed[0])
    assert max(margins) > 0.15 and min(margins) > -0.1, margins
    # interval 0: pretraining kept it near the healthy optimum (the quality bar's (a))
    assert sum(healthy) / 3 > 0.95, healthy
