"""``learned-mpc``: the online feature model on cases with known answers, its
planner's rollouts, and the controller on the real plant process over LCM."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from ftc.common.errors import CheckpointError
from ftc.control.agents.learned.learned_mpc import LearnedEvaluator, LearnedMPCAgent
from ftc.tools.mpc import main
from ftc.control.agents.learned.learned_mpc import LearnedMPCConfig
from ftc.control.planning.planners import hold_candidates
from ftc.learning.feature_model import FeatureModel
from ftc.plant import CorePlant
from ftc.plant.reward import reward


def _rows(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.uniform(0, 1, (n, 6)), rng.integers(0, 2, (n, 6))


def _linear(level: np.ndarray, valves: np.ndarray, gain: float) -> np.ndarray:
    """A plant in the model's span: each level falls by gain x its own level,
    and valve i's opening moves 0.01 m from tank i to tank 7 - i."""
    change = -gain * level + 0.01 * (valves[..., ::-1] - valves)
    return level + change


def test_a_function_in_the_span_of_the_features_is_fitted_exactly():
    level, valves = _rows(2000)
    model = FeatureModel(features=32, ridge=1e-9)
    model.fit(level, valves, _linear(level, valves, 0.02))
    test_level, test_valves = _rows(200, seed=1)
    # a least-squares fit of a linear target on features that include the inputs:
    # only rounding remains (1e-9 m is 7 orders below a step's change)
    assert np.abs(model.predict(test_level, test_valves)
                  - np.clip(_linear(test_level, test_valves, 0.02), 0, 1)).max() < 1e-9


def test_forgetting_follows_a_plant_that_changed():
    level, valves = _rows(3000)
    errors = {}
    for forget in (0.98, 1.0):
        model = FeatureModel(features=32, forget=forget, ridge=1e-6)
        model.fit(level[:2000], valves[:2000], _linear(level[:2000], valves[:2000], 0.02))
        for x, u in zip(level[2000:2500], valves[2000:2500]):  # the plant drains 50% faster
            model.add(x, u, _linear(x, u, 0.03))
        model.solve()
        errors[forget] = np.abs(model.predict(level[2500:], valves[2500:])
                                - np.clip(_linear(level[2500:], valves[2500:], 0.03), 0, 1)).max()
    # forgetting 0.98: the 2,000 nominal rows weigh 0.98^500 = 4e-5 each after 500 new
    # steps, so the new plant is nearly all that is left (measured 2.9e-4 m); never
    # forgetting, they outnumber the new rows 4 to 1 and pull the fit most of the way
    # back to the old drain (measured 9.4e-3 m; the change itself is up to 1e-2 m)
    assert errors[0.98] < 1e-3 < 5e-3 < errors[1.0]


def test_the_prior_holds_what_the_new_data_say_nothing_about():
    level, valves = _rows(2000)
    model = FeatureModel(features=32, forget=0.98, ridge=1.0)
    model.fit(level, valves, _linear(level, valves, 0.02))
    opened = np.ones((50, 6), np.int64)
    before = model.predict(level[:50], opened)
    closed = np.zeros(6, np.int64)
    for x in level[:500]:  # only closed valves from now on: nothing said about open ones
        model.add(x, closed, _linear(x, closed, 0.02))
    model.solve()
    # the data agree with the prior where they exist, and the prior (ridge 1 against
    # forgotten data) keeps the rest: the open-valve predictions stay within 1e-3 m
    assert np.abs(model.predict(level[:50], opened) - before).max() < 1e-3


def test_the_model_state_round_trips_and_a_mismatch_is_refused():
    level, valves = _rows(500)
    model = FeatureModel(features=16, seed=3)
    model.fit(level, valves, _linear(level, valves, 0.02))
    model.add(level[0], valves[0], level[0])
    other = FeatureModel(features=16, seed=3)
    other.load_state_dict(model.state_dict())
    assert np.array_equal(other.predict(level, valves), model.predict(level, valves))
    assert other.pending == model.pending == 1
    with pytest.raises(CheckpointError, match="gram: shape"):
        FeatureModel(features=8).load_state_dict(model.state_dict())


class _Still:
    """A model under which nothing ever moves."""

    def predict(self, level, valves):
        return np.array(np.broadcast_to(level, np.shape(valves)), np.float64)


