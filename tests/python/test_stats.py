"""ftc.experiments.stats on tiny cases computed by hand: the per-run normalized
score, the aggregates, the stratified bootstrap's distribution and the
probability of improvement."""

from __future__ import annotations

import numpy as np
import pytest

from ftc.experiments import stats

A = np.array


def _cell(scenario, method, seed, interval, r, ref, closed):
    return {"scenario": scenario, "method": method, "seed": seed, "interval": interval,
            "reward_per_step": r, "reference_reward_per_step": ref,
            "closed_reward_per_step": closed}


def test_a_run_is_normalized_over_its_intervals_not_per_cell():
    # interval 1: reference 0.01 above closed, the method 1 below: per cell -100;
    # interval 2: reference 2 above, the method 2 above: per cell 1.
    # Over the run: (-1 + 2) / (0.01 + 2) = 0.4975...; interval 0 does not count.
    rows = [_cell("s", "m", 0, 0, 0.0, 5.0, 5.0), _cell("s", "m", 0, 1, 2.0, 3.01, 3.0),
            _cell("s", "m", 0, 2, 4.0, 4.0, 2.0)]
    assert stats.run_scores(rows)["m"]["s"][0] == pytest.approx(1.0 / 2.01)
    assert sorted(stats.cell_scores(rows)["m"]["s"]) == pytest.approx([-100.0, 1.0])
    # the floor on the per-cell denominator: interval 1 -> -1 / 0.5
    assert sorted(stats.cell_scores(rows, floor=0.5)["m"]["s"]) == pytest.approx([-2.0, 1.0])
    # dropping interval 2 leaves a run where the reference's margin is 0.01
    assert stats.run_scores(rows, drop=("s", 0, 2))["m"]["s"][0] == pytest.approx(-100.0)
    # a run whose reference earns no more than closed has no score
    assert stats.run_scores([_cell("s", "m", 0, 1, 2.0, 3.0, 3.0)]) == {}


def test_the_aggregates_have_their_known_values():
    one = [A([[0.0, 1, 2, 3, 4, 5, 6, 7]])]  # one task of 8 runs: IQM drops 2 each side
    assert stats.iqm(one)[0] == pytest.approx(3.5)  # mean of 2, 3, 4, 5
    three = [A([[0.0, 0.0]]), A([[1.0, 1.0]]), A([[4.0, 6.0]])]  # task means 0, 1, 5
    assert stats.mean(three)[0] == pytest.approx(2.0)
    assert stats.median(three)[0] == pytest.approx(1.0)
    # shortfalls from 1: task 1: 1, 1; task 2: 0, 0; task 3: 0, 0 -> 1/3
    assert stats.optimality_gap(three)[0] == pytest.approx(1.0 / 3.0)
    assert stats.optimality_gap([A([[0.5, 1.2]])])[0] == pytest.approx(0.25)


def test_the_bootstrap_resamples_runs_within_each_task():
    # task a: runs 1, 1; task b: runs 0, 2. The mean over tasks of the task means
    # can only be 1/2 (b drew 0, 0: 1 in 4), 1 (0 and 2: 2 in 4) or 3/2 (2, 2: 1 in 4).
    # A bootstrap pooling the runs across tasks would also give 3/4 and 5/4.
    tasks = [A([1.0, 1.0]), A([0.0, 2.0])]
    seen = []

    def recording_mean(ts):
        values = stats.mean(ts)
        seen.append(values)
        return values

    est = stats.bootstrap(tasks, recording_mean, stats.BootstrapConfig(reps=4000, seed=3))
    samples = seen[-1]
    assert set(np.round(samples, 9)) == {0.5, 1.0, 1.5}
    # binomial sd of a frequency of 1/2 over 4000 draws: 0.008; 5 sd
    assert np.mean(samples == 1.0) == pytest.approx(0.5, abs=0.04)
    assert np.mean(samples == 0.5) == pytest.approx(0.25, abs=0.035)
    # 2.5th and 97.5th percentiles of {1/2: 1/4, 1: 1/2, 3/2: 1/4}
    assert (est.point, est.low, est.high) == (1.0, 0.5, 1.5)
    # a task whose runs all agree has no spread: one task of three equal runs
    flat = stats.bootstrap([A([0.7, 0.7, 0.7])], stats.iqm)
    assert (flat.point, flat.low, flat.high) == pytest.approx((0.7, 0.7, 0.7))


