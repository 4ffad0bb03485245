"""Guided PPO: the paper's scheme (PPO online on the plant, an offline phase
after every interval, nominal pretraining) with the offline phase guided by
a planner on a model of the plant (DAgger with the planner as the expert),
the policy refitted at once when the plant is seen to change within an
interval, and checked against the planner every few steps.

The model is the subclass's: ``ppo-robust`` (:mod:`ftc.control.agents.physics.ppo_robust`)
plans on the plant's physics with identified parameters; ``ppo-learned``
(:mod:`ftc.control.agents.learned.ppo_learned`) on a model learned from the observed
steps alone. This module holds what they share: the options of the guided fit
(:class:`GuidedConfig`), the online loop with its change and regret checks, the
guided fit itself and its plan cache. It knows no plant equations.
"""

from __future__ import annotations

import functools
import operator
import time
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar

import numpy as np
import torch

from ftc.common.cli import NONZERO, at_least, between
from ftc.common.constants import NUM_TANKS, offline_seed
from ftc.common.errors import CheckpointError
from ftc.control.run.agent import Agent, StepContext, Transition
from ftc.control.run.checkpoint import check_finite_state
from ftc.control.run.deferred import DeferredAgent
from ftc.control.run.metrics import PPO_COLUMNS, PPO_PROGRESS_KEYS
from ftc.control.planning.planners import Evaluator, HoldPlanner
from ftc.control.agents.ppo_online import OnlinePPO, PolicyConfig
from ftc.learning.distill import distill, distinct
from ftc.learning.ppo import PPO, PPOConfig
from ftc.plant.link import PlantObservation


@dataclass
class GuidedConfig(PolicyConfig):
    """A guided PPO run (ppo-robust, ppo-learned): the options of every PPO
    method and those of its guided fit."""

    #: options that act only with another's value (ftc.common.cli.unmet): the
    #: offline PPO phase runs only with offline steps, the regret check only
    #: every so many steps
    NEEDS: ClassVar[dict[str, Any]] = {
        **{name: ("offline_steps", NONZERO) for name in (
            "offline_envs", "offline_rollout", "offline_minibatch", "branch_fraction",
            "branch_steps")},
        "teacher_check_regret": ("teacher_check_every", NONZERO)}

    branch_fraction: float = field(default=0.5, metadata={"check": between(0.0, 1.0), "help": (
        "guided: share of offline episodes that start from a level observed on the "
        "plant (short branched rollouts) instead of full tanks")})
    teacher_states: int = field(default=2048, metadata={"check": at_least(2, 1_000_000), "help": (
        "guided: labelled levels the policy is fitted to (the most recent: first a "
        "sample of those observed on the plant, then those the policy visits on the model)")})
    teacher_rounds: int = field(default=3, metadata={"check": at_least(0, 100), "help": (
        "guided: DAgger rounds per interval (policy rollout on the model, labels, fit)")})
    teacher_refits: int = field(default=2, metadata={"check": at_least(0, 1000), "help": (
        "guided: refits of the policy within an interval when the plant is seen to change")})
    teacher_epochs: int = field(default=100, metadata={"check": at_least(1, 10_000), "help": (
        "guided: epochs of each fit to the labels (at most; see --teacher-stop-loss)")})
    teacher_stop_loss: float = field(default=0.002, metadata={"check": between(0.0, 10.0), "help": (
        "guided: end a fit early after an epoch whose mean cross-entropy per valve "
        "is below this (0: always --teacher-epochs; docs/controller.md)")})
    teacher_check_every: int = field(default=32, metadata={"check": at_least(0, 1_000_000), "help": (
        "guided: every this many steps on the plant, ask the planner (on its "
        "model of the plant) what the policy's choice at the current level costs; above "
        "--teacher-check-regret, refit the policy at once (at most --teacher-refits "
        "times per interval; 0: never check)")})
    teacher_check_regret: float = field(default=2.0, metadata={"check": between(0.0, 1e6), "help": (
        "guided: summed reward over the planner's horizon (L = 10 steps, about 25 "
        "at full tanks) that the policy's choice may lose against the planner's "
        "before a refit. Measured: a policy closing every valve with fuel stranded "
        "behind a dead pump loses 19; ordinary disagreements lose 0.06-0.5")})
    teacher_memory: int = field(default=1024, metadata={"check": at_least(0, 1_000_000), "help": (
        "guided: distinct levels labelled in earlier fits that each fit keeps, "
        "relabelled by the planner on the current parameters (DAgger's aggregated data: "
        "without it a fit forgets what earlier ones taught where it has no labels, e.g. "
        "fuel stranded behind a dead pump; 0: every fit starts afresh)")})
    teacher_sample: bool = field(default=True, metadata={"help": (
        "guided: the policy's DAgger rollouts on the model sample "
        "its actions, as it acts on the plant, so the labels cover the levels a "
        "sampled slip leads to (off: the deterministic policy)")})
    teacher_distinct: bool = field(default=False, metadata={"help": (
        "guided: fit to the distinct (level, label) pairs, each weighted by how often "
        "it was labelled (the same objective in fewer rows: an interval's episodes "
        "repeat their levels), instead of to every labelled level")})
    branch_steps: int = field(default=64, metadata={"check": at_least(1, 100_000), "help": (
        "guided: steps of a branched offline rollout")})


