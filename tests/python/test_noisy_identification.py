"""Identification under sensor noise (ftc/learning/identify.py): the noise's
estimate, the CUSUM change test that replaces the one-error trigger when the
levels are noisy, and the pumps' closed form with a noise margin. Tiny cases
with known answers, fixed seeds (numpy's generators give the same numbers on
every machine)."""

from __future__ import annotations

import numpy as np

from ftc.learning.identify import (CUSUM_DRIFT, CUSUM_THRESHOLD, Identifier,
                                   OnlineIdentification, PlantParameters, noise_std,
                                   pumps_and_demands)


def _closed_episode(noise: float, steps: int = 400, seed: int = 0):
    """Every valve closed, each engine drawing 0.001 m a step from its inner tank
    (tanks 3 and 4), read with Gaussian noise of std ``noise``."""
    rng = np.random.default_rng(seed)
    true = np.ones(6) * 0.9 - np.outer(np.arange(steps + 1), [0, 0, 0.001, 0.001, 0, 0])
    read = true + rng.normal(0.0, noise, true.shape)
    valves = np.zeros((steps, 6), np.int64)
    return read[:-1], valves, read[1:]


def test_noise_std_recovers_the_noise_and_is_zero_without():
    for noise in (0.005, 0.02):
        est = noise_std(*_closed_episode(noise))
        # 400 x 6 second differences: the MAD's relative standard error is ~2%
        assert abs(est - noise) < 0.1 * noise
    assert noise_std(*_closed_episode(0.0)) < 1e-12
    # too few pairs: no estimate
    level, valves, nxt = _closed_episode(0.01, steps=3)
    assert noise_std(level, valves, nxt) is None


def test_cusum_ignores_noise_and_catches_a_shift():
    online = OnlineIdentification(Identifier(), trigger=1e-4)
    online.noise = 0.01
    rng = np.random.default_rng(1)
    level = np.full(6, 0.5)
    scale = np.sqrt(2.0) * online.noise
    # 3000 steps of residuals that are noise only: the sums drift down by 1 a step,
    # a crossing of 12 needs a run of outliers the normal tail does not give
    assert not any(online._cusum(rng.normal(0, scale, 6), level, level) for _ in range(3000))
    # a shift of 3 stds on one tank: the sum grows by ~2 a step, past 12 in ~7 steps
    shifted = [online._cusum(rng.normal(0, scale, 6) + np.r_[3 * scale, 0, 0, 0, 0, 0],
                             level, level) for _ in range(20)]
    assert True in shifted and shifted.index(True) <= 12
    assert (CUSUM_THRESHOLD / (3 - CUSUM_DRIFT)) < 12
    # a tank read near empty is left out: its reading is not the state
    online.cusum[:] = 0
    near_empty = np.r_[0.01, 0.5, 0.5, 0.5, 0.5, 0.5]
    assert not any(online._cusum(np.r_[5 * scale, 0, 0, 0, 0, 0], near_empty, near_empty)
                   for _ in range(50))


def test_pumps_under_noise_keep_a_pump_that_was_never_at_its_limit():
    # tank 3 serves all of engine 1's 0.001 m a step (its pump gives 0.1): never at its limit,
    # so its capacity stays the prior's (0.1); without the noise margin, the rows where
    # the noise made it look short put it at the noise's tail (~0.03)
    level, valves, nxt = _closed_episode(0.01, seed=2)
    prior = PlantParameters.nominal()
    pump, demand = pumps_and_demands(level, valves, nxt, np.zeros((len(level), 2)), prior,
                                     noise=0.01)
    assert pump[2] == 0.1 and abs(demand[0] - 0.001) < 0.003
    naive, _ = pumps_and_demands(level, valves, nxt, np.zeros((len(level), 2)), prior)
    assert naive[2] < 0.05
