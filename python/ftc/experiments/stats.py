"""Scores a researcher can trust and compare: a method's normalized score per run,
aggregated over the suite with 95% stratified-bootstrap confidence intervals, the
probability that one method improves on another, and performance profiles (the
protocol of Agarwal et al., "Deep RL at the Edge of the Statistical Precipice",
NeurIPS 2021, the rliable library's, written here on NumPy: docs/benchmarks.md
says why).

The unit is a *run*: one (scenario, seed). Scenarios are the tasks, seeds the
runs of a task. A run's score is normalized over the whole run, not per interval:

    score = sum_k (r_k - closed_k) / sum_k (reference_k - closed_k),   k = 1 .. last

where r_k, closed_k and reference_k are the method's, all valves closed's and the
reference's mean reward per step in interval k of that scenario and seed. Closed
scores 0 and the reference 1, as the per-cell score did, but an interval where
the reference earns barely more than closed no longer divides by almost nothing:
docs/benchmarks.md has the measurement that chose it. Interval 0 (the healthy
plant, where closed is the best there is and the reference plays it) is left
out of both sums; its reward stays in results.csv.

Aggregates over the runs of every task (``tasks``: one array of run scores per
scenario):

* IQM, the interquartile mean: the mean of the middle 50% of every run score
  pooled (scipy's trim_mean, 25% cut each side);
* mean: the mean over tasks of each task's mean;
* median: the median over tasks of each task's mean;
* optimality gap: the mean over tasks of each task's mean of max(0, 1 - score),
  the shortfall from the reference (lower is better).

Each comes with a 95% percentile interval from the stratified bootstrap: every
task's runs are resampled with replacement, within that task, and the aggregate
recomputed ``reps`` times.

The probability of improvement P(X > Y) of method X over Y is, per task, the
chance that a run of X scores above a run of Y (ties count half: the
Mann-Whitney U statistic over the product of the run counts), averaged over the
tasks; its interval resamples X's and Y's runs independently, within each task.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

# One resampled set of tasks: per task, an array (reps, runs of that task).
Statistic = Callable[[Sequence[np.ndarray]], np.ndarray]


@dataclass(frozen=True)
class Estimate:
    """A point estimate and its confidence interval [low, high]."""

    point: float
    low: float
    high: float

    def text(self, digits: int = 3) -> str:
        """"0.812 [0.790, 0.833]": how tables show an estimate."""
        return f"{self.point:.{digits}f} [{self.low:.{digits}f}, {self.high:.{digits}f}]"


# ---------------------------------------------------------------------------
# Run scores
# ---------------------------------------------------------------------------

def run_scores(rows: Sequence[Mapping], first_interval: int = 1,
               drop: tuple[str, int, int] | None = None) -> dict[str, dict[str, dict[int, float]]]:
    """method -> scenario -> seed -> the run's normalized score (module docstring).

    ``rows``: results cells (scenario, method, seed, interval, reward_per_step,
    reference_reward_per_step, closed_reward_per_step: benchmark_report.read_scores).
    Intervals from ``first_interval`` on where all three rewards are given count;
    a run whose reference does not earn more than closed over them has no score.
    ``drop``: a (scenario, seed, interval) cell left out (the robustness check)."""
    sums: dict = defaultdict(lambda: [0.0, 0.0, 0])
    for r in rows:
        key = (r["scenario"], int(r["seed"]), int(r["interval"]))
        v, ref, closed = (r.get(c) for c in ("reward_per_step", "reference_reward_per_step",
                                              "closed_reward_per_step"))
        if key[2] < first_interval or key == drop or v is None or ref is None or closed is None:
            continue
        s = sums[(r["method"], key[0], key[1])]
        s[0] += v - closed
        s[1] += ref - closed
        s[2] += 1
    out: dict = defaultdict(lambda: defaultdict(dict))
    for (method, scenario, seed), (num, den, n) in sums.items():
        if n and den > 0:
            out[method][scenario][seed] = num / den
    return {m: {s: dict(v) for s, v in per.items()} for m, per in out.items()}


def cell_scores(rows: Sequence[Mapping], first_interval: int = 1,
                floor: float = 0.0) -> dict[str, dict[str, list[float]]]:
    """method -> scenario -> every cell's score (r - closed) / max(reference - closed,
    ``floor``) over seeds and intervals from ``first_interval``: the per-cell
    normalization (floor 0: the benchmark's original one, cells with no spread left
    out), kept to measure it against :func:`run_scores`."""
    out: dict = defaultdict(lambda: defaultdict(list))
    for r in rows:
        v, ref, closed = (r.get(c) for c in ("reward_per_step", "reference_reward_per_step",
                                              "closed_reward_per_step"))
        if int(r["interval"]) < first_interval or v is None or ref is None or closed is None:
            continue
        den = max(ref - closed, floor)
        if den > 0:
            out[r["method"]][r["scenario"]].append((v - closed) / den)
    return {m: dict(v) for m, v in out.items()}


def tasks_of(per_scenario: Mapping[Any, Mapping[int, float] | Sequence[float]],
             scenarios: Sequence[Any] | None = None) -> list[np.ndarray]:
    """One array of run scores per scenario (in ``scenarios`` order where given;
    scenarios without a run are left out)."""
    names = list(per_scenario) if scenarios is None else [s for s in scenarios
                                                            if s in per_scenario]
    out = []
    for s in names:
        v = per_scenario[s]
        values = list(v.values()) if isinstance(v, Mapping) else list(v)
        if values:
            out.append(np.asarray(values, dtype=float))
    return out


# ---------------------------------------------------------------------------
# Aggregates: each maps resampled tasks, arrays (reps, runs), to (reps,)
# ---------------------------------------------------------------------------

def iqm(tasks: Sequence[np.ndarray]) -> np.ndarray:
    """Interquartile mean of every run pooled (25% trimmed from each end)."""
    from scipy.stats import trim_mean  # scipy: on the first aggregate

    return np.asarray(trim_mean(np.concatenate(tasks, axis=-1), 0.25, axis=-1))


def mean(tasks: Sequence[np.ndarray]) -> np.ndarray:
    """Mean over tasks of the task's mean run score."""
    return np.mean([t.mean(axis=-1) for t in tasks], axis=0)


