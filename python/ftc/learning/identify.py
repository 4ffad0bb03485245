"""Grey-box identification of the plant's physical parameters from observed
transitions: pump capacities p_i, valve resistances R_i and engine demands d_j
(``docs/plant-model.md``).

This *assumes the plant's structure*: the hybrid tank model (pumps feeding
each engine innermost first, the shared conduit, its source/sink rule) with
unknown parameter values. It is told nothing about the faults: the parameters
are fitted so that the model's one-step predictions (the C++ core's own
integrator, :class:`ftc._core.BatchRollout`) match the levels the plant
published, by bounded nonlinear least squares with a Gaussian prior (the
previous estimate, or an extrapolation of it) that keeps the parameters the
data say nothing about (a valve never opened, a pump never at its limit)
where they were.

Conductances ``1 / R`` are fitted rather than resistances (the flow is linear
in them); a conductance at its floor means a valve that passes almost nothing.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ftc.common.constants import NUM_ENGINES, NUM_TANKS

NOMINAL_PUMP = 0.1        # m^3/s
NOMINAL_RESISTANCE = 100.0
NOMINAL_DEMAND = 0.05     # m^3/s per engine
# parameter vector: 6 pumps, 6 conductances, 2 demands
LOWER = np.r_[np.zeros(NUM_TANKS), np.full(NUM_TANKS, 1e-5), np.zeros(NUM_ENGINES)]
UPPER = np.r_[np.full(NUM_TANKS, 0.5), np.full(NUM_TANKS, 0.1), np.full(NUM_ENGINES, 1.0)]
# prior standard deviations: wide enough that a few informative steps move a
# parameter anywhere in its range, narrow enough to hold the uninformed ones
PRIOR_STD = np.r_[np.full(NUM_TANKS, 0.05), np.full(NUM_TANKS, 0.01), np.full(NUM_ENGINES, 0.05)]
LEVEL_STD = 1e-4  # m: residual scale of a predicted level (integration error ~1e-8)
# m: sensor noise above this is treated as noise (weighed, tested by CUSUM); below it
# the published levels are taken as exact (the noise-free plant estimates ~1e-12)
NOISY = 1e-3


@dataclass(frozen=True)
class PlantParameters:
    """Physical parameters of the tank model (SI units as plant-model.md)."""

    pump: np.ndarray        # (6,) m^3/s
    resistance: np.ndarray  # (6,)
    demand: np.ndarray      # (2,) m^3/s

    @classmethod
    def nominal(cls) -> "PlantParameters":
        return cls(np.full(NUM_TANKS, NOMINAL_PUMP), np.full(NUM_TANKS, NOMINAL_RESISTANCE),
                   np.full(NUM_ENGINES, NOMINAL_DEMAND))

    @classmethod
    def from_vector(cls, theta: np.ndarray) -> "PlantParameters":
        theta = np.clip(theta, LOWER, UPPER)
        return cls(theta[:6].copy(), 1.0 / theta[6:12], theta[12:14].copy())

    def vector(self) -> np.ndarray:
        return np.r_[self.pump, 1.0 / self.resistance, self.demand]

    def as_core(self) -> dict:
        """The dict ``ftc._core`` takes (other parameters nominal)."""
        return {"pump": self.pump, "resistance": self.resistance, "demand": self.demand}

    def extrapolate(self, previous: "PlantParameters", steps: float = 1.0) -> "PlantParameters":
        """The parameters ``steps`` intervals on, continuing the linear trend from
        ``previous`` (one interval earlier) to self: the degradation model of the
        spec is linear in age for p, R and d. Kept within physical bounds."""
        pump = np.clip(self.pump + steps * (self.pump - previous.pump), 0.0, None)
        resistance = np.maximum(self.resistance + steps * (self.resistance - previous.resistance),
                                1.0 / UPPER[6:12])
        demand = np.clip(self.demand + steps * (self.demand - previous.demand), 0.0, None)
        return PlantParameters(np.minimum(pump, self.pump), np.maximum(resistance, 1.0),
                               np.maximum(demand, self.demand))


class Identifier:
    """Fits :class:`PlantParameters` to transitions (level, valves, next level)."""

    def __init__(self, rtol: float = 1e-6, atol: float = 1e-8, max_rows: int = 512,
                 seed: int = 0) -> None:
        from ftc import _core  # native: the plant's own integrator

        self.rollout = _core.BatchRollout(rtol=rtol, atol=atol)
        self.max_rows = max_rows
        self.rng = np.random.default_rng(seed)

    def predict(self, params: PlantParameters, level: np.ndarray, valves: np.ndarray
                ) -> np.ndarray:
        """Next levels (T, 6) of rows (level (T, 6), valves (T, 6)) under ``params``;
        NaN for a row the integrator refuses under these parameters (chattering)."""
        return self.rollout.step_each(np.asarray(level, np.float64),
                                      np.asarray(valves, np.int64), params.as_core())

    def fit(self, level: np.ndarray, valves: np.ndarray, next_level: np.ndarray,
            deficit: np.ndarray, prior: PlantParameters, max_iterations: int = 20,
            noise: float = 0.0) -> tuple[PlantParameters, float]:
        """The parameters that best explain the rows; returns them and the RMS
        one-step error (m) of the model on the rows.

        Pumps and demands first, in closed form from the rows where the conduit
        is closed (fewer than two valves open) and no tank runs dry during the
        step: there each tank's drop is its pump's supply, a wing's drops plus
        its engine's published deficit are its demand, and a tank that gives
        less than what is left of the demand is at its pump's capacity. (These
        are kinks of min(): a gradient method stalls on them.) Then the valve
        conductances by least squares on the rows with an open conduit, where
        the flow is smooth in them.

        ``noise``: the standard deviation (m) of the sensor noise on the published
        levels (:func:`noise_std`). Above :data:`NOISY` the residuals are weighed
        by it instead of by the integration error, and the pumps' kinks are told
        from noise by a margin of it (:func:`pumps_and_demands`)."""
        level, valves, next_level, deficit = (
            np.asarray(a, np.float64) for a in (level, valves, next_level, deficit))
        noisy = noise > NOISY
        level_std = max(LEVEL_STD, np.sqrt(2.0) * noise) if noisy else LEVEL_STD
        pump, demand = pumps_and_demands(level, valves, next_level, deficit, prior,
                                         noise=noise if noisy else 0.0)
        base = PlantParameters(pump, prior.resistance, demand)
        conduit = np.flatnonzero(valves.sum(axis=1) >= 2)
        if len(conduit) > self.max_rows:
            conduit = np.sort(self.rng.choice(conduit, self.max_rows, replace=False))
        params = base
        if len(conduit):
            x, u, y = level[conduit], valves[conduit], next_level[conduit]
            c0 = 1.0 / prior.resistance
            used = np.flatnonzero(u.any(axis=0))  # conductances the rows say something about

            def with_c(c_used: np.ndarray) -> PlantParameters:
                c = c0.copy()
                c[used] = c_used
                return PlantParameters(pump, 1.0 / c, demand)

            def residuals(c_used: np.ndarray) -> np.ndarray:
                error = np.nan_to_num(self.predict(with_c(c_used), x, u) - y, nan=1.0)
                return np.r_[(error / level_std).ravel(),
                             (c_used - c0[used]) / PRIOR_STD[6:12][used]]

            # scipy.optimize costs 0.4-0.6 s to import; only identification needs it
            from scipy.optimize import least_squares

            result = least_squares(residuals, np.clip(c0[used], LOWER[6:12][used],
                                                      UPPER[6:12][used]),
                                   bounds=(LOWER[6:12][used], UPPER[6:12][used]),
                                   x_scale=PRIOR_STD[6:12][used], diff_step=1e-3,
                                   max_nfev=max_iterations * (len(used) + 1))
            params = with_c(result.x)
        rows = np.arange(len(level))
        if len(rows) > self.max_rows:
            rows = np.sort(self.rng.choice(rows, self.max_rows, replace=False))
        error = np.nan_to_num(self.predict(params, level[rows], valves[rows]) - next_level[rows],
                              nan=1.0)
        rms = float(np.sqrt(np.mean(error ** 2))) if len(rows) else float("nan")
        return params, rms

    def _rows(self, valves: np.ndarray) -> np.ndarray:
        n = len(valves)
        conduit = np.flatnonzero(valves.sum(axis=1) >= 2)
        others = np.flatnonzero(valves.sum(axis=1) < 2)
        room = max(0, self.max_rows - len(conduit))
        if len(conduit) > self.max_rows:
            conduit = np.sort(self.rng.choice(conduit, self.max_rows, replace=False))
        if len(others) > room:
            others = np.sort(self.rng.choice(others, room, replace=False))
        return np.sort(np.r_[conduit, others]).astype(int) if n else np.zeros(0, int)


LEFT_INWARD, RIGHT_INWARD = (2, 1, 0), (3, 4, 5)  # the order each engine draws from
DRY = 1e-9  # m: a tank at or below this level supplies nothing


def pumps_and_demands(level: np.ndarray, valves: np.ndarray, next_level: np.ndarray,
                      deficit: np.ndarray, prior: PlantParameters, tol: float = 1e-7,
                      noise: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Pump capacities (6,) and engine demands (2,) in closed form (see
    :meth:`Identifier.fit`); where the rows say nothing (a pump never at its
    limit, no clean row) the prior's value is kept, raised to what was seen.

    With sensor noise of std ``noise`` (m) on the levels a drop is off by
    sqrt(2) noise: a tank is taken to be at its pump's limit only when it gave
    less than what was left by 2.5 times that, and "what was seen" is the 90th
    percentile of its drops less 1.28 times that; a tank read within 3 noise
    stds of empty is taken as empty (the largest drop of hundreds
    would be the noise's extreme); and a tank is at its limit only if it was in
    a fifth of the rows that reached it (a pump well above its share is below
    the margin in the noise's tail only, and those rows would make its capacity
    the share less the tail)."""
    pump, demand = prior.pump.copy(), prior.demand.copy()
    drop_std = np.sqrt(2.0) * noise
    tol = max(tol, 2.5 * drop_std)
    dry = DRY + 3.0 * noise  # a tank read within 3 noise stds of empty may be empty
    closed = valves.sum(axis=1) < 2
    drop = level - next_level
    for j, wing in enumerate((LEFT_INWARD, RIGHT_INWARD)):
        w = list(wing)
        stays = ((level[:, w] > dry) & (next_level[:, w] > dry)) | \
                ((level[:, w] <= dry) & (next_level[:, w] <= dry))
        clean = closed & stays.all(axis=1)
        if not clean.any():
            continue
        d = drop[clean][:, w].sum(axis=1) + deficit[clean, j]
        demand[j] = float(np.median(d))
        at_limit: dict[int, list[float]] = {i: [] for i in w}
        seen = {i: 0.0 for i in w}
        gave: dict[int, list[float]] = {i: [] for i in w}
        for row in np.flatnonzero(clean):
            left = demand[j]
            for i in w:
                if level[row, i] <= dry:
                    continue
                s = drop[row, i]
                seen[i] = max(seen[i], s)
                gave[i].append(s)
                if s < left - tol:
                    at_limit[i].append(s)
                left = max(0.0, left - s)
                if left <= tol:
                    break
        for i in w:
            if at_limit[i] and not (noise and len(at_limit[i]) < 0.2 * len(gave[i])):
                pump[i] = float(np.median(at_limit[i]))
            elif noise and gave[i]:
                pump[i] = max(pump[i], float(np.percentile(gave[i], 90)) - 1.28 * drop_std)
            else:
                pump[i] = max(pump[i], seen[i])
    return pump, demand


