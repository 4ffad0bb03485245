"""The episode planner behind ``reference``: the value of a repeated episode by
hand, coordinate ascent finding a known optimum, on the true physics never
below the oracle's closed loop (and measurably above it), the plan followed
while the plant agrees with it and remade where it does not, refused rollouts
scored -inf and counted, and its options refused where they mean nothing."""

from __future__ import annotations

import csv
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from ftc import _core
from ftc.tools import mpc as mpc_cli
from ftc.control.planning.physics.episode_planner import EpisodePlanner, Repeated, repeat_scores, tail_scores
from ftc.control.planning.physics.true_physics import TruePhysics

FULL = np.ones(6)


def test_a_repeated_episode_is_worth_its_whole_returns_and_a_prefix():
    # an episode of 3 steps earning 1, 2, 3: 7 steps are two episodes and one step
    r = Repeated(np.array([0.0, 1.0, 3.0, 6.0]), 3)
    assert r.value(7) == 2 * 6 + 1 and r.value(3) == 6 and r.value(0) == 0
    assert list(r.value(np.array([1, 2, 6]))) == [1, 3, 12]
    endless = Repeated(np.array([0.0, 1.0, 3.0, 6.0]), None)  # never ended: no restart
    assert endless.value(2) == 3


class _WeightedSteps:
    """A physics with a known optimum: step t of a sequence earns w[t] . u[t]; an
    episode ends after ``length`` steps (None: never)."""

    def __init__(self, weights: np.ndarray, length: int | None) -> None:
        self.w, self.length, self.refused, self.simulated = weights, length, 0, 0

    def schedule(self, step0, length):
        return None, None, ("fixed",)

    def run(self, x0, sequences, step0, frozen):
        k, n, _ = sequences.shape
        rewards = (sequences * self.w[:n]).sum(-1).astype(float)
        terminal = np.zeros((k, n), bool)
        if self.length is not None:
            terminal[:, self.length - 1::self.length] = True
        return rewards, terminal, np.zeros((k, n, 6))


@pytest.mark.parametrize("seed", [0, 1])
def test_coordinate_ascent_finds_the_best_sequence_of_a_separable_reward(seed):
    w = np.random.default_rng(seed).normal(size=(12, 6))
    planner = EpisodePlanner(_WeightedSteps(w, None), sweeps=1)  # one sweep: separable
    score = tail_scores(planner.physics, FULL, 0, False, 12, None)
    seq, value = planner.ascend(score, np.zeros((12, 6), np.int64))
    best = (w > 0).astype(np.int64)  # each valve open exactly where its weight pays
    assert (seq == best).all()
    assert value == pytest.approx(w[w > 0].sum(), abs=1e-12)


def test_a_repeated_episode_is_scored_over_the_interval():
    w = np.random.default_rng(3).normal(size=(16, 6))
    planner = EpisodePlanner(_WeightedSteps(w, 4), sweeps=2)
    # 10 steps of a 4-step episode played again after each reset: 2 whole + 2 steps
    score = repeat_scores(planner.physics, 0, False, 10)
    seq, value = planner.ascend(score, np.zeros((8, 6), np.int64))
    gains = np.clip(w[:4], 0, None).sum(1)
    assert value == pytest.approx(2 * gains.sum() + gains[:2].sum(), abs=1e-12)
    assert (seq[:4] == (w[:4] > 0)).all()


@pytest.fixture(scope="module")
def single_128():
    scenario = _core.load_scenario("scenarios/single.toml")
    scenario.steps_per_interval = 128
    return scenario


def test_on_the_true_physics_the_plan_beats_the_oracles_closed_loop(single_128):
    """Age 6 of the single fault, 128-step intervals: measured 315.51 (the H3 hold
    planner closed-loop) against 325.21 (the plan), +3.1%; asserted at +1.5%, so
    a search that stopped improving on the oracle would fail."""
    physics = TruePhysics(single_128, 1e-6, 1e-8, True)
    planner = EpisodePlanner(physics)
    step0 = 6 * 128
    oracle = planner._closed_loop(FULL, step0, 128, False)
    planner._replan(FULL, step0, 128, False)
    totals = physics.run(FULL, np.stack([oracle, planner.plan]), step0, False)[0].sum(1)
    assert totals[1] >= totals[0] * 1.015
    assert planner.plan.shape == (128, 6) and physics.refused == 0