def median(tasks: Sequence[np.ndarray]) -> np.ndarray:
    """Median over tasks of the task's mean run score."""
    return np.median([t.mean(axis=-1) for t in tasks], axis=0)


def optimality_gap(tasks: Sequence[np.ndarray], gamma: float = 1.0) -> np.ndarray:
    """Mean over tasks of the task's mean shortfall from ``gamma`` (the reference)."""
    return np.mean([np.maximum(gamma - t, 0.0).mean(axis=-1) for t in tasks], axis=0)


AGGREGATES: dict[str, Statistic] = {"IQM": iqm, "mean": mean, "median": median,
                                    "optimality gap": optimality_gap}


@dataclass(frozen=True)
class BootstrapConfig:
    """The stratified bootstrap.

    reps: resamples of every task's runs
    confidence: the interval's coverage (0.95: the 2.5th and 97.5th percentiles)
    seed: the resampling's random seed (fixed: a report is reproducible)
    """

    reps: int = 5000
    confidence: float = 0.95
    seed: int = 0


def _resample(tasks: Sequence[np.ndarray], reps: int,
              rng: np.random.Generator) -> list[np.ndarray]:
    """Each task's runs drawn with replacement within the task: (reps, runs) each."""
    return [t[rng.integers(0, len(t), size=(reps, len(t)))] for t in tasks]


def _interval(point: float, samples: np.ndarray, confidence: float) -> Estimate:
    tail = 50.0 * (1.0 - confidence)
    low, high = np.percentile(samples, [tail, 100.0 - tail])
    return Estimate(float(point), float(low), float(high))


def bootstrap(tasks: Sequence[np.ndarray], statistic: Statistic,
              config: BootstrapConfig = BootstrapConfig()) -> Estimate:
    """``statistic`` of the tasks, with its stratified-bootstrap interval."""
    if not tasks:
        raise ValueError("no task has a run score")
    point = float(statistic([t[None, :] for t in tasks])[0])
    rng = np.random.default_rng(config.seed)
    return _interval(point, statistic(_resample(tasks, config.reps, rng)), config.confidence)


def set_mean(tasks: Sequence[np.ndarray],
             config: BootstrapConfig = BootstrapConfig()) -> Estimate:
    """The mean over tasks of each task's mean, with a two-stage bootstrap
    interval: the tasks drawn with replacement, then each drawn task's runs
    within it.

    For a set of scenarios drawn from a distribution of faults (a held-out
    check), whose mean stands for the distribution's. The stratified bootstrap
    holds the tasks fixed, so its interval covers only the seeds' spread; this
    one also covers which faults happened to be drawn.
    """
    if not tasks:
        raise ValueError("no task has a run score")
    rng = np.random.default_rng(config.seed)
    drawn = rng.integers(0, len(tasks), size=(config.reps, len(tasks)))
    point = float(np.mean([t.mean() for t in tasks]))
    return _interval(point, _set_means(tasks, drawn, rng), config.confidence)


