"""The oracle's rollouts at the state where every oracle-mpc run of a benchmark
ended ("more than 1000 mode switches in one step (chattering)"), and the
safety net of every evaluator that plans on the C++ integrator: a candidate
whose rollout is refused scores -inf and is counted in the agent's metrics.

The state: tank_factor [8, inf, inf, inf, inf, 11], engine_factor [9, inf],
levels [0.472, 0, 0, 0, 0, 0.539]. Tank 1's pump is dead, so its fuel reaches
engine 1 only through the conduit into empty tanks 3 and 2; at age 8 tank 2's
inflow exceeded what pinned tank 3 left of the demand by 5e-7 m^3/s, and it
rose off the bottom by less than the rollouts' tolerance (dynamics.cpp). The
issue reported age 6; the runs actually failed in interval 8 (age 8), from
the levels below at full precision. Both ages are checked, at both the
rounded and the full-precision levels."""

from __future__ import annotations

import numpy as np
import pytest

from ftc import _core
from ftc.control.agents.physics.identified_mpc import IdentifiedAgent
from ftc.control.agents.physics.mpc import MPCAgent, OracleConfig
from ftc.control.planning.physics.evaluators import OracleEvaluator, ParamsEvaluator
from ftc.control.planning.planners import HoldPlanner, hold_candidates, valve_settings
from ftc.control.agents.physics.ppo_robust import RobustPPOAgent

SCENARIO = """
name = "chatter"
tank_factor = [8.0, inf, inf, inf, inf, 11.0]
engine_factor = [9.0, inf]
degradation = "stepwise"
steps_per_interval = 512
"""
LEVELS = {
    "reported": np.array([0.472, 0, 0, 0, 0, 0.539]),
    "planned from": np.array([0.4722248125680078, 0, 0, 0, 0, 0.53918186095492437]),
}
RTOL, ATOL = 1e-6, 1e-8  # the oracle's rollout tolerances (MPCConfig)


def _scenario() -> object:
    return _core.parse_scenario(SCENARIO, "chatter.toml")


@pytest.mark.parametrize("age", [6.0, 8.0])
@pytest.mark.parametrize("levels", list(LEVELS))
@pytest.mark.parametrize("exact_active_conduit", [False, True])
def test_every_valve_setting_rolls_out_from_the_chattering_state(age, levels,
                                                                 exact_active_conduit):
    """The 64 settings held 3 steps then closed (the oracle's batch), and each
    held for all 10 steps (a candidate alone), at the rollouts' tolerances:
    no error, levels within [0, 1] after every step."""
    params = _core.degraded_params(_scenario(), age)
    x0 = LEVELS[levels]
    rollout = _core.BatchRollout(rtol=RTOL, atol=ATOL,
                                 exact_active_conduit=exact_active_conduit)
    held = np.repeat(valve_settings()[:, None, :], 10, axis=1)
    for sequences in (hold_candidates(3, 10), *(held[k:k + 1] for k in range(64))):
        out = rollout.run(x0, sequences, params, details=True)
        assert np.isfinite(out["total"]).all()
        assert (out["levels"] >= 0).all() and (out["levels"] <= 1).all()


def test_the_oracle_plans_there_without_refusing_a_rollout():
    oracle = OracleEvaluator(_scenario(), RTOL, ATOL)
    oracle.set_age(8.0)
    u, _, total = HoldPlanner(3, 10).plan(oracle, LEVELS["planned from"])
    assert np.isfinite(total) and oracle.refused == 0
    assert u.shape == (6,)


class RefusingRollout:
    """A BatchRollout stand-in that refuses (RuntimeError, as the integrator
    does) every batch holding a candidate whose first valves are ``refuse``;
    otherwise the total of a candidate is its number of open first valves."""

    def __init__(self, refuse: np.ndarray) -> None:
        self.refuse = refuse

    def run(self, x0: np.ndarray, sequences: np.ndarray, params: object) -> np.ndarray:
        if (np.asarray(sequences)[:, 0] == self.refuse).all(axis=1).any():
            raise RuntimeError("StepIntegrator::Step: more than 1000 mode switches in one "
                               "step (chattering)")
        return np.asarray(sequences)[:, 0].sum(axis=1).astype(np.float64)


def _evaluators() -> dict[str, object]:
    oracle = OracleEvaluator(_scenario(), RTOL, ATOL)
    oracle.set_age(8.0)
    identified = ParamsEvaluator(None)
    identified.params = _core.degraded_params(_scenario(), 8.0)
    return {"oracle": oracle, "identified": identified}


@pytest.mark.parametrize("name", ["oracle", "identified"])
def test_a_refused_candidate_scores_minus_inf_and_is_counted(name):
    """Every evaluator that plans on the C++ integrator (the oracle's, and the
    identified physics of adaptive and ppo-robust's teacher)."""
    evaluate = _evaluators()[name]
    everything_open = np.ones(6, np.int64)
    evaluate.rollout = RefusingRollout(everything_open)
    candidates = hold_candidates(3, 10)
    totals = evaluate(LEVELS["planned from"], candidates)
    refused = (candidates[:, 0] == everything_open).all(axis=1)
    assert np.isneginf(totals[refused]).all() and refused.sum() == 1
    np.testing.assert_array_equal(totals[~refused], candidates[~refused, 0].sum(axis=1))
    assert evaluate.refused == 1
    u, _, total = HoldPlanner(3, 10).plan(evaluate, LEVELS["planned from"])
    assert total == 5 and u.sum() == 5  # the best candidate that was rolled out
    assert evaluate.refused == 2


def test_the_oracle_mpc_reports_refused_rollouts_per_interval():
    agent = MPCAgent(OracleConfig(method="oracle-mpc", scenario=""))
    agent.oracle.set_age(0.0)
    agent.oracle.rollout = RefusingRollout(np.ones(6, np.int64))
    agent.oracle(LEVELS["planned from"], hold_candidates(3, 10))
    assert agent.end_interval(0, None) == {"refused_rollouts": 1}
    assert agent.end_interval(1, None) == {"refused_rollouts": 0}  # counted per interval


@pytest.mark.parametrize("agent", [MPCAgent, IdentifiedAgent, RobustPPOAgent])
def test_every_agent_planning_on_the_integrator_has_the_column(agent):
    assert list(agent.extra_columns).count("refused_rollouts") == 1
