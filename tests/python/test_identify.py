"""Grey-box identification (ftc.learning.identify) on data with known answers:
transitions of the in-process plant at a known degraded age, where the true
parameters are the scenario's formulas (ftc._core.degraded_params). And the
adaptive controller built on it plans as well as the oracle that is told the
faults, on a fault scenario."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ftc import _core
from ftc.learning.identify import Identifier, PlantParameters, pumps_and_demands
from ftc.plant import CorePlant

REPO = Path(__file__).resolve().parents[2]
SCENARIO = """name = "id"
tank_factor = [inf, 8.0, inf, inf, 12.0, inf]
engine_factor = [10.0, inf]
degradation = "stepwise"
steps_per_interval = 512
"""
AGE = 4


def _data(tmp_path: Path, open_probability: float, seed: int = 0):
    path = tmp_path / "id.toml"
    path.write_text(SCENARIO)
    plant = CorePlant(str(path), seed, start_step=AGE * 512)
    rng = np.random.default_rng(seed)
    rows = []
    o = plant.reset()
    for _ in range(511):
        u = (rng.random(6) < open_probability).astype(np.int8)
        n = plant.step(u)
        rows.append((o.level, u, n.level, n.deficit))
        o = plant.reset() if n.terminal else n
    true = _core.degraded_params(_core.parse_scenario(SCENARIO, "id"), float(AGE))
    return [np.array(c) for c in zip(*rows)], true


def test_pumps_and_demands_in_closed_form(tmp_path):
    (x, u, y, d), true = _data(tmp_path, 0.0)  # valves closed: pumps only
    pump, demand = pumps_and_demands(x, u, y, d, PlantParameters.nominal())
    # engine E1 burns 0.05 (1 + 4/10) = 0.07 m^3/s; tank 2's pump gives 0.1 (1 - 4/8) = 0.05
    # and is at its limit once tank 3 is empty (0.05 < 0.07): both exact to float rounding
    assert demand == pytest.approx(true["demand"], abs=1e-9)
    assert pump[1] == pytest.approx(true["pump"][1], abs=1e-9)
    # tank 5's pump (0.0667) never limits E2's 0.05: unobservable, the prior (0.1) is kept
    assert pump[4] == pytest.approx(0.1)


def test_fit_recovers_the_degraded_valves_and_predicts_to_integration_error(tmp_path):
    (x, u, y, d), true = _data(tmp_path, 0.15)
    params, rms = Identifier().fit(x, u, y, d, PlantParameters.nominal())
    # valves 2 and 5 degrade (R = 100 (1 + 4/8) = 150, 100 (1 + 4/12) = 133.3); the others
    # are nominal; each valve was open in ~15% of the rows, enough to pin R to < 0.5%
    assert params.resistance == pytest.approx(true["resistance"], rel=5e-3)
    assert rms < 1e-6  # m: the model is the plant's own, so only integration error remains
    nominal_rms = np.sqrt(np.mean((Identifier().predict(PlantParameters.nominal(), x, u) - y) ** 2))
    assert nominal_rms > 1e-3  # the nominal model is visibly wrong on these rows


def test_extrapolation_continues_a_linear_trend_within_bounds():
    a = PlantParameters(np.full(6, 0.1), np.full(6, 100.0), np.full(2, 0.05))
    b = PlantParameters(np.full(6, 0.08), np.full(6, 110.0), np.full(2, 0.06))
    c = b.extrapolate(a)
    assert c.pump == pytest.approx(0.06) and c.resistance == pytest.approx(120.0)
    assert c.demand == pytest.approx(0.07)
    dead = PlantParameters(np.full(6, 0.01), np.full(6, 100.0), np.full(2, 0.05))
    assert dead.extrapolate(b).pump.min() == 0.0  # a dying pump stops at zero, not below


def _metrics(module: str, method: str, scenario: Path, out: Path) -> list[float]:
    subprocess.run([sys.executable, "-m", module, "--method", method, "--scenario", str(scenario),
                    "--intervals", "4", "--link", "core", "--quiet", "--out", str(out)],
                   cwd=REPO, check=True, timeout=900)
    with open(out / "metrics.csv") as f:
        return [float(r["reward_per_step"]) for r in csv.DictReader(f)]


@pytest.mark.slow
def test_identified_mpc_plans_as_well_as_the_oracle(tmp_path, scenarios):
    scenario = scenarios / "multiple.toml"
    oracle = _metrics("ftc.mpc", "oracle-mpc", scenario, tmp_path / "oracle")
    adaptive = _metrics("ftc.mpc", "identified-mpc", scenario, tmp_path / "adaptive")
    closed = _metrics("ftc.controller", "closed", scenario, tmp_path / "closed")
    # measured: within 0.1% of the oracle in every interval; all closed loses 9-19%
    assert all(a >= 0.99 * o for a, o in zip(adaptive, oracle)), (adaptive, oracle)
    assert all(a > c + 0.1 for a, c in zip(adaptive[1:], closed[1:]))


def test_step_each_equals_one_step_runs_bit_for_bit_and_marks_refused_rows(tmp_path):
    """The identifier's predictions come from BatchRollout.step_each; it must give
    exactly what one-step run() calls give, row by row (consecutive rows that
    continue one another continue CVODE warm in both), and NaN for a row the
    integrator refuses, without stopping the others."""
    (x, u, y, d), true = _data(tmp_path, 0.3)
    params = {k: true[k] for k in ("pump", "resistance", "demand")}
    one = _core.BatchRollout(rtol=1e-6, atol=1e-8)
    expected = np.array([one.run(x[t], u[t].reshape(1, 1, 6).astype(np.int64), params,
                                 details=True)["levels"][0, 0] for t in range(len(x))])
    got = _core.BatchRollout(rtol=1e-6, atol=1e-8).step_each(x, u, params)
    assert got.shape == x.shape
    assert np.array_equal(got, expected)  # bit-identical, not merely close
    assert np.abs(got - y).max() < 1e-6  # and the plant's own next levels (its tolerances)
    # a row CVODE refuses (its right-hand side fails on a NaN level; run() raises)
    bad, valves = np.full((3, 6), 0.5), np.tile([1, 1, 0, 0, 0, 0], (3, 1))
    bad[1, 0] = np.nan
    with pytest.raises(RuntimeError, match="CVode"):
        _core.BatchRollout().run(bad[1], valves[1].reshape(1, 1, 6), params)
    out = _core.BatchRollout().step_each(bad, valves, params)
    assert np.isnan(out[1]).all() and np.isfinite(out[[0, 2]]).all()
    with pytest.raises(ValueError, match="valves must be an array of shape"):
        _core.BatchRollout().step_each(x[:3], u[:2], params)
    with pytest.raises(ValueError, match="valves must be 0 or 1"):
        _core.BatchRollout().step_each(x[:1], np.full((1, 6), 2), params)
