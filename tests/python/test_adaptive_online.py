"""adaptive-policy's online fine-tune (--fine-tune; docs/adaptive.md, "Online
adaptation"): the fine-tune moves the student toward the labels it is given and
nowhere else, the labels are the learned model's best setting only where it beats
the student's choice by the margin, the batched rating is the planner's
evaluator state by state, and the method with the option runs on the real plant."""

from __future__ import annotations

import copy
import dataclasses
import json

import numpy as np
import pytest
import torch

from ftc.control.agents.learned.adaptive_policy import AdaptiveConfig, AdaptivePolicyAgent
from ftc.control.agents.learned.learned_mpc import LearnedEvaluator
from ftc.control.agents.learned.online_tune import (corrected_labels, fine_tune,
                                                     likeliest_only, rate_settings,
                                                     setting_codes, setting_log_probs)
from ftc.control.planning.planners import hold_candidates
from ftc.control.run.agent import StepContext, Transition
from ftc.learning.feature_model import FeatureModel
from ftc.learning.history_policy import HistoryPolicy, StudentConfig
from ftc.plant.link import PlantObservation
from ftc.tools import controller

TARGET = 37  # valves 0, 2 and 5 open


def _codes(policy: HistoryPolicy, x: np.ndarray) -> np.ndarray:
    return setting_codes(policy.act(x))


def test_the_fine_tune_moves_the_student_toward_its_label_and_not_elsewhere(one_torch_thread):
    """States with x0 > 0.5 are labelled 37, every other its own choice: after
    the fine-tune the first pick 37 and the others keep their choice. Before,
    37 is rare (a random network spreads its choices over the 64 settings)."""
    torch.manual_seed(0)
    policy = HistoryPolicy(StudentConfig(window=1, hidden=(64, 64), head="joint"))
    x = np.random.default_rng(0).uniform(-1, 1, (600, 12)).astype(np.float32)
    own = _codes(policy, x)
    moved = x[:, 0] > 0.5
    labels = np.where(moved, TARGET, own)
    assert np.mean(own[moved] == TARGET) < 0.2 and len(set(own[~moved])) > 3
    fine_tune(policy, x, labels, lr=3e-3, epochs=40, batch=64, seed=0)
    after = _codes(policy, x)
    # the thresholds leave room for the states near the boundary x0 = 0.5 and for
    # other float rounding (BLAS kernels); a fine-tune that did nothing scores < 0.2
    # on the first, one that moved everything to 37 scores < 0.5 on the second
    assert np.mean(after[moved] == TARGET) > 0.9
    assert np.mean(after[~moved] == own[~moved]) > 0.9
    assert np.mean(after[~moved] == TARGET) <= np.mean(own[~moved] == TARGET) + 0.02


def test_the_valves_head_is_fine_tuned_on_the_labels_bits(one_torch_thread):
    torch.manual_seed(1)
    policy = HistoryPolicy(StudentConfig(window=1, hidden=(64, 64), head="valves"))
    before = copy.deepcopy(policy)
    x = np.random.default_rng(1).uniform(-1, 1, (400, 12)).astype(np.float32)
    own = _codes(policy, x)
    moved = x[:, 1] < -0.5
    labels = np.where(moved, TARGET, own)
    fine_tune(policy, x, labels, lr=3e-3, epochs=40, batch=64, seed=0)
    after = _codes(policy, x)
    assert np.mean(after[moved] == TARGET) > 0.9
    # each valve's logit is fitted on its own: its bit kept where the label is the own choice
    assert np.mean(policy.act(x[~moved]) == before.act(x[~moved])) > 0.95


def test_a_label_is_the_best_setting_only_where_it_beats_the_choice_by_the_margin():
    totals = np.zeros((3, 64))
    totals[0, 5], totals[1, 9], totals[2, 9], totals[2, 11] = 1.0, 0.4, 2.0, 2.0
    chosen = np.array([3, 3, 11])
    labels, corrected = corrected_labels(totals, chosen, margin=0.5)
    # state 0: 5 beats 3 by 1.0 > 0.5; state 1: 9 beats it by 0.4 only;
    # state 2: the choice ties the best (the first maximum, 9, gains 0)
    assert labels.tolist() == [5, 3, 11] and corrected.tolist() == [True, False, False]