def test_the_evaluator_sums_rewards_and_restarts_full_after_a_predicted_end():
    seq = hold_candidates(3, 5)
    x0 = np.array([0.2, 0.1, 0.0, 0.0, 0.1, 0.3])
    still = LearnedEvaluator(_Still(), demand=0.1, band=0.0)
    totals = still(x0, seq)
    expected = [sum(reward(x0, seq[k, t]) for t in range(5)) for k in range(len(seq))]
    assert np.allclose(totals, expected, atol=1e-12)
    # 0.7 m^3 left: above a demand of 0.1, below one of 1.0: after the first step the
    # episode ends and the tanks are full (reward of full tanks, 2.16 - activity)
    ends = LearnedEvaluator(_Still(), demand=1.0, band=0.0)(x0, seq[:1])
    full = np.ones(6)
    assert ends[0] == pytest.approx(reward(x0, seq[0, 0]) + 4 * reward(full, seq[0, 0]))
    # the band: an end predicted by less than it is not believed
    assert LearnedEvaluator(_Still(), demand=0.75, band=0.1)(x0, seq[:1])[0] == \
        pytest.approx(expected[0])


class _Moves:
    """A model under which an open valve 4 moves 0.05 m from tank 4 to tank 1."""

    def predict(self, level, valves):
        out = np.array(np.broadcast_to(level, np.shape(valves)), np.float64)
        moved = 0.05 * np.asarray(valves)[..., 3]
        out[..., 3] -= moved
        out[..., 0] += moved
        return out


def test_a_stuck_valve_is_planned_as_it_will_be():
    seq = hold_candidates(3, 5)
    x0 = np.array([0.2, 0.5, 0.5, 0.9, 0.5, 0.5])  # heavy right: opening valve 4 pays
    free = LearnedEvaluator(_Moves(), demand=0.0, band=0.0)(x0, seq)
    stuck = LearnedEvaluator(_Moves(), demand=0.0, band=0.0, stuck={3: 0})(x0, seq)
    opens_4 = seq[:, 0, 3] == 1
    closed_twin = [int(np.flatnonzero((seq[:, 0] == np.where(np.arange(6) == 3, 0, seq[k, 0]))
                                      .all(axis=1))[0]) for k in np.flatnonzero(opens_4)]
    # free, valve 4 alone is the best plan (the transfer balances the wings); stuck
    # closed, every plan that opens it moves fuel as its twin with it closed, and pays
    # the activity of the command (1/6 a step, 3 held steps) on top
    assert int(np.argmax(free)) == int(np.flatnonzero((seq[:, 0] == [0, 0, 0, 1, 0, 0])
                                                      .all(axis=1))[0])
    assert np.allclose(stuck[opens_4] + 3 / 6, stuck[closed_twin], rtol=0, atol=1e-12)
    assert stuck.max() < free.max()


def test_the_model_learns_a_pump_that_died(tmp_path):
    """Tank 3's pump dead (factor 0.5, age 1), every valve closed: the nominal fit
    expects tank 3 to drain first, and the model learns otherwise from the steps
    it observes."""
    agent = LearnedMPCAgent(LearnedMPCConfig(seed=0, learn_episodes=20))
    agent.prepare()
    scenario = tmp_path / "dead.toml"
    scenario.write_text('name = "dead"\ntank_factor = [inf, inf, 0.5, inf, inf, inf]\n'
                        'engine_factor = [inf, inf]\n')
    plant = CorePlant(str(scenario), 0, start_step=512)  # age 1: pump 3 gives nothing
    closed = np.zeros(6, np.int64)
    obs, errors = plant.reset(), []
    for _ in range(100):
        nxt = plant.step(closed)
        errors.append(np.abs(agent.model.predict(obs.level, nxt.valves) - nxt.level).max())
        agent.model.add(obs.level, nxt.valves, nxt.level)
        obs = nxt if not nxt.done else plant.reset()
    # each step's error before the model saw it: measured 0.09 m over steps 1-10 (tank 3
    # expected to fall 0.05 m, tank 2 not), 9e-4 m over steps 71-80 and less after
    assert np.mean(errors[:10]) > 0.03
    assert np.mean(errors[80:]) < 2e-3


def test_cli_runs_on_the_plant_process(tmp_path, scenarios):
    out = tmp_path / "learned"
    args = ["--method", "learned-mpc", "--scenario", str(scenarios / "single.toml"),
            "--seed", "0", "--out", str(out), "--intervals", "2", "--steps-per-interval",
            "64", "--learn-episodes", "20", "--quiet"]
    assert main(args) == 0
    with open(out / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["interval"]) for r in rows] == [0, 1]
    for r in rows:
        # near all closed, the optimum of the nearly healthy plant (2.65 / 2.43 per
        # step over these steps); measured 2.64 / 2.59 (seed 0)
        assert float(r["reward_per_step"]) > 2.3 and float(r["eval_reward_per_step"]) > 2.3
        assert 0 < float(r["model_one_step_rmse"]) < 0.05
        assert float(r["demand_estimate"]) == pytest.approx(0.1 * (1 + int(r["interval"]) / 40),
                                                            rel=0.05)
    config = json.loads((out / "config.json").read_text())
    assert config["mpc"]["method"] == "learned-mpc"
    assert config["mpc"]["learn_terminal_band"] == 0.005