class ModelHooks(DeferredAgent):
    """What a guided agent's subclass supplies: the model the planner plans on,
    ``teacher_eval`` (the planner's evaluator), and the hooks: ``watch(t)``
    learns from one step on the plant and says whether it shows the plant
    changed; ``observed_levels()`` (N, 6) and ``steps_seen()``: this interval's;
    ``teacher_ready()``: the planner has a model; ``on_change()``: plan on the
    model as it is now; ``plan_key()``: what the planner's labels depend on and
    how two compare; ``rollout_env(seed)``: one env on the model for the
    policy's DAgger rollouts; ``end_model(interval)``: fit the model for the
    next interval, plan on it, return what was measured; ``offline(interval,
    observed)``: PPO on the model after the guided fit (reward per step,
    updates, refused steps); ``take_refused()``; ``(load_)model_state``."""

    teacher_eval: Evaluator

    def watch(self, t: Transition) -> bool: raise NotImplementedError
    def observed_levels(self) -> np.ndarray: raise NotImplementedError
    def plan_key(self) -> tuple[Any, Callable[[Any, Any], bool]]: raise NotImplementedError
    def rollout_env(self, seed: int) -> Any: raise NotImplementedError
    def end_model(self, interval: int) -> dict[str, Any]: raise NotImplementedError
    def model_state(self) -> dict[str, Any]: raise NotImplementedError
    def load_model_state(self, state: dict[str, Any]) -> None: raise NotImplementedError
    def on_change(self) -> None: pass
    def teacher_ready(self) -> bool: return True
    def take_refused(self) -> int: return 0

    def steps_seen(self) -> int: return len(self.observed_levels())
    def offline(self, interval: int, observed: np.ndarray) -> tuple[float, int, int]:
        return float("nan"), 0, 0