def test_the_batched_rating_is_the_planners_evaluator_state_by_state():
    model = FeatureModel(64, seed=0)
    rng = np.random.default_rng(0)
    level = rng.uniform(0.2, 1.0, (300, 6))
    valves = rng.integers(0, 2, (300, 6))
    model.fit(level, valves, np.clip(level - 0.01 + 0.02 * valves * (level < 0.6), 0, 1))
    evaluate = LearnedEvaluator(model, demand=0.05, band=0.005, stuck={2: 1})
    starts = rng.uniform(0.1, 1.0, (70, 6))  # more than one batch of 64 states
    batched = rate_settings(evaluate, starts, hold=3, horizon=10)
    one_by_one = np.array([evaluate(x, hold_candidates(3, 10)) for x in starts])
    # the same arithmetic on the same rows (a row's features do not depend on the others)
    np.testing.assert_allclose(batched, one_by_one, rtol=0, atol=1e-9)
    assert np.ptp(batched, axis=1).min() > 0  # the settings are told apart


def test_the_method_with_the_fine_tune_runs_on_the_real_plant(tmp_path, one_torch_thread):
    """Two short intervals on the real plant (--link core): after interval 0 the
    learned model corrected some of the student's choices (margin 0) and the
    student the run saved is not the checkpoint's; interval 1 ran on it."""
    torch.manual_seed(3)
    policy = HistoryPolicy(StudentConfig(window=4, hidden=(16,), head="joint"))
    path = tmp_path / "student.pt"
    torch.save({"policy": policy.record()}, path)
    out = tmp_path / "run"
    # the command's own main, in this process (the plant in process too: --link core)
    assert controller.main(["--method", "adaptive-policy", "--checkpoint", str(path),
                            "--link", "core", "--intervals", "2", "--steps-per-interval", "64",
                            "--fine-tune", "--fine-tune-margin", "0", "--fine-tune-epochs", "20",
                            "--fine-tune-lr", "0.01", "--out", str(out), "--quiet"]) == 0
    lines = (out / "metrics.csv").read_text().splitlines()
    rows = [dict(zip(lines[0].split(","), ln.split(","))) for ln in lines[1:]]
    assert [int(r["interval"]) for r in rows] == [0, 1]
    assert int(rows[0]["fine_tune_states"]) == 64 and int(rows[0]["fine_tune_corrected"]) > 0
    state = torch.load(out / "checkpoint.pt", weights_only=True)["agent"]
    tuned = HistoryPolicy.from_record(state["student"])
    memory = {k: state["fine_tune"][f"memory_{k}"].numpy()[:64] for k in "xyc"}
    x, labels = memory["x"][memory["c"]], memory["y"][memory["c"]]
    # interval 0's states (the oldest 64 of the memory), on which the checkpoint's student
    # acted: the corrected labels differ from its choices by construction; the student
    # tuned on them (and on interval 1's) picks most of them
    assert len(x) and np.mean(_codes(policy, x) == labels) == 0
    assert np.mean(_codes(tuned, x) == labels) > 0.5
    assert json.loads((out / "config.json").read_text())["controller"]["fine_tune"] is True


