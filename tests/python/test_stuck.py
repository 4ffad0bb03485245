"""The shared stuck-valve detector (ftc/learning/stuck.py) and how every planning
controller uses it: stuck valves rolled out as they will be, the activity term
charged for the commanded valves (as the runner's reward is), stuck valves
commanded closed, detections reported with their step. Tiny cases with known
answers, on the real C++ physics where a rollout is involved."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ftc import _core
from ftc.control.agents.physics.identified_mpc import IdentifiedAgent, IdentifiedConfig
from ftc.control.planning.physics.evaluators import ParamsEvaluator
from ftc.control.planning.planners import hold_candidates
from ftc.control.run.agent import StepContext, Transition
from ftc.learning.physics_env import PhysicsEnv
from ftc.learning.stuck import StuckMemory, StuckValves, charge_commanded
from ftc.plant.link import PlantObservation


def test_detects_open_and_closed_from_the_applied_valves_with_their_step():
    s = StuckValves()
    assert not s.observe([1, 0, 0, 0, 0, 0], [1, 0, 0, 0, 0, 0], 5)  # as commanded
    assert s.observe([1, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0], 7)      # valve 1 stays closed
    assert s.observe([0, 0, 0, 0, 0, 0], [0, 1, 0, 0, 0, 0], 9)      # valve 2 stays open
    assert not s.observe([1, 0, 0, 0, 0, 0], [0, 1, 0, 0, 0, 0], 10)  # nothing new
    assert s.stuck == {0: 0, 1: 1}
    assert s.detections == [(0, 0, 7), (1, 1, 9)]
    m = s.metrics()
    assert m == {"stuck_valves": 2,
                 "stuck_detected": "valve 1 closed at step 7; valve 2 open at step 9"}
    assert s.metrics()["stuck_detected"] == ""  # reported once
    # planned as they will be; commanded closed (closed costs no activity)
    assert s.applied(np.ones((2, 6), np.int64)).tolist() == [[0, 1, 1, 1, 1, 1]] * 2
    assert s.command(np.array([1, 1, 0, 1, 0, 0])).tolist() == [0, 0, 0, 1, 0, 0]


def test_state_round_trip_keeps_the_dict_the_evaluators_hold():
    s = StuckValves()
    s.observe([0] * 6, [0, 0, 1, 0, 0, 0], 3)
    held = s.stuck
    t = StuckValves()
    held_by_t = t.stuck
    t.load_state_dict(s.state_dict())
    assert t.stuck is held_by_t and t.stuck == {2: 1} and t.detections == [(2, 1, 3)]
    assert held == {2: 1}


def test_the_learned_policies_memory_holds_what_the_detector_finds():
    # one rule, two keepers: the detector's dict (planners) and the student's
    # (N, 12) memory must agree after any sequence of commanded/applied valves,
    # including a valve seen stuck closed, then open (the newest sighting wins)
    rng = np.random.default_rng(3)
    n, steps = 5, 40
    detectors, memory = [StuckValves() for _ in range(n)], StuckMemory(n)
    for t in range(steps):
        commanded = rng.integers(0, 2, (n, 6))
        applied = np.where(rng.random((n, 6)) < 0.1, 1 - commanded, commanded)
        memory.see(commanded, applied)
        for d, c, a in zip(detectors, commanded, applied):
            d.observe(c, a, t)
    for i, d in enumerate(detectors):
        want = np.zeros(12, np.float32)
        for valve, state in d.stuck.items():
            want[valve + 6 * state] = 1.0
        np.testing.assert_array_equal(memory.stuck[i], want)
    assert memory.stuck.sum() > n  # the case is not empty
    np.testing.assert_array_equal(memory.features(), 2.0 * memory.stuck - 1.0)
    memory.forget(np.array([True, False, False, False, False]))
    assert memory.stuck[0].sum() == 0 and memory.stuck[1:].sum() > 0


def test_charge_commanded_known_answer():
    # two steps, valve 1 applied open both, commanded open once: 1/6 less charged
    applied = np.array([[[1, 0, 0, 0, 0, 0], [1, 0, 0, 0, 0, 0]]])
    commanded = np.array([[[1, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0]]])
    assert charge_commanded(np.array([1.0]), commanded, applied)[0] == pytest.approx(1 + 1 / 6)


def _params() -> dict:
    return _core.degraded_params(_core.Scenario(), 0.0)


def test_params_evaluator_rolls_stuck_valves_as_they_are_and_charges_the_commands():
    x0 = np.array([0.3, 0.5, 0.9, 0.6, 0.5, 0.4])
    seq = hold_candidates(3, 5)
    free = ParamsEvaluator(_core.BatchRollout())
    free.params = _params()
    stuck = ParamsEvaluator(_core.BatchRollout())
    stuck.params = free.params
    stuck.stuck[1] = 1  # valve 2 stuck open
    applied = seq.copy()
    applied[:, :, 1] = 1
    got = stuck(x0, seq)
    # the same rollout as the applied valves on the free plant, the activity of the
    # command: known answer up to rounding
    want = free(x0, applied) + (applied.mean(-1) - seq.mean(-1)).sum(-1)
    assert np.allclose(got, want, rtol=0, atol=1e-12)
    # commanding the stuck valve open moves the same fuel and costs 3 held steps x 1/6
    opens = np.flatnonzero(seq[:, 0, 1] == 1)
    twins = [int(np.flatnonzero((seq[:, 0] == np.where(np.arange(6) == 1, 0, seq[k, 0]))
                                .all(axis=1))[0]) for k in opens]
    assert np.allclose(got[opens] + 0.5, got[twins], rtol=0, atol=1e-12)


def test_physics_env_moves_fuel_through_a_stuck_valve_and_charges_the_action():
    start = np.array([[0.3, 0.5, 0.9, 0.6, 0.5, 0.4]])
    a = PhysicsEnv(_params(), 1, starts=start, branch_fraction=1.0, seed=0, stuck={1: 1})
    b = PhysicsEnv(_params(), 1, starts=start, branch_fraction=1.0, seed=0)
    a.reset(), b.reset()
    assert np.array_equal(a.level, b.level)
    act = torch.tensor([[0, 0, 1, 0, 0, 0]])
    sa = a.step(act)
    sb = b.step(torch.tensor([[0, 1, 1, 0, 0, 0]]))  # what the stuck plant applies
    assert torch.equal(sa.obs, sb.obs)
    # same levels, one valve fewer commanded: 1/6 more reward (float32)
    assert float(sa.reward[0] - sb.reward[0]) == pytest.approx(1 / 6, abs=1e-6)


def _obs(level, valves, step) -> PlantObservation:
    level = np.asarray(level, np.float64)
    return PlantObservation(level=level, true_level=level, valves=np.asarray(valves, np.int8),
                            deficit=np.zeros(2), age=0.0, step=step, episode=0,
                            operating_steps=step, terminal=False, truncated=False,
                            evaluation=False)


def test_identified_mpc_plans_and_commands_a_stuck_open_valve_closed():
    agent = IdentifiedAgent(IdentifiedConfig(seed=0, identify_every=0, identify_trigger=0.0))
    agent.begin_interval(0)
    level = np.array([0.3, 0.5, 0.9, 0.6, 0.5, 0.4])
    nxt = level - 0.01
    # commanded all closed, valve 2 applied open: stuck open, found at step 40
    agent.observe(Transition(_obs(level, np.zeros(6), 40), np.zeros(6, np.int8), 0.0,
                             _obs(nxt, [0, 1, 0, 0, 0, 0], 41), _obs(nxt, [0, 1, 0, 0, 0, 0], 41)))
    assert agent.evaluator_.stuck == {1: 1}
    u = agent.act(_obs(nxt, np.zeros(6), 41), StepContext(0, 1, 100))
    assert u[1] == 0
    m = agent.end_interval(0, None)
    assert m["stuck_valves"] == 1 and m["stuck_detected"] == "valve 2 open at step 40"