def test_the_probability_of_improvement_has_its_known_value_and_interval():
    # task 1: x runs 1, 2 against y runs 0, 2: pairs (1>0) 1, (1<2) 0, (2>0) 1,
    # (2=2) 1/2 -> 2.5 / 4 = 0.625; task 2: x 0 against y 1 -> 0. Mean 0.3125.
    x, y = [A([1.0, 2.0]), A([0.0])], [A([0.0, 2.0]), A([1.0])]
    est = stats.probability_of_improvement(x, y, stats.BootstrapConfig(reps=4000, seed=1))
    assert est.point == pytest.approx(0.3125)
    # resampled, task 1 reaches 0 (x drew 1, 1 and y drew 2, 2: 1 in 16) and 1
    # (x 2, 2 and y 0, 0: 1 in 16), both above the 2.5% tails; task 2 stays 0.
    assert (est.low, est.high) == pytest.approx((0.0, 0.5))
    # against itself: one half, exactly, in every resample of a single run
    assert stats.probability_of_improvement([A([3.0])], [A([3.0])]) == \
        stats.Estimate(0.5, 0.5, 0.5)
    with pytest.raises(ValueError, match="same tasks"):
        stats.probability_of_improvement(x, y[:1])


def test_the_performance_profile_counts_runs_above_each_threshold():
    # task 1 runs 0.2, 0.8; task 2 runs 0.6, 0.6: above 0.5: 1/2 and 1 -> 3/4
    point, low, high = stats.performance_profile([A([0.2, 0.8]), A([0.6, 0.6])],
                                                 np.array([0.0, 0.5, 0.7, 1.0]))
    assert point == pytest.approx([1.0, 0.75, 0.25, 0.0])
    assert low[1] == pytest.approx(0.5) and high[1] == pytest.approx(1.0)


def test_the_set_mean_resamples_the_tasks_and_then_their_runs():
    # tasks a: runs 0, 0 and b: 1, 1. Drawing two tasks with replacement gives a
    # mean of 0 (a, a: 1 in 4), 1/2 (2 in 4) or 1 (b, b: 1 in 4), so the interval
    # is [0, 1]; the stratified bootstrap holds the tasks and has no spread here.
    tasks = [A([0.0, 0.0]), A([1.0, 1.0])]
    est = stats.set_mean(tasks, stats.BootstrapConfig(reps=4000, seed=3))
    assert (est.point, est.low, est.high) == (0.5, 0.0, 1.0)
    fixed = stats.bootstrap(tasks, stats.mean)
    assert (fixed.low, fixed.high) == pytest.approx((0.5, 0.5))
    # one task of runs 0 and 2: the second stage resamples its runs (0, 1 or 2)
    alone = stats.set_mean([A([0.0, 2.0])], stats.BootstrapConfig(reps=4000, seed=3))
    assert (alone.point, alone.low, alone.high) == (1.0, 0.0, 2.0)
    with pytest.raises(ValueError, match="no task"):
        stats.set_mean([])


def test_the_set_mean_interval_covers_the_mean_of_the_distribution_the_tasks_come_from():
    # 300 sets of 12 tasks, each task's mean drawn from N(0.9, 0.1) and two runs
    # of it with seed noise N(0, 0.02): the interval should hold 0.9 in about 95%
    # of the sets. A percentile bootstrap of 12 tasks covers less: 0.89 to 0.91
    # measured with data seeds 11, 12 and 13 (pure NumPy, the same on every CPU).
    # 300 sets give a binomial sd of 0.017: the lower bound is 3 sd below 0.90.
    # The stratified bootstrap, which holds the tasks fixed, covers only the
    # seeds' spread: it held 0.9 in 0.13 to 0.19 of the sets.
    rng = np.random.default_rng(11)
    config = stats.BootstrapConfig(reps=1000, seed=0)
    held = fixed_held = 0
    for _ in range(300):
        means = rng.normal(0.9, 0.1, size=12)
        tasks = [m + rng.normal(0.0, 0.02, size=2) for m in means]
        est = stats.set_mean(tasks, config)
        held += est.low <= 0.9 <= est.high
        fixed = stats.bootstrap(tasks, stats.mean, config)
        fixed_held += fixed.low <= 0.9 <= fixed.high
    assert 0.85 <= held / 300 <= 0.99
    assert fixed_held / 300 < 0.5


def test_the_set_difference_is_paired_on_the_tasks():
    # y is x plus 0.1 on every task: drawn on the same tasks, the difference is
    # 0.1 in every resample, where two independent draws of x and y would spread
    # over [-0.9, 1.1] (tasks 0 and 1 apart)
    x = [A([0.0, 0.0]), A([1.0, 1.0])]
    y = [t + 0.1 for t in x]
    d = stats.set_difference(y, x, stats.BootstrapConfig(reps=2000, seed=1))
    assert (d.point, d.low, d.high) == pytest.approx((0.1, 0.1, 0.1))
    # the runs are drawn afresh within each task: one task of runs 0 and 2 against
    # a constant 1 differs by -1, 0 or 1
    e = stats.set_difference([A([0.0, 2.0])], [A([1.0])], stats.BootstrapConfig(reps=2000))
    assert (e.point, e.low, e.high) == (0.0, -1.0, 1.0)
    with pytest.raises(ValueError, match="the same tasks"):
        stats.set_difference(x, x[:1])