def test_a_fine_tune_option_without_the_fine_tune_is_refused(capsys):
    with pytest.raises(SystemExit) as e:
        controller.parse_args(["--method", "adaptive-policy", "--fine-tune-margin", "1", "--out", "x"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "--fine-tune-margin has no effect" in err[0]


def _step(level: np.ndarray, valves: np.ndarray, nxt: np.ndarray, step: int) -> Transition:
    now, then = _obs(level, step, valves), _obs(nxt, step + 1, valves)
    return Transition(obs=now, valves=valves, reward=0.0, next_obs=then, following=then)


def _obs(level: np.ndarray, step: int, valves: np.ndarray | None = None) -> PlantObservation:
    fields = {f.name: 0 for f in dataclasses.fields(PlantObservation)}
    fields.update(level=np.asarray(level, np.float64), terminal=False, truncated=False,
                  operating_steps=step, valves=np.zeros(6, np.int8) if valves is None else valves,
                  deficit=np.zeros(2))
    return PlantObservation(**fields)


def test_on_a_real_time_plant_the_fine_tune_runs_off_the_loop_and_is_swapped_in(
        tmp_path, one_torch_thread):
    """background_learning (a real-time plant): end_interval returns at once,
    the checkpoint's student acts while the job runs, and the tuned one acts
    after it is taken between two steps; its metrics arrive late, the runner
    told through on_learned."""
    torch.manual_seed(3)
    policy = HistoryPolicy(StudentConfig(window=2, hidden=(16,), head="joint"))
    path = tmp_path / "student.pt"
    torch.save({"policy": policy.record()}, path)
    agent = AdaptivePolicyAgent(AdaptiveConfig(
        checkpoint=str(path), fine_tune=True, fine_tune_margin=0.0, fine_tune_lr=0.01,
        fine_tune_epochs=20, fine_tune_memory=64))
    agent.background_learning = True
    learned = []
    agent.on_learned = learned.append
    agent.prepare()
    rng = np.random.default_rng(0)
    level = np.full(6, 0.9)
    agent.start_episode(_obs(level, 0))
    for t in range(48):
        u = agent.act(_obs(level, t), StepContext(0, t, 48 - t))
        nxt = np.clip(level - rng.uniform(0.0, 0.01, 6), 0, 1)
        agent.observe(_step(level, u, nxt, t))
        level = nxt
    acting = agent.policy
    assert agent.end_interval(0, None) == {} and agent.learning
    assert agent.policy is acting  # the checkpoint's student acts until the job is taken
    agent.finish()  # waits for the job, swaps the student in
    assert not agent.learning and learned == [0] and agent.policy is not acting
    ((interval, metrics),) = agent.late_metrics()
    assert interval == 0 and metrics["fine_tune_states"] == 48
    assert metrics["fine_tune_corrected"] > 0
    corrected = agent.teacher.memory_c
    x, labels = agent.teacher.memory_x[corrected], agent.teacher.memory_y[corrected]
    assert np.mean(_codes(acting, x) == labels) == 0
    assert np.mean(_codes(agent.policy, x) == labels) > 0.5
    # a resumed run continues with the tuned student, the learned model and the memory
    again = AdaptivePolicyAgent(agent.cfg)
    again.load_state_dict(agent.state_dict())
    assert np.array_equal(_codes(again.policy, x), _codes(agent.policy, x))
    assert np.array_equal(again.teacher.memory_y, agent.teacher.memory_y)
    assert np.array_equal(again.teacher.model.weights, agent.teacher.model.weights)
    agent.close()


def test_the_model_arbitrates_only_between_the_students_likeliest_settings():
    totals = np.zeros((2, 64))
    totals[:, 63] = 10.0  # the model's favourite, which the student finds unlikely
    totals[:, 6] = 1.0
    log_probs = np.full((2, 64), -20.0)
    log_probs[:, 6], log_probs[:, 9] = -0.5, -1.0  # the student: 6, then 9
    chosen = np.array([20, 6])  # state 0 acted on a setting it finds unlikely: still kept
    kept = likeliest_only(totals, log_probs, chosen, k=2)
    assert np.isfinite(kept).sum(axis=1).tolist() == [2, 2]
    assert kept[0, 20] == 0 and kept[0, 6] == 1.0 and kept[1, 9] == 0 and kept[1, 6] == 1.0
    labels, corrected = corrected_labels(kept, chosen, margin=0.5)
    assert labels.tolist() == [6, 6] and corrected.tolist() == [True, False]


def test_the_students_setting_probabilities_are_its_heads():
    torch.manual_seed(0)
    x = np.random.default_rng(0).uniform(-1, 1, (5, 12)).astype(np.float32)
    joint = HistoryPolicy(StudentConfig(window=1, hidden=(8,), head="joint"))
    np.testing.assert_allclose(setting_log_probs(joint, x), torch.log_softmax(
        joint(torch.as_tensor(x)), 1).detach().numpy(), atol=1e-6)
    valves = HistoryPolicy(StudentConfig(window=1, hidden=(8,), head="valves"))
    p_open = torch.sigmoid(valves(torch.as_tensor(x))).detach().numpy().astype(np.float64)
    code = 37  # valves 0, 2, 5 open, the others closed
    bits = (code >> np.arange(6)) & 1
    expected = np.log(np.where(bits, p_open, 1 - p_open)).sum(axis=1)
    np.testing.assert_allclose(setting_log_probs(valves, x)[:, code], expected, atol=1e-5)
    # each row a distribution over the 64 settings
    np.testing.assert_allclose(np.exp(setting_log_probs(valves, x)).sum(1), 1.0, atol=1e-5)