def noise_std(level: np.ndarray, valves: np.ndarray, next_level: np.ndarray) -> float | None:
    """The standard deviation (m) of the sensor noise on the published levels,
    from consecutive rows (T, 6) of one episode (a row's next level is the
    following row's level) with the same valves and the conduit closed (fewer
    than two open): a tank's drop is then its pump's draw, the same in both
    rows, so the difference of the two drops is noise alone, with variance 6
    noise^2 (three independent readings, weights 1, -2, 1). Robust (median
    absolute deviation) to the few pairs where a tank runs dry or a pump's
    share changes. Tanks near empty or full (readings clipped) are left out.
    None: fewer than 20 such differences."""
    level, valves, next_level = (np.asarray(a, np.float64) for a in (level, valves, next_level))
    if len(level) < 2:
        return None
    pair = ((next_level[:-1] == level[1:]).all(axis=1) & (valves[:-1] == valves[1:]).all(axis=1)
            & (valves[:-1].sum(axis=1) < 2))
    k = np.flatnonzero(pair)
    second = (level[k + 1] - next_level[k + 1]) - (level[k] - next_level[k])
    inside = ((level[k] > 0.05) & (level[k] < 0.95) & (next_level[k + 1] > 0.05)
              & (next_level[k + 1] < 0.95))
    second = second[inside]
    if len(second) < 20:
        return None
    return float(np.median(np.abs(second - np.median(second))) / 0.6745 / np.sqrt(6.0))