class GuidedPPOAgent(ModelHooks):
    """PPO online on the plant (its :class:`OnlinePPO`, as Algorithm 1's) with
    the planner-guided fit after every interval and when the plant changes
    within one (the module's docstring); on a real-time plant the fits run off
    the control loop (:class:`ftc.control.run.deferred.DeferredAgent`). The model
    comes from a subclass (:class:`ModelHooks`)."""

    extra_columns = (*PPO_COLUMNS, "distill_loss", "distill_agreement", "distill_epochs",
                     "teacher_labels", "teacher_plans", "teacher_memory", "teach_seconds",
                     "refit_seconds", "offline_model_errors", "guided_refits", "detected_changes",
                     "mispredicted_steps", "checks", "check_refits", "refused_rollouts",
                     "stuck_valves", "stuck_detected")
    progress_keys = PPO_PROGRESS_KEYS
    Config = GuidedConfig
    parts = {"ppo": (PPOConfig, "ppo-")}

    def __init__(self, cfg: GuidedConfig, ppo_config: PPOConfig) -> None:
        super().__init__(cfg.seed)
        self.cfg = cfg
        self.ppo = PPO(ppo_config, seed=cfg.seed)
        self.online = OnlinePPO(self.ppo, cfg.update_every)
        self.refits, self.teacher = 0, HoldPlanner(3, 10)  # the oracle MPC's planner (H3, L10)
        # distinct levels labelled by earlier fits, most recent last (DAgger's aggregate)
        self.memory = np.empty((0, NUM_TANKS))
        self.plan_cache = PlanCache()

    @classmethod
    def from_configs(cls, configs: dict[str, Any]) -> "GuidedPPOAgent":
        return cls(configs["controller"], configs["ppo"])

    # -- the loop -------------------------------------------------------------------
    def prepare(self) -> dict[str, Any]:
        """Pretrain the policy (--pretrain)."""
        cfg = self.cfg
        return (self.online.pretrain(cfg.pretrain_settings(), cfg.pretrain_cache,
                                     cfg.fresh_optimizer) if cfg.pretrain else {})

    def _begin_interval(self, interval: int) -> None:
        self.online.begin_interval(self.background_learning)
        self.refits = 0
        self.interval = interval
        self.checks, self.check_refits = 0, 0

    def _act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        return self.online.act(obs, ctx)

    def _observe(self, t: Transition) -> None:
        stats = self.online.observe(t)
        if stats is not None:
            self.telemetry.update(stats._asdict())
        cfg = self.cfg
        changed = self.watch(t)
        if changed and self.refits < cfg.teacher_refits:
            # the plant changed (the interval boundary, an abrupt fault): fit the policy
            # to the planner on the plant as it is now, at once; the partial rollout was
            # collected by the old policy, so it is dropped rather than used off-policy
            self.refits += 1
            self.on_change()
            self._refit(self.interval * 1000 + self.refits)
        elif (cfg.teacher_check_every and self.steps_seen() % cfg.teacher_check_every == 0
              and self.check_refits < cfg.teacher_refits and self.teacher_ready()):
            # the policy where the plant is, checked against the planner: a level no
            # fit labelled can be one the policy never leaves (fuel stranded behind a
            # dead pump with every valve closed earns 0 per step for good)
            self.checks += 1
            level = np.asarray(t.following.level, np.float64)
            if regret(self.ppo, self.teacher, self.teacher_eval, level) > cfg.teacher_check_regret:
                self.check_refits += 1
                # one DAgger round: what it must learn is at the levels already seen
                self._refit(self.interval * 1000 + 100 + self.check_refits, rounds=1)

    def _refit(self, fit_id: int, rounds: int | None = None) -> None:
        """A guided fit within the interval, from the levels observed in it so far."""
        def refit() -> dict[str, Any]:
            metrics = self._guided_fit(self.observed_levels(), fit_id, rounds)
            self.online.drop_rollout()  # collected by the policy before the fit
            return metrics
        self.learn(refit)

    def _end_online(self) -> dict[str, Any]: return self.online.end_online()
    def _finish(self) -> None: self.online.finish()  # a background update in flight
    def _close(self) -> None: self.online.close()
    def acting_policy(self) -> Any: return self.ppo.policy

    def end_interval(self, interval: int, data: Any) -> dict[str, Any]:
        self._poll(wait=True)  # a refit still running, and the steps queued behind it
        return self.learn(lambda: self._end_interval(interval), interval) or {}

    def _end_interval(self, interval: int) -> dict[str, Any]:
        start = time.perf_counter()
        model_metrics = self.end_model(interval)  # the planner now plans for the next interval
        observed = self.observed_levels()
        refit_seconds = time.perf_counter() - start
        # guided: the planner on the model labels the levels the policy meets
        metrics = self._guided_fit(observed, interval)
        teach_seconds = time.perf_counter() - start - refit_seconds
        refused = self.take_refused()  # this interval's
        rew, updates, errors = self.offline(interval, observed)
        check_finite_state(self.ppo.policy.state_dict(),
                           f"policy weights after the offline phase of interval {interval}")
        return {**metrics, **model_metrics, "offline_reward_per_step": rew,
                "offline_updates": updates, "refit_seconds": refit_seconds,
                "teach_seconds": teach_seconds,
                "offline_seconds": time.perf_counter() - start, "policy_swaps": 0,
                "guided_refits": self.refits, "checks": self.checks,
                "check_refits": self.check_refits, "offline_model_errors": errors,
                "refused_rollouts": refused}

    def _guided_fit(self, observed: np.ndarray, interval: int,
                    rounds: int | None = None) -> dict[str, Any]:
        """DAgger with the planner as the expert: start from a sample of the levels
        observed on the plant; each round, run the current policy (its actions
        sampled, or greedy with --no-teacher-sample) on the model for
        an interval (``rounds`` rounds if given), add the levels it visits, have
        the planner label the new ones, and fit the policy to all labels (the last
        ``teacher_states``, plus up to ``teacher_memory`` distinct levels of earlier
        fits, relabelled for the current parameters). Measured on the single fault
        at age 2: three rounds of 100 epochs make the policy act exactly as the
        planner (2.5845 per step against 2.5845; one round of 30 epochs: 2.518).

        The memory is DAgger's aggregation across fits. Without it a refit after a
        change within the interval (from the few levels seen since) kept no label
        where fuel is stranded behind a dead pump, which the fit before had taught
        (random-19, seed 2, interval 7: the policy then closed every valve there
        for the rest of the interval, 0.24 of the oracle)."""
        self.online.finish()  # an update in flight would overwrite the fit when taken in
        cfg = self.cfg
        seed = offline_seed(cfg.seed, interval)
        rng = np.random.default_rng(seed)
        start = observed[rng.choice(len(observed), min(cfg.teacher_states // 2, len(observed)),
                                    replace=False)]
        # An interval's episodes all start from full tanks and repeat one another:
        # its 1,024-2,048 labelled levels held 55-124 distinct ones, each planned once
        plans: dict[bytes, np.ndarray] = {}  # this fit's labels (teacher_plans: how many)
        self.plan_cache.begin(*self.plan_key())
        label = functools.partial(self.plan_cache.label, self.teacher, self.teacher_eval,
                                  plans=plans)
        carried = self.memory
        carried_labels = label(carried)
        states, labels = start, label(start)
        metrics: dict[str, Any] = {}
        env = self.rollout_env(seed)
        generator_state = self.ppo.generator.get_state()  # the online sampling stream
        self.ppo.generator.manual_seed(seed)
        for _ in range(cfg.teacher_rounds if rounds is None else rounds):
            obs, visited = env.reset(), []
            with torch.no_grad():
                for _ in range(cfg.steps_per_interval):
                    visited.append(obs[0].numpy().astype(np.float64))
                    actions, _, _ = self.ppo.act(obs, deterministic=not cfg.teacher_sample)
                    obs = env.step(actions).obs
            visited = np.array(visited)
            states = np.concatenate([states, visited])[-cfg.teacher_states:]
            labels = np.concatenate([labels, label(visited)])[-cfg.teacher_states:]
            all_states = np.concatenate([carried, states])
            all_labels = np.concatenate([carried_labels, labels])
            if cfg.teacher_distinct:
                rows, acts, counts = distinct(all_states, all_labels)
            else:
                rows, acts, counts = (torch.as_tensor(all_states, dtype=torch.float32),
                                      torch.as_tensor(all_labels, dtype=torch.float32), None)
            metrics = distill(self.ppo, rows, acts, epochs=cfg.teacher_epochs, seed=seed,
                              stop_loss=cfg.teacher_stop_loss, weights=counts)
        self.ppo.generator.set_state(generator_state)
        self.plan_cache.labels.update(plans)
        self.memory = _recent_distinct(np.concatenate([carried, states]), cfg.teacher_memory)
        metrics["teacher_labels"], metrics["teacher_plans"] = len(carried) + len(states), len(plans)
        metrics["teacher_memory"] = len(carried)
        # Adam's moments belong to the weights before the fit: carried over, they make
        # the next online update jump (measured: approx-KL 0.8-3.8 per update)
        self.ppo.reset_optimizer()
        return metrics

    def _state_dict(self) -> dict[str, Any]:
        return {"ppo": self.online.state_dict(), **self.model_state(),
                "teacher_memory": self.memory.tolist()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        missing = sorted({"ppo", "teacher_memory"} - set(state))
        if missing:
            raise CheckpointError(f"checkpoint lacks the agent's {', '.join(missing)}")
        self.online.load_state_dict(state["ppo"])
        self.load_model_state(state)
        memory = np.asarray(state["teacher_memory"], dtype=np.float64)
        self.memory = memory.reshape(-1, NUM_TANKS)


class PlanCache:
    """The planner's labels by level for the model (parameters and stuck valves,
    or a learned model's version) they were planned on: a refit after a check
    plans on the model of the fit before it, and would relabel that fit's levels
    (the memory) to the same labels."""

    def __init__(self) -> None:
        self.labels: dict[bytes, np.ndarray] = {}
        self.planned_for: Any = None

    def begin(self, planned_for: Any, same: Callable[[Any, Any], bool] = operator.eq) -> None:
        """Keep the labels if they were planned on ``planned_for`` (as ``same``
        compares), else drop them."""
        if self.planned_for is None or not same(self.planned_for, planned_for):
            self.labels, self.planned_for = {}, planned_for

    def label(self, planner: HoldPlanner, evaluate: Evaluator, states: np.ndarray,
              plans: dict[bytes, np.ndarray]) -> np.ndarray:
        """``planner``'s first valves (N, 6) on ``evaluate`` at each of ``states``
        (N, 6); ``plans`` (a fit's) caches them by level (the planner is
        deterministic for fixed parameters), taking those an earlier fit planned
        on the same parameters from :attr:`labels`."""
        out = np.empty((len(states), NUM_TANKS))
        for n, x in enumerate(states):
            key = x.tobytes()
            if key not in plans:
                label = self.labels.get(key)
                plans[key] = planner.plan(evaluate, x)[0] if label is None else label
            out[n] = plans[key]
        return out


def _recent_distinct(states: np.ndarray, limit: int) -> np.ndarray:
    """The last ``limit`` distinct rows of ``states`` (N, 6), in the order of their
    last occurrence (most recent last)."""
    if limit == 0:
        return states[:0]
    last: dict[bytes, int] = {}
    for n, x in enumerate(states):
        last[x.tobytes()] = n
    keep = sorted(last.values())[-limit:]
    return states[keep]


def regret(ppo: Any, planner: HoldPlanner, evaluate: Evaluator, level: np.ndarray) -> float:
    """Summed reward over the planner's horizon that the policy's deterministic
    choice at ``level`` loses against the planner's best (its hold-then-close
    candidates on ``evaluate``; 0 when they agree)."""
    candidates = planner.candidates(planner.horizon)
    totals = evaluate(level, candidates)
    with torch.no_grad():
        mine, _, _ = ppo.act(torch.as_tensor(level, dtype=torch.float32)[None], deterministic=True)
    row = int(np.flatnonzero((candidates[:, 0] == mine[0].numpy()).all(axis=1))[0])
    loss = float(np.max(totals) - totals[row])
    return loss if np.isfinite(loss) else 0.0
