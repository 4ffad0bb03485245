"""The balance rule (ftc.control.agents.balance) on cases with known answers,
one row at a time and in batches (the teacher's closed-loop continuation rolls
it out over many plans at once)."""

from __future__ import annotations

import numpy as np

from ftc.control.agents.balance import balance_valves, balance_valves_batch
from ftc.plant.reward import MOMENT_ARMS


def _one_row(level: np.ndarray, band: float = 0.1) -> np.ndarray:
    """The rule written for one row, independently: the reference the batch is
    checked against."""
    mass = np.maximum(level, 0.0)  # areas of 1 m2
    u = np.zeros(6, np.int8)
    if mass.sum() <= 0:
        return u
    cg = float(mass @ MOMENT_ARMS / mass.sum())
    if abs(cg) <= band:
        return u
    heavy, light = (np.arange(3, 6), np.arange(3)) if cg > 0 else (np.arange(3), np.arange(3, 6))
    u[heavy[np.argmax(level[heavy])]] = 1
    u[light[np.argmin(level[light])]] = 1
    return u


def test_the_rule_opens_the_fullest_heavy_tank_and_the_emptiest_light_one():
    # left heavy (cg -1.2 arm units): from tank 1 (the first of the fullest) to tank 6
    assert balance_valves(np.array([1.0, 1.0, 1.0, 0.2, 0.3, 0.1])).tolist() == [1, 0, 0, 0, 0, 1]
    # right heavy: from tank 5 to tank 2
    assert balance_valves(np.array([0.5, 0.1, 0.5, 0.6, 0.9, 0.8])).tolist() == [0, 1, 0, 0, 1, 0]
    # balanced (cg 0), inside the band (cg 0.05 < 0.1) and empty tanks: nothing opens
    assert not balance_valves(np.full(6, 0.7)).any()
    assert not balance_valves(np.array([0.5, 0.5, 0.5, 0.5, 0.5, 0.55])).any()
    assert not balance_valves(np.zeros(6)).any()


def test_a_batch_is_each_row_alone_whatever_rows_it_holds():
    rng = np.random.default_rng(0)
    levels = rng.uniform(-0.05, 1.0, (3000, 6))
    levels[:300] = np.round(levels[:300], 1)  # ties, and cg on the band's edge
    levels[300:320] = 0.0
    alone = np.stack([balance_valves(x) for x in levels])
    assert (balance_valves_batch(levels) == alone).all()
    # and the rule as written for one row, where no row sits on the band's edge
    # (there the two sums of the cg may round apart)
    reference = np.stack([_one_row(x) for x in levels[320:]])
    assert (alone[320:] == reference).all()
    assert (balance_valves_batch(levels[::-1]) == alone[::-1]).all()
    odd = np.concatenate([balance_valves_batch(levels[i:i + 7]) for i in range(0, 3000, 7)])
    assert (odd == alone).all()
    assert alone.any(axis=1).mean() > 0.5  # most rows move fuel: the case is not empty


def test_the_rule_the_cpp_rollouts_step_is_this_rule():
    # BatchRollout.run_balance_rule steps the rule written again in C++
    # (rollout.cpp, BalanceValves): the same valves on every row, ties and
    # empty tanks included, except where the cg sits on the band's edge, where
    # the two languages' sums may round to either side (within 1e-12 of it)
    from ftc import _core

    rng = np.random.default_rng(1)
    levels = rng.uniform(-0.05, 1.0, (3000, 6))
    levels[:300] = np.round(levels[:300], 1)
    levels[300:320] = 0.0
    params = {}  # nominal: areas of 1 m2, as the Python rule takes
    for band in (0.1, 0.4):
        want = balance_valves_batch(levels, band)
        got = _core.balance_valves(levels, params, band)
        assert got.dtype == np.int8 and got.shape == want.shape
        apart = np.flatnonzero((got != want).any(axis=1))
        mass = np.maximum(levels[apart], 0.0)
        cg = mass @ MOMENT_ARMS / mass.sum(axis=1)
        assert np.abs(np.abs(cg) - band).max(initial=0.0) < 1e-12
        assert len(apart) < 10 and want.any(axis=1).mean() > 0.4
    # a band no cg reaches (|cg| <= 3): the rule never opens a valve
    assert not _core.balance_valves(levels, params, 3.0).any()