TRIGGER_ROWS = 8  # rows since a detected change before re-identifying from them
NOISY_TRIGGER_ROWS = 48  # the same with noisy levels: enough rows to average the noise
CUSUM_DRIFT = 1.0       # per step, in residual stds: a shift below it is not a change
CUSUM_THRESHOLD = 12.0  # the sum that is one (measured: no false alarm in 9 x 512 steps)


class OnlineIdentification:
    """The parameters of the plant as it is now, kept up to date step by step.

    Per interval (``begin``): the parameters start from the extrapolation of
    the last two intervals' estimates (the degradation of the spec is linear
    in age), or the last one's. Every row (``add``) is predicted first; a
    prediction error above ``trigger`` (m) means the plant changed (an abrupt
    fault, the interval boundary's degradation): the rows before it are stale,
    and the parameters are re-identified from the rows since as soon as there
    are TRIGGER_ROWS of them (and every ``every`` rows, 0: never). ``end``
    fits the interval's rows once more and keeps the estimate.

    ``mispredicted`` counts the interval's steps whose one-step prediction was
    off by more than ``tolerance`` (m) under the parameters in force at the
    time (checked whether or not a trigger is set): how long the model stayed
    wrong, the measure of how fast relearning recovers from a change.

    With noisy levels (the noise estimated from the rows, :func:`noise_std`,
    above :data:`NOISY`; kept across intervals: it is the sensor's) one large
    error proves nothing: each tank's one-step residual, in units of its noise
    (sqrt(2) noise), feeds a two-sided CUSUM (drift ``CUSUM_DRIFT``), and a change
    is a sum above ``CUSUM_THRESHOLD``; the parameters are re-identified from the
    ``NOISY_TRIGGER_ROWS`` rows after it, and every fit weighs the noise
    (:meth:`Identifier.fit`). ``alarms`` lists the rows of the interval at which
    changes were detected.
    """

    def __init__(self, identifier: Identifier, trigger: float = 1e-4, every: int = 64,
                 tolerance: float = 1e-4) -> None:
        self.identifier, self.trigger, self.every = identifier, trigger, every
        self.tolerance = tolerance
        self.history: list[PlantParameters] = []
        self.params = self.prior = PlantParameters.nominal()
        self.rows: list[tuple[np.ndarray, ...]] = []
        self.change_at, self.pending, self.changes, self.seconds = 0, False, 0, 0.0
        self.mispredicted = 0
        self.noise = 0.0  # m, the sensor's (estimated)
        self.cusum = np.zeros((2, NUM_TANKS))
        self.alarms: list[int] = []

    @property
    def noisy(self) -> bool:
        return self.noise > NOISY

    def begin(self) -> None:
        self.rows, self.change_at, self.pending, self.changes, self.seconds = [], 0, False, 0, 0.0
        self.mispredicted = 0
        self.cusum[:] = 0.0
        self.alarms = []
        if len(self.history) >= 2:
            self.prior = self.history[-1].extrapolate(self.history[-2])
        elif self.history:
            self.prior = self.history[-1]
        self.params = self.prior

    def add(self, level: np.ndarray, valves: np.ndarray, next_level: np.ndarray,
            deficit: np.ndarray) -> bool:
        """One observed step; True when the parameters were re-identified."""
        self.rows.append((level, valves, next_level, deficit))
        if len(self.rows) % 16 == 0:  # the sensor's noise, from the rows so far
            estimate = noise_std(*(np.array(c) for c in list(zip(*self.rows))[:3]))
            self.noise = self.noise if estimate is None else estimate
        if self.trigger or self.tolerance:
            predicted = self.identifier.predict(self.params, level[None], valves[None])[0]
            error = float(np.max(np.abs(predicted - next_level)))  # NaN: refused, wrong
            self.mispredicted += int(not error <= self.tolerance)
            if self.noisy:
                wrong = bool(self.trigger) and self._cusum(predicted - next_level, level,
                                                           next_level)
            else:
                wrong = bool(self.trigger) and not error <= self.trigger
            if wrong and not self.pending:
                self.change_at, self.pending = len(self.rows) - 1, True
                self.changes += 1
                self.alarms.append(len(self.rows) - 1)
        if self.pending and len(self.rows) - self.change_at >= self.trigger_rows:
            self.pending = False
            self.params = self.fit()[0]
            return True
        if self.every and len(self.rows) % self.every == 0:
            self.params = self.fit()[0]
            return True
        return False

    @property
    def trigger_rows(self) -> int:
        return NOISY_TRIGGER_ROWS if self.noisy else TRIGGER_ROWS

    def _cusum(self, residual: np.ndarray, level: np.ndarray, next_level: np.ndarray) -> bool:
        """One step of the two-sided CUSUM on the residuals (6,) m; True (and
        the sums reset) when one crosses the threshold. A refused prediction
        (NaN) is a change. Tanks read within 3 noise stds of empty are left out:
        the plant's state there is not what the reading says (an empty tank
        read above 0 is predicted to drain)."""
        z = residual / (np.sqrt(2.0) * self.noise)
        z[(level <= 3.0 * self.noise) | (next_level <= 3.0 * self.noise)] = 0.0
        if not np.all(np.isfinite(z)):
            self.cusum[:] = 0.0
            return True
        self.cusum[0] = np.maximum(0.0, self.cusum[0] + z - CUSUM_DRIFT)
        self.cusum[1] = np.maximum(0.0, self.cusum[1] - z - CUSUM_DRIFT)
        if self.cusum.max() > CUSUM_THRESHOLD:
            self.cusum[:] = 0.0
            return True
        return False

    def fit(self) -> tuple[PlantParameters, float]:
        """Parameters from the rows since the last change (all rows if too few)."""
        start = time.perf_counter()
        rows = self.rows[self.change_at:] if len(self.rows) - self.change_at >= self.trigger_rows \
            else self.rows
        level, valves, next_level, deficit = (np.array(c) for c in zip(*rows))
        params, rms = self.identifier.fit(level, valves, next_level, deficit, self.prior,
                                          noise=self.noise)
        self.seconds += time.perf_counter() - start
        return params, rms

    def end(self) -> tuple[PlantParameters, float]:
        """The interval's final estimate (kept for the next extrapolation)."""
        self.params, rms = self.fit()
        self.history.append(self.params)
        return self.params, rms

    def ahead(self) -> PlantParameters:
        """The parameters expected one interval on."""
        if len(self.history) >= 2:
            return self.history[-1].extrapolate(self.history[-2])
        return self.history[-1] if self.history else self.params

    def state_dict(self) -> dict:
        return {"history": [p.vector().tolist() for p in self.history],
                "rng": self.identifier.rng.bit_generator.state, "noise": self.noise}

    def load_state_dict(self, state: dict) -> None:
        self.identifier.rng.bit_generator.state = state["rng"]
        self.noise = float(state.get("noise", 0.0))  # none in older checkpoints
        self.history = [PlantParameters.from_vector(np.array(v)) for v in state["history"]]
        if self.history:
            self.params = self.prior = self.history[-1]
