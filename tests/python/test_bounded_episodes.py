"""Every episode kind has an explicit bound (Reliability: a dead pump).

A tank whose pump dies strands its fuel: with its valve closed the volume
never falls to one step of demand, so an episode under a policy that keeps
that valve closed never reaches the termination rule. Operating episodes are
cut by the plant at the interval boundary; the evaluation episode is cut by
the runner after steps_per_interval steps (reported as eval_steps); model
rollouts by ModelEnv's max_episode_steps; MPC planning by its horizon.
"""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np

from ftc.control.agents.baselines import BaselineAgent
from ftc.control.agents.ppo import ControllerConfig
from ftc.control.run.runner import IntervalRunner
from ftc.plant import CorePlant

REPO = Path(__file__).resolve().parents[2]
STEPS = 64
# tank 4's pump (and valve) degrade with D_T = 1: its pump is dead from interval 1 on
DEAD_PUMP = """name = "dead-pump"
tank_factor = [inf, inf, inf, 1.0, inf, inf]
engine_factor = [inf, inf]
degradation = "stepwise"
steps_per_interval = 512
"""


def _scenario(tmp_path: Path) -> Path:
    path = tmp_path / "dead-pump.toml"
    path.write_text(DEAD_PUMP)
    return path


class ClosedAndEvaluated(BaselineAgent):
    """All valves closed, with an evaluation episode (a policy that learned to
    keep every valve closed: the pretrained PPO's deterministic policy)."""

    evaluates = True


def test_a_closed_policy_on_a_dead_pump_never_terminates_without_the_bound(tmp_path):
    # the premise: 10 x STEPS evaluation steps at age 1 and the episode is still running
    plant = CorePlant(str(_scenario(tmp_path)), 0, steps_per_interval=STEPS, start_step=STEPS)
    closed = np.zeros(6, np.int8)
    plant.reset()
    plant.step(closed)  # one operating step at age 1: evaluation freezes this age
    o = plant.evaluate()
    assert o.age == 1.0
    for _ in range(10 * STEPS):
        o = plant.step(closed)
        assert not o.done
    assert o.level[3] > 0.5  # tank 4's fuel is stranded (its pump gives nothing)


def test_the_evaluation_episode_is_cut_at_steps_per_interval(tmp_path):
    cfg = ControllerConfig(scenario=str(_scenario(tmp_path)), out=str(tmp_path / "run"),
                           intervals=3, steps_per_interval=STEPS, link="core", quiet=True)
    rows = IntervalRunner(cfg, ClosedAndEvaluated("closed", 0), {"controller": cfg}).run()
    assert [r["eval_steps"] for r in rows[1:]] == [STEPS, STEPS]  # cut, not hung
    assert rows[0]["eval_steps"] == 59  # healthy at age 0: the nominal 59-step episode
    assert all(np.isfinite(r["eval_reward_per_step"]) for r in rows)
    with open(tmp_path / "run" / "metrics.csv") as f:
        assert [row["eval_steps"] for row in csv.DictReader(f)] == ["59", str(STEPS), str(STEPS)]


def _run(args: list[str], out: Path) -> list[dict[str, str]]:
    proc = subprocess.run([sys.executable, "-m", *args, "--out", str(out), "--quiet"], cwd=REPO,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    with open(out / "metrics.csv") as f:
        return list(csv.DictReader(f))


SHORT = ["--intervals", "3", "--steps-per-interval", "128", "--seed", "1"]


def test_controller_and_both_mpcs_finish_on_a_dead_pump(tmp_path):
    scenario = ["--scenario", str(_scenario(tmp_path))]
    runs = {
        "ppo": ["ftc.controller", "--method", "ppo", "--update-every", "64", "--offline-steps",
                "256", "--model-episodes", "5", "--link", "lcm"],
        "oracle": ["ftc.mpc", "--method", "oracle-mpc", "--link", "core"],
        "model": ["ftc.mpc", "--method", "model-mpc", "--model-episodes", "5", "--link", "core"],
    }
    for name, args in runs.items():
        rows = _run([*args, *SHORT, *scenario], tmp_path / name)
        assert len(rows) == 3, name
        assert all(1 <= int(r["eval_steps"]) <= 128 for r in rows), name


def test_the_experiments_finish_on_a_dead_pump(tmp_path):
    """The benchmark (the experiments' machinery) runs a dead-pump scenario to the
    end with a baseline, a rule that evaluates, and the oracle MPC."""
    out = tmp_path / "bench"
    proc = subprocess.run(
        [sys.executable, "-m", "ftc.experiments", "benchmark", "--scenarios",
         str(_scenario(tmp_path)), "--methods", "closed", "balance", "--seeds", "0",
         "--intervals", "3", "--steps-per-interval", "64", "--jobs", "2",
         "--reference", "oracle-mpc", "--out", str(out)],
        cwd=REPO, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    with open(out / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert {r["method"] for r in rows} == {"closed", "balance", "oracle-mpc"}
    assert len(rows) == 9 and all(r["scenario"] == "dead-pump" for r in rows)
    evaluated = [r for r in rows if r["method"] != "closed"]
    assert all(1 <= int(r["eval_steps"]) <= 64 for r in evaluated)
