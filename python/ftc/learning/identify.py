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
            deficit: np.ndarray, prior: PlantParameters, max_iterations: int = 20
            ) -> tuple[PlantParameters, float]:
        """The parameters that best explain the rows; returns them and the RMS
        one-step error (m) of the model on the rows.

        Pumps and demands first, in closed form from the rows where the conduit
        is closed (fewer than two valves open) and no tank runs dry during the
        step: there each tank's drop is its pump's supply, a wing's drops plus
        its engine's published deficit are its demand, and a tank that gives
        less than what is left of the demand is at its pump's capacity. (These
        are kinks of min(): a gradient method stalls on them.) Then the valve
        conductances by least squares on the rows with an open conduit, where
        the flow is smooth in them."""
        level, valves, next_level, deficit = (
            np.asarray(a, np.float64) for a in (level, valves, next_level, deficit))
        pump, demand = pumps_and_demands(level, valves, next_level, deficit, prior)
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
                return np.r_[(error / LEVEL_STD).ravel(),
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
                      deficit: np.ndarray, prior: PlantParameters, tol: float = 1e-7
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Pump capacities (6,) and engine demands (2,) in closed form (see
    :meth:`Identifier.fit`); where the rows say nothing (a pump never at its
    limit, no clean row) the prior's value is kept, raised to what was seen."""
    pump, demand = prior.pump.copy(), prior.demand.copy()
    closed = valves.sum(axis=1) < 2
    drop = level - next_level
    for j, wing in enumerate((LEFT_INWARD, RIGHT_INWARD)):
        w = list(wing)
        stays = ((level[:, w] > DRY) & (next_level[:, w] > DRY)) | \
                ((level[:, w] <= DRY) & (next_level[:, w] <= DRY))
        clean = closed & stays.all(axis=1)
        if not clean.any():
            continue
        d = drop[clean][:, w].sum(axis=1) + deficit[clean, j]
        demand[j] = float(np.median(d))
        at_limit: dict[int, list[float]] = {i: [] for i in w}
        seen = {i: 0.0 for i in w}
        for row in np.flatnonzero(clean):
            left = demand[j]
            for i in w:
                if level[row, i] <= DRY:
                    continue
                s = drop[row, i]
                seen[i] = max(seen[i], s)
                if s < left - tol:
                    at_limit[i].append(s)
                left = max(0.0, left - s)
                if left <= tol:
                    break
        for i in w:
            if at_limit[i]:
                pump[i] = float(np.median(at_limit[i]))
            else:
                pump[i] = max(pump[i], seen[i])
    return pump, demand


TRIGGER_ROWS = 8  # rows since a detected change before re-identifying from them


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

    def begin(self) -> None:
        self.rows, self.change_at, self.pending, self.changes, self.seconds = [], 0, False, 0, 0.0
        self.mispredicted = 0
        if len(self.history) >= 2:
            self.prior = self.history[-1].extrapolate(self.history[-2])
        elif self.history:
            self.prior = self.history[-1]
        self.params = self.prior

    def add(self, level: np.ndarray, valves: np.ndarray, next_level: np.ndarray,
            deficit: np.ndarray) -> bool:
        """One observed step; True when the parameters were re-identified."""
        self.rows.append((level, valves, next_level, deficit))
        if self.trigger or self.tolerance:
            predicted = self.identifier.predict(self.params, level[None], valves[None])[0]
            error = float(np.max(np.abs(predicted - next_level)))  # NaN: refused, wrong
            self.mispredicted += int(not error <= self.tolerance)
            wrong = bool(self.trigger) and not error <= self.trigger
            if wrong and not self.pending:
                self.change_at, self.pending = len(self.rows) - 1, True
                self.changes += 1
        if self.pending and len(self.rows) - self.change_at >= TRIGGER_ROWS:
            self.pending = False
            self.params = self.fit()[0]
            return True
        if self.every and len(self.rows) % self.every == 0:
            self.params = self.fit()[0]
            return True
        return False

    def fit(self) -> tuple[PlantParameters, float]:
        """Parameters from the rows since the last change (all rows if too few)."""
        start = time.perf_counter()
        rows = self.rows[self.change_at:] if len(self.rows) - self.change_at >= TRIGGER_ROWS \
            else self.rows
        level, valves, next_level, deficit = (np.array(c) for c in zip(*rows))
        params, rms = self.identifier.fit(level, valves, next_level, deficit, self.prior)
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
                "rng": self.identifier.rng.bit_generator.state}

    def load_state_dict(self, state: dict) -> None:
        self.identifier.rng.bit_generator.state = state["rng"]
        self.history = [PlantParameters.from_vector(np.array(v)) for v in state["history"]]
        if self.history:
            self.params = self.prior = self.history[-1]