def test_the_plan_is_followed_while_the_plant_agrees_and_remade_where_it_does_not(single_128):
    physics = TruePhysics(single_128, 1e-6, 1e-8, True)
    planner = EpisodePlanner(physics, sweeps=1)
    step0, x = 3 * 128, FULL.copy()
    played = []
    for t in range(6):  # the plant doing exactly what the rollouts predict
        played.append(planner.decide(x, step0 + t, 128 - t, False, 128))
        x = planner.expected[planner.pos]
    assert planner.replans == 1 and (np.array(played) == planner.plan[:6]).all()
    planner.decide(x + 1e-3, step0 + 6, 122, False, 128)  # the plant elsewhere: replanned
    assert planner.replans == 2 and planner.pos == 1 and len(planner.plan) == 122
    planner.decide(FULL, step0, None, True, 128)  # an evaluation episode: its own plan
    assert planner.replans == 3 and planner.evaluation


def test_a_refused_rollout_scores_minus_infinity_and_is_counted(single_128):
    physics = TruePhysics(single_128, 1e-6, 1e-8, True)
    real = physics.rollout

    class Refusing:  # the integrator refusing every sequence that opens valve 6
        def run(self, x0, sequences, params, details=False):
            if (np.asarray(sequences)[..., 5] == 1).any():
                raise RuntimeError("StepIntegrator::Step: chattering")
            return real.run(x0, sequences, params, details=details)

    physics.rollout = Refusing()
    seqs = np.zeros((3, 4, 6), np.int64)
    seqs[1, 2, 5] = 1
    rewards, terminal, _ = physics.run(FULL, seqs, 0, False)
    assert np.isneginf(rewards[1]).all() and np.isfinite(rewards[[0, 2]]).all()
    assert physics.refused == 1 and not terminal[1].any()


def test_stuck_valves_are_applied_and_the_commanded_ones_charged():
    scenario = _core.load_scenario("scenarios/abrupt.toml")  # valve 4 stuck closed from 2816
    physics = TruePhysics(scenario, 1e-6, 1e-8, True)
    commanded = np.zeros((1, 3, 6), np.int64)
    commanded[0, :, 3] = 1  # valve 4 open: the plant keeps it closed
    closed = np.zeros((1, 3, 6), np.int64)
    r_cmd = physics.run(FULL, commanded, 2816, False)[0]
    r_closed = physics.run(FULL, closed, 2816, False)[0]
    # the same levels as all closed, and 1/6 less reward per step for the open command
    assert r_cmd == pytest.approx(r_closed - 1 / 6, abs=1e-12)
    before = physics.run(FULL, commanded, 2815 - 3, False)[0]  # before the event: it opens
    assert not np.allclose(before, r_closed[:, :3] - 1 / 6)


def _parse(args, tmp_path):
    return subprocess.run([sys.executable, "-m", "ftc.mpc", *args, "--scenario", "",
                           "--link", "core", "--intervals", "1", "--steps-per-interval", "8",
                           "--out", str(tmp_path / "o")], capture_output=True, text=True,
                          timeout=120)


@pytest.mark.parametrize("args, message", [
    (["--method", "model-mpc", "--planner", "episode"], "invalid choice: 'episode'"),
    (["--method", "oracle-mpc", "--episode-sweeps", "3"], "--episode-sweeps"),
])
def test_the_planners_options_are_refused_where_they_mean_nothing(args, message, tmp_path):
    proc = _parse(args, tmp_path)
    assert proc.returncode == 2 and message in proc.stderr, proc.stderr
    assert not (tmp_path / "o").exists()


def test_the_episode_planner_is_an_option_of_the_oracle_mpc(tmp_path):
    cfg = mpc_cli.parse_args(["--method", "oracle-mpc", "--planner", "episode",
                              "--episode-sweeps", "2", "--scenario", "", "--out",
                              str(tmp_path / "o")])
    assert (cfg.planner, cfg.episode_sweeps, cfg.episode_tolerance) == ("episode", 2, 1e-6)


def test_an_exhausted_budget_stops_the_search_and_keeps_the_oracles_plan(single_128):
    physics = TruePhysics(single_128, 1e-6, 1e-8, True)
    planner = EpisodePlanner(physics, budget=0)  # no search at all
    step0 = 6 * 128
    oracle = planner._closed_loop(FULL, step0, 128, False)
    spent = physics.simulated
    planner._replan(FULL, step0, 128, False)
    # the closed loop again, a few whole-plan rollouts, and no ascent (each ascent's
    # batches are 64 candidates or more)
    assert physics.simulated - spent < 2 * spent + 10 * 128
    totals = physics.run(FULL, np.stack([oracle, planner.plan]), step0, False)[0].sum(1)
    assert totals[1] >= totals[0]


