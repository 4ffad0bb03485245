"""Receding-horizon planners over valve sequences, and the evaluators they
plan with: the true degraded physics (C++ batch rollouts; the oracle) or the
learned world model (one torch batch per step). See :mod:`ftc.control.mpc_agent`."""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch

from ftc.common.constants import NUM_TANKS, TANK_HEIGHT, TERMINAL_TOLERANCE
from ftc.plant.reward import AREAS, reward_torch

# Summed rewards (K,) of candidate valve sequences (K, L, 6) from levels (6,).
Evaluator = Callable[[np.ndarray, np.ndarray], np.ndarray]


# --------------------------------------------------------------------------
# Planners
# --------------------------------------------------------------------------

def valve_settings() -> np.ndarray:
    """All 64 valve settings, (64, 6) int; row a has valve i open iff bit i of a."""
    codes = np.arange(2 ** NUM_TANKS)
    return ((codes[:, None] >> np.arange(NUM_TANKS)) & 1).astype(np.int64)


def hold_candidates(hold: int, horizon: int) -> np.ndarray:
    """(64, horizon, 6): setting a held for ``hold`` steps, then all closed.

    Row 0 is all closed throughout, so ties go to doing nothing."""
    seq = np.zeros((2 ** NUM_TANKS, horizon, NUM_TANKS), np.int64)
    seq[:, :min(hold, horizon)] = valve_settings()[:, None, :]
    return seq


class HoldPlanner:
    """Best of the 64 'hold H then closed' sequences (first maximum: fewest valves on ties)."""

    def __init__(self, hold: int, horizon: int) -> None:
        self.hold, self.horizon = hold, horizon
        self._candidates: dict[int, np.ndarray] = {}

    def candidates(self, horizon: int) -> np.ndarray:
        if horizon not in self._candidates:
            self._candidates[horizon] = hold_candidates(self.hold, horizon)
        return self._candidates[horizon]

    def plan(self, evaluate: Evaluator, x0: np.ndarray, horizon: int | None = None
             ) -> tuple[np.ndarray, np.ndarray, float]:
        """(first valves (6,), best sequence (L, 6), its summed reward)."""
        seq = self.candidates(horizon or self.horizon)
        totals = evaluate(x0, seq)
        best = int(np.argmax(totals))
        return seq[best, 0].copy(), seq[best], float(totals[best])


class CEMPlanner:
    """Cross-entropy search over independent per-step valve-open probabilities.

    Each decision starts from the previous decision's probabilities shifted by
    one step (new last step: 0.5), samples ``samples`` sequences, adds the best
    hold plan and the previous best plan shifted (so it never does worse than
    the hold planner on the rollouts it plans with), keeps the ``elites`` best
    and moves the probabilities towards their mean; the best sequence seen wins.
    """

    def __init__(self, cfg: Any, rng: np.random.Generator) -> None:
        """cfg: an MPCConfig (hold, horizon, cem_* options)."""
        self.cfg, self.rng = cfg, rng
        self.hold = HoldPlanner(cfg.hold, cfg.horizon)
        self.probs: np.ndarray | None = None
        self.previous: np.ndarray | None = None

    def plan(self, evaluate: Evaluator, x0: np.ndarray, horizon: int | None = None
             ) -> tuple[np.ndarray, np.ndarray, float]:
        cfg, L = self.cfg, horizon or self.cfg.horizon
        _, hold_best, hold_total = self.hold.plan(evaluate, x0, L)
        probs = np.full((L, NUM_TANKS), 0.5)
        seeds = [hold_best]
        if self.probs is not None:
            n = min(L, len(self.probs) - 1)
            probs[:n] = self.probs[1:n + 1]
            shifted = np.zeros((L, NUM_TANKS), np.int64)
            shifted[:n] = self.previous[1:n + 1]
            seeds.append(shifted)
        best_seq, best_total = hold_best, hold_total
        for _ in range(cfg.cem_iterations):
            samples = (self.rng.random((cfg.cem_samples, L, NUM_TANKS)) < probs).astype(np.int64)
            batch = np.concatenate([samples, np.stack(seeds)])
            totals = evaluate(x0, batch)
            elite = np.argsort(-totals, kind="stable")[:cfg.cem_elites]
            probs = cfg.cem_smoothing * probs + (1 - cfg.cem_smoothing) * batch[elite].mean(0)
            if totals[elite[0]] > best_total:
                best_total, best_seq = float(totals[elite[0]]), batch[elite[0]]
            seeds = [best_seq]
        self.probs, self.previous = probs, best_seq
        return best_seq[0].copy(), best_seq, best_total

    def reset(self) -> None:
        """Forget the warm start (a new episode starts from full tanks)."""
        self.probs = self.previous = None


# --------------------------------------------------------------------------
# Evaluators: where the candidates are simulated
# --------------------------------------------------------------------------

class OracleEvaluator:
    """The true physics degraded to a given age (C++ batch rollouts)."""

    def __init__(self, scenario: Any, rtol: float = 1e-6, atol: float = 1e-8) -> None:
        from ftc import _core  # native: the C++ physics

        self._core, self.scenario = _core, scenario
        self.rollout = _core.BatchRollout(rtol=rtol, atol=atol)
        self._params: dict[float, dict] = {}
        self.params: dict | None = None

    def set_age(self, age: float) -> None:
        if age not in self._params:
            self._params[age] = self._core.degraded_params(self.scenario, float(age))
        self.params = self._params[age]

    def age_at(self, operating_steps: int) -> float:
        return float(self._core.age_at(self.scenario, int(operating_steps)))

    def __call__(self, x0: np.ndarray, sequences: np.ndarray) -> np.ndarray:
        return self.rollout.run(np.asarray(x0, np.float64), sequences, self.params)


class ModelEvaluator:
    """The learned world model, all candidates in one torch batch per step.

    Terminal rule as the plant's with the demand estimated from data:
    total volume < demand + 1e-6 m^3, then full tanks.
    """

    def __init__(self, model: Any, demand: float) -> None:
        self.model, self.demand, self.height = model, float(demand), TANK_HEIGHT

    def __call__(self, x0: np.ndarray, sequences: np.ndarray) -> np.ndarray:
        k, horizon, _ = sequences.shape
        areas = torch.as_tensor(AREAS, dtype=torch.float32)
        with torch.no_grad():
            u = torch.as_tensor(sequences, dtype=torch.float32)
            x = torch.as_tensor(np.asarray(x0), dtype=torch.float32).expand(k, NUM_TANKS)
            full = torch.full((NUM_TANKS,), self.height, dtype=torch.float32)
            total = torch.zeros(k, dtype=torch.float64)
            for t in range(horizon):
                nxt = self.model.predict(x, u[:, t])
                total += reward_torch(nxt, u[:, t]).double()
                terminal = nxt @ areas < self.demand + TERMINAL_TOLERANCE
                x = torch.where(terminal[:, None], full, nxt)
        return total.numpy()