def set_difference(tasks: Sequence[np.ndarray], others: Sequence[np.ndarray],
                   config: BootstrapConfig = BootstrapConfig()) -> Estimate:
    """:func:`set_mean` of ``tasks`` minus that of ``others``, the same tasks
    scored for another method (in the same order), with the interval of the
    same two-stage bootstrap, paired: each resample draws the same tasks for
    both, then each method's runs within them."""
    if not tasks or len(tasks) != len(others):
        raise ValueError(f"set_difference: {len(tasks)} tasks against {len(others)}: the "
                         "same tasks, at least one, are needed for both")
    rng = np.random.default_rng(config.seed)
    drawn = rng.integers(0, len(tasks), size=(config.reps, len(tasks)))
    point = float(np.mean([t.mean() for t in tasks]) - np.mean([t.mean() for t in others]))
    samples = _set_means(tasks, drawn, rng) - _set_means(others, drawn, rng)
    return _interval(point, samples, config.confidence)


def _set_means(tasks: Sequence[np.ndarray], drawn: np.ndarray,
               rng: np.random.Generator) -> np.ndarray:
    """Per resample (a row of ``drawn``: which task fills each place), the mean
    over the places of the place's task's runs drawn afresh with replacement."""
    reps, n = drawn.shape
    total = np.zeros(reps)
    for t, runs in enumerate(tasks):
        again = runs[rng.integers(0, len(runs), size=(reps, n, len(runs)))].mean(axis=2)
        total += np.where(drawn == t, again, 0.0).sum(axis=1)
    return total / n


def aggregates(tasks: Sequence[np.ndarray],
               config: BootstrapConfig = BootstrapConfig()) -> dict[str, Estimate]:
    """Every aggregate of :data:`AGGREGATES` with its interval (one resampling each,
    the same seed: the intervals are those of one bootstrap)."""
    return {name: bootstrap(tasks, f, config) for name, f in AGGREGATES.items()}


# ---------------------------------------------------------------------------
# Probability of improvement
# ---------------------------------------------------------------------------

def _p_greater(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(a run of x scores above a run of y), ties half: x (reps, n), y (reps, m) -> (reps,)."""
    diff = x[:, :, None] - y[:, None, :]
    return ((diff > 0).sum(axis=(1, 2)) + 0.5 * (diff == 0).sum(axis=(1, 2))) / (
        x.shape[1] * y.shape[1])


def probability_of_improvement(x: Sequence[np.ndarray], y: Sequence[np.ndarray],
                               config: BootstrapConfig = BootstrapConfig()) -> Estimate:
    """P(X > Y) over tasks paired by position (``x[i]`` and ``y[i]``: one scenario's
    runs of each method), with an interval that resamples both independently
    within each task."""
    if len(x) != len(y) or not x:
        raise ValueError(f"the probability of improvement needs the same tasks on both "
                         f"sides ({len(x)} and {len(y)})")
    point = float(np.mean([_p_greater(a[None, :], b[None, :])[0] for a, b in zip(x, y)]))
    rng = np.random.default_rng(config.seed)
    rx, ry = _resample(x, config.reps, rng), _resample(y, config.reps, rng)
    samples = np.mean([_p_greater(a, b) for a, b in zip(rx, ry)], axis=0)
    return _interval(point, samples, config.confidence)


# ---------------------------------------------------------------------------
# Performance profiles
# ---------------------------------------------------------------------------

def performance_profile(tasks: Sequence[np.ndarray], taus: np.ndarray,
                        config: BootstrapConfig = BootstrapConfig()
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fraction of runs scoring above each tau (mean over tasks of the task's
    fraction), with its interval: (point, low, high), each shaped like ``taus``."""
    def profile(ts: Sequence[np.ndarray]) -> np.ndarray:  # (reps, len(taus))
        return np.mean([(t[..., None] > taus).mean(axis=-2) for t in ts], axis=0)

    point = profile([t[None, :] for t in tasks])[0]
    samples = profile(_resample(tasks, min(config.reps, 2000), np.random.default_rng(
        config.seed)))
    tail = 50.0 * (1.0 - config.confidence)
    low, high = np.percentile(samples, [tail, 100.0 - tail], axis=0)
    return point, low, high