def test_sensor_noise_widens_the_tolerance_by_six_standard_deviations(tmp_path):
    from ftc.control.agents.physics.mpc import MPCAgent

    noisy = tmp_path / "noisy.toml"
    noisy.write_text(open("scenarios/single.toml").read() + "\n[noise]\nstd = 0.005\n")
    cfg = mpc_cli.parse_args(["--method", "reference", "--scenario", str(noisy),
                              "--out", str(tmp_path / "o")])
    agent = MPCAgent(cfg)
    assert agent.episode.tolerance == pytest.approx(1e-6 + 6 * 0.005)


def test_the_plan_is_never_below_the_balance_rules_closed_loop():
    """random-05 of the default suite at age 3: the balance rule's closed loop earns
    more than the oracle's there (measured 2.6395 against 2.6191 a step); the
    reference, which searched from the oracle's loop alone, stayed at 2.6362."""
    from ftc.experiments.suite import default_suite

    scenario = next(s for s in default_suite() if s.name == "random-05")
    path = Path(tempfile.mkdtemp()) / "random-05.toml"
    path.write_text(scenario.toml(512))
    physics = TruePhysics(_core.load_scenario(str(path)), 1e-6, 1e-8, True)
    planner = EpisodePlanner(physics)
    step0 = 3 * 512
    rule = planner._rule_loop(FULL, step0, 512, False)
    planner._replan(FULL, step0, 512, False)
    totals = physics.run(FULL, np.stack([rule, planner.plan]), step0, False)[0].sum(1)
    assert totals[1] >= totals[0]


def test_on_the_real_plant_process_the_plan_is_followed_and_beats_the_oracle(tmp_path):
    """The plant process (CVODE at its own tolerances, over LCM) does what the
    closed-form rollouts predicted: one plan per interval and one for its
    evaluation episode, none remade; and the reward is at least the oracle's."""
    rewards = {}
    for method in ("reference", "oracle-mpc"):
        out = tmp_path / method
        proc = subprocess.run(
            [sys.executable, "-m", "ftc.mpc", "--method", method, "--scenario",
             "scenarios/multiple.toml", "--intervals", "3", "--steps-per-interval", "128",
             "--link", "lcm", "--out", str(out)], capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-2000:]
        with open(out / "metrics.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        rewards[method] = [float(r["reward_per_step"]) for r in rows]
        if method == "reference":
            assert [r["episode_plans"] for r in rows] == ["2", "2", "2"]
    assert all(r >= o for r, o in zip(rewards["reference"], rewards["oracle-mpc"]))
    assert sum(rewards["reference"][1:]) > sum(rewards["oracle-mpc"][1:])


def test_an_abrupt_fault_ahead_is_planned_episode_by_episode(tmp_path):
    """An event in the middle of the interval (engine 1 jumps to D = 5, valve 4
    sticks closed, as scenarios/abrupt.toml but at step 5 * 128 + 64): the episodes
    after it are not the first one again, so the plan is remade at each episode's
    end, each time never below the closed loops nor the rest of the plan played."""
    text = (Path("scenarios/abrupt.toml").read_text().replace("steps_per_interval = 512",
                                                              "steps_per_interval = 128")
            .replace("at_step = 2816", "at_step = 704"))
    path = tmp_path / "abrupt.toml"
    path.write_text(text)
    scenario = _core.load_scenario(str(path))
    physics = TruePhysics(scenario, 1e-6, 1e-8, True)
    planner = EpisodePlanner(physics)
    step0, x, played = 5 * 128, FULL.copy(), []
    for t in range(128):  # the plant doing what the rollouts predict
        played.append(planner.decide(x, step0 + t, 128 - t, False, 128))
        _, term, lev = physics.run(x, np.array(played[-1:])[None], step0 + t, False)
        x = FULL if term[0, 0] else lev[0, 0]
    assert planner.replans > 1
    loops = [planner._closed_loop(FULL, step0, 128, False),
             planner._rule_loop(FULL, step0, 128, False)]
    totals = physics.run(FULL, np.stack([np.array(played, np.int64), *loops]), step0,
                         False)[0].sum(1)
    assert totals[0] >= totals[1:].max()
