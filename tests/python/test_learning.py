"""Learning happened, asserted on what holds across seeds and CPUs.

On the paper's single fault, opening valves pays once engine E1 burns 15-25%
more than E2. The paper's controller (PPO online + offline, from scratch)
starts near random valves and must learn that: by interval 5 it beats keeping
every valve closed. Nominal pretraining must keep the healthy plant (interval
0) near its optimum, all-closed.

Which quantity to assert was chosen by measurement, because learning outcomes
move with the CPU: AMD and Intel run other BLAS kernels (OpenBLAS and MKL pick
them by vendor), the policies differ in the last bits, and then the runs
diverge. Besides real seeds, the "CPU" was varied on one Intel machine by
running the same seeds with ``OPENBLAS_CORETYPE=Zen MKL_ENABLE_INSTRUCTIONS=AVX2
ATEN_CPU_CAPABILITY=avx2`` (AMD's kernel paths), which changes the runs as an
AMD machine does. Margins are mean reward per step over all-closed:

* pretrained, intervals 3-5 (this test's old quantity): bimodal. Some seeds
  slide back to all-closed (-0.01 to -0.105 measured; -0.105 on an AMD EPYC),
  the others hold +0.13 to +0.37, and which seeds slide depends on the CPU.
  Under the Zen kernels seeds 0-2 gave 0.13, 0.02, -0.01, so the old bar
  (best seed > 0.15) failed on Intel hardware too. This is the method's seed
  noise (docs/controller.md, "Quality bar": std 0.17-0.25 over 20 seeds), not a
  property a three-seed test can pin down.
* from scratch, interval 5: unimodal. 0.14-0.41 over seeds 0-9 on both kernel
  paths (20 runs: mean 0.27, std 0.07; the quality bar's 20 Intel seeds:
  mean 0.246, std 0.070), and the gain over its own interval 0 is 0.03-0.34
  (mean 0.19). A controller that does not learn stays at random valves: -0.04
  over all-closed in interval 5, and 0.11 below its interval 0. Bars: every
  seed above all-closed (about 3.5 std below the mean), the mean of three
  seeds above 0.1 (about 4 std of a three-seed mean), and a positive mean gain.
* pretrained, interval 0 over all-closed: 0.967-0.991 per seed on both paths
  of the Intel machine, but 0.898-0.990 over seeds 0-19 on an AMD EPYC (mean
  0.970, std 0.022; seed 2 0.898, seed 9 0.925), where the mean of seeds 0-2
  is 0.946 and 7 % of three-seed subsets fall below the quality bar's 0.95
  (a bar for a 20-seed mean, scripts/quality_controller.py). A controller that is
  not pretrained earns 0.687-0.709 there (seeds 0-5, AMD). Bars: every seed
  above 0.85 (2.2 std of the pretrained seeds below their worst, 0.14 above
  the untrained's best) and the mean above 0.90 (the worst three-seed mean
  of the 20 AMD seeds: 0.927).
"""

from __future__ import annotations

import csv
from pathlib import Path

from forked_tools import run_tool

REPO = Path(__file__).resolve().parents[2]
SEEDS = (0, 1, 2)


def _rewards(args: list[str], out: Path) -> list[float]:
    # forked, not started afresh: the same run bit for bit (test_fork_server.py)
    done = run_tool("ftc.controller", [*args, "--out", str(out), "--quiet"], REPO, timeout=1800)
    assert done.returncode == 0, done.stderr[-3000:]
    with open(out / "metrics.csv") as f:
        return [float(r["reward_per_step"]) for r in csv.DictReader(f)]


def _single(scenarios: Path, intervals: int) -> list[str]:
    return ["--scenario", str(scenarios / "single.toml"), "--intervals", str(intervals),
            "--link", "core"]


def test_the_papers_ppo_learns_to_beat_all_closed_once_opening_pays(tmp_path, scenarios):
    common = _single(scenarios, 6)
    # all-closed does not depend on the seed on this scenario (no noise): one run
    closed = _rewards([*common, "--method", "closed"], tmp_path / "closed")
    margins, gains = [], []
    for seed in SEEDS:
        ppo = _rewards([*common, "--seed", str(seed), "--method", "ppo"], tmp_path / f"ppo{seed}")
        margins.append(ppo[5] - closed[5])
        gains.append(ppo[5] - ppo[0])  # it got better while the plant got worse
    assert min(margins) > 0 and sum(margins) / len(margins) > 0.1, margins
    assert closed[5] < closed[0] and sum(gains) / len(gains) > 0, (gains, closed)


def test_pretraining_keeps_the_healthy_plant_near_its_optimum(tmp_path, scenarios):
    common = _single(scenarios, 1)
    closed = _rewards([*common, "--method", "closed"], tmp_path / "closed")
    healthy = []
    for seed in SEEDS:
        ppo = _rewards([*common, "--seed", str(seed), "--method", "ppo", "--pretrain",
                        "--pretrain-cache", str(tmp_path / "cache")], tmp_path / f"ppo{seed}")
        healthy.append(ppo[0] / closed[0])
    assert min(healthy) > 0.85 and sum(healthy) / len(healthy) > 0.90, healthy
