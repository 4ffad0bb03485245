"""The adaptive policy's privileged teacher: oracle-mpc's planner on the true
physics of each plant of a batch (docs/adaptive.md).

For env i of a pool, given its scenario (the true faults), its operating
steps (the age and the events in force) and its published levels, the
teacher returns the valves ``oracle-mpc`` would apply there: the best of the
64 "hold H steps, then all closed" plans over a horizon of L steps, the
horizon cut at the interval's end (oracle-mpc's defaults: H = 3, L = 10).
With more hold lengths (``extra_holds``), each setting is valued by the best
of its plans: held H steps or any of those, then all closed. With a second
stage (``second_stage`` K > 0), the K settings valued best that way are also
valued by their 64 two-stage plans: held H steps, then any one setting held
to the horizon (all closed among them), so the continuation is chosen too.
With a recheck (``recheck`` K > 0), the K settings valued best are valued
again over a longer horizon (``recheck_horizon``, cut at the interval's
end too) by the best of their plans holding each hold length, then all
closed, and the label is the best of those K: a setting whose benefit
outlasts the short horizon is then told from one that only looks as good
over it. With ``recheck_rule`` "balance", the rechecked plans are held, then
the balance rule's (:func:`ftc.control.agents.balance.balance_valves`) in
closed loop to the longer horizon instead of all closed: a continuation
that keeps balancing, as a policy would, rather than doing nothing. With
"best", each rechecked plan is valued by the better of the two
continuations, and all closed (setting 0) is always among the rechecked
settings: where doing nothing is nearly optimal, late in a degraded life,
a plan has to beat it over the longer horizon to be chosen.
It is used for training only: the student never sees it at run time.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from ftc.common.constants import NUM_TANKS
from ftc.control.planning.physics.evaluators import OracleEvaluator
from ftc.control.planning.planners import HoldPlanner, two_stage_candidates, valve_settings
from ftc.learning.stuck import charge_commanded

RECHECK_RULES = ("closed", "balance", "best")  # what a rechecked plan does after its hold
CLOSED = 0  # the setting with every valve closed


class PoolTeacher:
    """Labels states of many plants with oracle-mpc's decision.

    hold, horizon: the planner's H and L; extra_holds: more hold lengths, a
    setting valued by the best of its plans (its first step is what they
    share); second_stage: how many of the best settings are also valued by
    their two-stage plans (held ``hold`` steps, then any setting to the
    horizon; 0: none); recheck: how many of the best settings are valued
    again over ``recheck_horizon`` steps (0: none; the label is then the best
    of them); recheck_rule: what a rechecked plan does after its hold, "closed"
    (every valve), "balance" (the balance rule in closed loop:
    :func:`hold_then_rule`) or "best" (the better of the two, all closed always
    rechecked too); closed_form: the rollouts step the conduit in closed
    form (``_core.BatchRollout``'s exact_active_conduit, several times faster
    than CVODE, within its tolerances)."""

    def __init__(self, hold: int = 3, horizon: int = 10, closed_form: bool = True,
                 extra_holds: Sequence[int] = (), second_stage: int = 0, recheck: int = 0,
                 recheck_horizon: int = 10, recheck_rule: str = "closed") -> None:
        for name, value in (("second_stage", second_stage), ("recheck", recheck)):
            if not 0 <= value <= 2 ** NUM_TANKS:
                raise ValueError(f"PoolTeacher: {name} must be in [0, {2 ** NUM_TANKS}], "
                                 f"got {value}")
        if recheck_horizon < 1:
            raise ValueError(f"PoolTeacher: recheck_horizon must be >= 1, got {recheck_horizon}")
        if recheck_rule not in RECHECK_RULES:
            raise ValueError(f"PoolTeacher: recheck_rule must be one of {list(RECHECK_RULES)}, "
                             f"got {recheck_rule!r}")
        if min((hold, *extra_holds)) < 1:
            raise ValueError(f"PoolTeacher: holds must be >= 1 step, got {[hold, *extra_holds]}")
        if recheck and recheck_horizon <= horizon:
            raise ValueError(f"PoolTeacher: recheck_horizon ({recheck_horizon}) must be longer "
                             f"than the horizon ({horizon}), or nothing is rechecked")
        self.planners = [HoldPlanner(h, horizon)
                         for h in dict.fromkeys((hold, *extra_holds))]  # in order, once each
        self.planner = self.planners[0]
        self._plans: dict[int, np.ndarray] = {}  # horizon -> every planner's plans, stacked
        self.second_stage = second_stage
        self._two_stage: dict[int, np.ndarray] = {}  # horizon -> (64, 64, horizon, 6)
        self.recheck, self.recheck_horizon = recheck, recheck_horizon
        self.recheck_rule = recheck_rule
        self.horizon = horizon
        self.closed_form = closed_form
        self._evaluators: dict[int, tuple[Any, OracleEvaluator]] = {}
        self.labels = 0

    @classmethod
    def from_config(cls, config: Any) -> "PoolTeacher":
        """The teacher a training configuration names (its hold, horizon,
        extra_holds, second_stage, recheck, recheck_horizon and recheck_rule:
        a ``TrainingConfig``)."""
        return cls(config.hold, config.horizon, extra_holds=config.extra_holds,
                   second_stage=config.second_stage, recheck=config.recheck,
                   recheck_horizon=config.recheck_horizon, recheck_rule=config.recheck_rule)

    def forget(self) -> None:
        """Drop the per-env evaluators (the pool was reseeded with new plants)."""
        self._evaluators.clear()

    def _evaluator(self, env: int, scenario: Any) -> OracleEvaluator:
        kept = self._evaluators.get(env)
        if kept is None or kept[0] is not scenario:
            kept = (scenario, OracleEvaluator(scenario, closed_form=self.closed_form))
            self._evaluators[env] = kept
        return kept[1]

    def label(self, envs: Sequence[int], scenarios: Sequence[Any], operating_steps: np.ndarray,
              levels: np.ndarray) -> np.ndarray:
        """Valves (len(envs), 6) int8: the teacher's decision for env ``envs[k]``
        (scenario ``scenarios[envs[k]]``) at ``operating_steps[k]`` operating
        steps taken, levels ``levels[k]`` (6,) m."""
        return self.label_with_regrets(envs, scenarios, operating_steps, levels)[0]

    def label_with_regrets(self, envs: Sequence[int], scenarios: Sequence[Any],
                           operating_steps: np.ndarray, levels: np.ndarray,
                           seen_stuck: np.ndarray | None = None
                           ) -> tuple[np.ndarray, np.ndarray]:
        """(valves (len(envs), 6) int8, regrets (len(envs), 64) float32): the
        decision of :meth:`label` and, for each of the 64 settings a (valve i
        open iff bit i of a), the summed reward its plan loses against the
        best plan over the horizon (0 for the decision and its exact ties;
        a refused plan's: :func:`regrets_of`; with a recheck, where it runs:
        :meth:`_rechecked`'s, every setting not rechecked above 0).

        seen_stuck: (len(envs), 12), valves seen stuck closed then seen stuck
        open (> 0: seen; a student's stuck memory): the teacher then plans with
        those stuck valves only, every other valve as healthy, knowing what a
        controller that watches its valves knows (the rest of the physics stays
        the true one); None: with every valve stuck at that step."""
        out = np.zeros((len(envs), NUM_TANKS), np.int8)
        regrets = np.zeros((len(envs), 2 ** NUM_TANKS), np.float32)
        for k, env in enumerate(envs):
            scenario = scenarios[env]
            evaluator = self._evaluator(int(env), scenario)
            step = int(operating_steps[k])
            evaluator.set_step(step)
            if seen_stuck is not None:
                closed, opened = seen_stuck[k, :NUM_TANKS] > 0, seen_stuck[k, NUM_TANKS:] > 0
                mask = closed | opened
                evaluator.stuck = (mask, opened.astype(np.int64)) if mask.any() else None
            steps_left = scenario.steps_per_interval - step % scenario.steps_per_interval
            horizon = max(1, min(self.horizon, steps_left))
            x0 = np.asarray(levels[k], np.float64)
            totals = self._setting_totals(evaluator, x0, horizon)
            longer = min(self.recheck_horizon, steps_left)
            if self.recheck and longer > horizon:
                totals = self._rechecked(evaluator, x0, totals, longer)
            best = int(np.argmax(totals))  # the planner's rule: first maximum
            out[k] = self.planner.candidates(horizon)[best, 0]
            regrets[k] = regrets_of(totals)
        self.labels += len(envs)
        return out, regrets

    def _setting_totals(self, evaluator: OracleEvaluator, x0: np.ndarray, horizon: int
                        ) -> np.ndarray:
        """(64,) summed reward of each setting's best plan over ``horizon`` steps
        (row a: setting a, as every hold planner numbers them)."""
        totals = np.asarray(evaluator(x0, self._hold_plans(horizon)), np.float64)
        totals = totals.reshape(len(self.planners), -1).max(axis=0)
        first = self.planner.hold
        if self.second_stage and horizon > first:  # else no step is left for a second stage
            if horizon not in self._two_stage:
                self._two_stage[horizon] = two_stage_candidates(first, horizon)
            best = best_settings(totals, self.second_stage)
            plans = self._two_stage[horizon][best].reshape(-1, horizon, NUM_TANKS)
            staged = np.asarray(evaluator(x0, plans), np.float64).reshape(len(best), -1)
            totals[best] = np.maximum(totals[best], staged.max(axis=1))
        return totals

    def _rechecked(self, evaluator: OracleEvaluator, x0: np.ndarray, totals: np.ndarray,
                   horizon: int) -> np.ndarray:
        """(64,) values of the settings after the recheck, read as totals are
        (the largest is the label; a setting's regret is the largest minus its
        own): the ``recheck`` settings of the largest ``totals`` (ties at the
        cut to the lower code) valued by their best plan over ``horizon``
        steps, held each hold length then all closed (with ``recheck_rule``
        "balance": then the balance rule in closed loop; "best": the better of
        the two, and setting 0, all closed, rechecked too), less the best of
        those (so 0 for the label); every other setting at minus the larger of its
        own regret in ``totals`` and the largest regret among the rechecked,
        and below 0, so that the label is always a rechecked setting. The
        recheck values hold plans only: with a second stage, its values choose
        which settings are rechecked, not the label among them."""
        best = best_settings(totals, self.recheck)
        if self.recheck_rule == "best":  # doing nothing is always a candidate
            best = np.union1d(best, [CLOSED])
        long = np.full(len(best), -np.inf)
        if self.recheck_rule in ("balance", "best"):
            long = hold_then_rule(evaluator, x0, best, [p.hold for p in self.planners],
                                  horizon).max(axis=0)
        if self.recheck_rule in ("closed", "best"):
            plans = self._hold_plans(horizon).reshape(len(self.planners), -1, horizon,
                                                      NUM_TANKS)
            plans = plans[:, best].reshape(-1, horizon, NUM_TANKS)
            closed = np.asarray(evaluator(x0, plans), np.float64).reshape(len(self.planners), -1)
            long = np.maximum(long, closed.max(axis=0))
        if not np.isfinite(long).any():  # every long plan refused: the short values stand
            return totals
        rechecked = long - long.max()  # a refused long plan stays -inf
        # above 0 in the float32 regrets too (K = 1, or the K tie over the long horizon)
        floor = max(float(-rechecked[np.isfinite(rechecked)].min()),
                    float(np.finfo(np.float32).tiny))
        out = np.minimum(-regrets_of(totals), -floor)  # a refused short plan's: finite
        out[best] = rechecked
        return out

    def _hold_plans(self, horizon: int) -> np.ndarray:
        """Every hold planner's 64 plans over ``horizon`` steps, stacked in
        planner order ((planners * 64, horizon, 6)), built once per horizon."""
        if horizon not in self._plans:
            self._plans[horizon] = np.concatenate([p.candidates(horizon) for p in self.planners])
        return self._plans[horizon]


def hold_then_rule(evaluator: OracleEvaluator, x0: np.ndarray, settings: np.ndarray,
                   holds: Sequence[int], horizon: int, band: float = 0.1) -> np.ndarray:
    """Summed rewards (len(holds), len(settings)) over ``horizon`` steps from
    levels x0 on ``evaluator``'s physics: setting a (valve i open iff bit i of
    a) held h steps (h of ``holds``, at most the horizon), then the balance
    rule (:mod:`ftc.control.agents.balance`, with its ``band``) in closed loop,
    each step's valves from the levels the step before left. As the
    evaluator's rollouts: its stuck valves applied in place of the commands
    and the activity term charged for the commanded ones, a step after which
    the plant is terminal followed by full tanks, and a plan the integrator
    refuses -inf (counted once in ``evaluator.refused``; a plan refused in its
    hold is not continued).

    Each hold length's plans run as one batch rollout; the rule's steps run
    in C++ (``BatchRollout.run_balance_rule``, every plan's continuation in
    one call)."""
    p = evaluator.params
    height = np.asarray(p["height"], np.float64)
    if evaluator.stuck is None:
        mask, state = np.zeros(NUM_TANKS, np.int64), np.zeros(NUM_TANKS, np.int64)
    else:
        mask, state = evaluator.stuck
    x0 = np.asarray(x0, np.float64)
    codes = valve_settings()[np.asarray(settings, np.int64)]
    holds = [min(int(h), horizon) for h in holds]
    totals, states = [], []
    for hold in holds:  # each hold length's plans in one batch rollout
        commanded = np.repeat(codes[:, None, :], hold, axis=1)
        applied = np.where(mask, state, commanded)
        total, x = _held(evaluator, x0, applied, height)
        totals.append(charge_commanded(total, commanded, applied))
        states.append(x)
    # then the rule, every plan at once: row r has horizon - hold_r steps left
    total, x = np.concatenate(totals), np.concatenate(states)
    left = np.where(np.isfinite(total), horizon - np.repeat(np.array(holds), len(codes)), 0)
    after = np.asarray(evaluator.rollout.run_balance_rule(
        x, left, p, np.asarray(mask, np.int64), np.asarray(state, np.int64), band))
    evaluator.refused += int(np.isneginf(after).sum())
    return (total + after).reshape(len(holds), len(codes))


def _held(evaluator: OracleEvaluator, x0: np.ndarray, applied: np.ndarray,
          height: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(summed rewards (K,), levels after (K, 6)) of the valve sequences
    ``applied`` (K, L, 6) from x0 on the evaluator's physics, full tanks where
    the last step ended the episode; the batch at once, or where the
    integrator refuses it each plan alone, a refused one at -inf (counted in
    ``evaluator.refused``)."""
    p = evaluator.params
    try:
        runs = [(np.arange(len(applied)), evaluator.rollout.run(x0, applied, p, details=True))]
    except RuntimeError:
        runs = []
        for k in range(len(applied)):
            try:
                runs.append((np.array([k]), evaluator.rollout.run(x0, applied[k:k + 1], p,
                                                                  details=True)))
            except RuntimeError:
                evaluator.refused += 1
    total, x = np.full(len(applied), -np.inf), np.repeat(height[None], len(applied), axis=0)
    for rows, d in runs:
        total[rows] = d["total"]
        ended = np.asarray(d["terminal"], bool)[:, -1]
        x[rows] = np.where(ended[:, None], height, np.asarray(d["levels"])[:, -1])
    return total, x


def best_settings(totals: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` settings of the largest ``totals`` (ties at the cut to the
    lower code), in code order."""
    return np.sort(np.argsort(-totals, kind="stable")[:k])


def regrets_of(totals: np.ndarray) -> np.ndarray:
    """Regret (K,) of each plan of summed rewards ``totals`` (K,): the best total
    minus its own. A plan whose rollout the integrator refused scores -inf
    (``guarded_rollout``); its regret is the largest finite one of the state
    (as bad as the worst plan that ran), so that a student's loss on it stays
    finite."""
    with np.errstate(invalid="ignore"):  # every plan refused: -inf - -inf, handled below
        regrets = np.max(totals) - np.asarray(totals, np.float64)
    finite = np.isfinite(regrets)
    regrets[~finite] = regrets[finite].max() if finite.any() else 0.0
    return regrets
