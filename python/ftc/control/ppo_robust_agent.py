"""``ppo-robust``: the paper's scheme (PPO online on the plant, offline on a
model refitted after every interval, nominal pretraining) with the changes
that made it hold up on faults it was never tuned on (docs/controller.md):

* the offline model is the plant's physics with its parameters identified
  from the interval's data (:mod:`ftc.learning.identify`; it assumes the
  plant's structure), extrapolated one interval ahead, so the offline phase
  trains for the plant the next interval will meet, not the one just left;
  and when the one-step prediction error shows that the plant changed (the
  interval boundary, an abrupt fault) the parameters are re-identified and
  the policy refitted at once, within the interval;
* guided offline training (DAgger with a planner as the expert): the oracle's
  planner, run on the identified physics, labels levels the policy will meet
  (a sample of those observed on the plant, then, round by round, those the
  current policy visits on the model), and the policy is fitted to those
  decisions (:mod:`ftc.learning.distill`); then, optionally
  (``--offline-steps``), PPO on the identified physics, half of its episodes
  short branches from observed levels (MBPO).

    python -m ftc.controller --method ppo-robust --pretrain --offline-steps 16384 ...
"""

from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ftc.common.cli import at_least, between
from ftc.common.constants import NUM_TANKS, offline_seed
from ftc.common.errors import CheckpointError
from ftc.control.agent import Agent, StepContext, Transition
from ftc.control.checkpoint import check_finite_state
from ftc.control.physics_evaluators import ParamsEvaluator
from ftc.control.planners import HoldPlanner
from ftc.control.metrics import PPO_COLUMNS, PPO_PROGRESS_KEYS
from ftc.control.ppo_agent import ControllerConfig
from ftc.control.ppo_online import OnlinePPO
from ftc.learning.distill import distill, distinct
from ftc.learning.identify import Identifier, OnlineIdentification
from ftc.learning.physics_env import PhysicsEnv
from ftc.learning.ppo import PPO, PPOConfig
from ftc.learning.rollout import train_on_env
from ftc.learning.transitions import Transitions
from ftc.plant.link import PlantObservation


@dataclass
class RobustConfig(ControllerConfig):
    """A ppo-robust run: the controller's options and those of its guided fit."""

    branch_fraction: float = field(default=0.5, metadata={"check": between(0.0, 1.0), "help": (
        "ppo-robust: share of offline episodes that start from a level observed on the "
        "plant (short branched rollouts) instead of full tanks")})
    teacher_states: int = field(default=2048, metadata={"check": at_least(2, 1_000_000), "help": (
        "ppo-robust: labelled levels the policy is fitted to (the most recent: first a "
        "sample of those observed on the plant, then those the policy visits on the model)")})
    teacher_rounds: int = field(default=3, metadata={"check": at_least(0, 100), "help": (
        "ppo-robust: DAgger rounds per interval (policy rollout on the model, labels, fit)")})
    teacher_refits: int = field(default=2, metadata={"check": at_least(0, 1000), "help": (
        "ppo-robust: refits of the policy within an interval when the plant is seen to change")})
    teacher_epochs: int = field(default=100, metadata={"check": at_least(1, 10_000), "help": (
        "ppo-robust: epochs of each fit to the labels (at most; see --teacher-stop-loss)")})
    teacher_stop_loss: float = field(default=0.002, metadata={"check": between(0.0, 10.0), "help": (
        "ppo-robust: end a fit early after an epoch whose mean cross-entropy per valve "
        "is below this (0: always --teacher-epochs; docs/controller.md)")})
    teacher_check_every: int = field(default=32, metadata={"check": at_least(0, 1_000_000), "help": (
        "ppo-robust: every this many steps on the plant, ask the planner (on the "
        "identified physics) what the policy's choice at the current level costs; above "
        "--teacher-check-regret, refit the policy at once (at most --teacher-refits "
        "times per interval; 0: never check)")})
    teacher_check_regret: float = field(default=2.0, metadata={"check": between(0.0, 1e6), "help": (
        "ppo-robust: summed reward over the planner's horizon (L = 10 steps, about 25 "
        "at full tanks) that the policy's choice may lose against the planner's "
        "before a refit. Measured: a policy closing every valve with fuel stranded "
        "behind a dead pump loses 19; ordinary disagreements lose 0.06-0.5")})
    teacher_memory: int = field(default=1024, metadata={"check": at_least(0, 1_000_000), "help": (
        "ppo-robust: distinct levels labelled in earlier fits that each fit keeps, "
        "relabelled by the planner on the current parameters (DAgger's aggregated data: "
        "without it a fit forgets what earlier ones taught where it has no labels, e.g. "
        "fuel stranded behind a dead pump; 0: every fit starts afresh)")})
    teacher_sample: bool = field(default=True, metadata={"help": (
        "ppo-robust: the policy's DAgger rollouts on the identified physics sample "
        "its actions, as it acts on the plant, so the labels cover the levels a "
        "sampled slip leads to (off: the deterministic policy)")})
    teacher_distinct: bool = field(default=False, metadata={"help": (
        "ppo-robust: fit to the distinct (level, label) pairs, each weighted by how often "
        "it was labelled (the same objective in fewer rows: an interval's episodes "
        "repeat their levels), instead of to every labelled level")})
    branch_steps: int = field(default=64, metadata={"check": at_least(1, 100_000), "help": (
        "ppo-robust: steps of a branched offline rollout")})

# the options only ppo-robust reads
ROBUST_FIELDS = tuple(f.name for f in dataclasses.fields(RobustConfig)
                      if f.name not in {g.name for g in dataclasses.fields(ControllerConfig)})


class RobustPPOAgent(Agent):
    """PPO online on the plant (its :class:`OnlinePPO`, as Algorithm 1's) with
    the identified physics and the planner-guided fit after every interval and
    when the plant changes within one (the module's docstring)."""

    name = "ppo-robust"
    extra_columns = (*PPO_COLUMNS, "distill_loss", "distill_agreement", "distill_epochs",
                     "teacher_labels", "teacher_plans", "teacher_memory", "teach_seconds",
                     "refit_seconds", "offline_model_errors", "guided_refits", "detected_changes",
                     "mispredicted_steps", "checks", "check_refits", "refused_rollouts")
    progress_keys = PPO_PROGRESS_KEYS

    def __init__(self, cfg: RobustConfig, ppo_config: PPOConfig) -> None:
        from ftc import _core  # native: the plant's integrator for the teacher's rollouts

        self.cfg = cfg
        self.ppo = PPO(ppo_config, seed=cfg.seed)
        self.online = OnlinePPO(self.ppo, cfg.update_every)
        self.online_id = OnlineIdentification(Identifier(seed=cfg.seed), trigger=1e-4, every=0)
        self.refits = 0
        self.teacher = HoldPlanner(3, 10)  # the oracle MPC's planner (H = 3, L = 10)
        self.teacher_eval = ParamsEvaluator(_core.BatchRollout(rtol=1e-6, atol=1e-8,
                                                             exact_active_conduit=True))
        # distinct levels labelled by earlier fits, most recent last (DAgger's aggregate)
        self.memory = np.empty((0, NUM_TANKS))
        self.plan_cache = PlanCache()

    @classmethod
    def from_configs(cls, configs: dict[str, Any]) -> "RobustPPOAgent":
        return cls(configs["controller"], configs["ppo"])

    def prepare(self) -> dict[str, Any]:
        """Pretrain the policy (--pretrain); no world model to pretrain."""
        cfg = self.cfg
        return (self.online.pretrain(cfg.pretrain_settings(), cfg.pretrain_cache,
                                     cfg.fresh_optimizer) if cfg.pretrain else {})

    def begin_interval(self, interval: int) -> None:
        self.online.begin_interval()
        self.online_id.begin()
        self.refits = 0
        self.interval = interval
        self.checks, self.check_refits = 0, 0

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        return self.online.act(obs, ctx)

    def observe(self, t: Transition) -> None:
        stats = self.online.observe(t)
        if stats is not None:
            self.telemetry.update(stats._asdict())
        cfg = self.cfg
        changed = self.online_id.add(t.obs.level, t.next_obs.valves, t.next_obs.level,
                                     t.next_obs.deficit)  # the valves the plant applied
        if changed and self.refits < cfg.teacher_refits:
            # the plant changed (the interval boundary, an abrupt fault): fit the policy
            # to the planner on the plant as it is now, at once; the partial rollout was
            # collected by the old policy, so it is dropped rather than used off-policy
            self.refits += 1
            self.teacher_eval.params = self.online_id.params.as_core()
            self._refit(self.interval * 1000 + self.refits)
        elif (cfg.teacher_check_every and len(self.online_id.rows) % cfg.teacher_check_every == 0
              and self.check_refits < cfg.teacher_refits
              and self.teacher_eval.params is not None):  # identified at least once
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
        observed = np.array([r[2] for r in self.online_id.rows])
        self._guided_fit(observed, fit_id, rounds)
        self.online.drop_rollout()

    def end_online(self) -> dict[str, Any]:
        return self.online.end_online()

    def end_interval(self, interval: int, data: Transitions | None) -> dict[str, Any]:
        cfg, start = self.cfg, time.perf_counter()
        params, rms = self.online_id.end()
        ahead = self.online_id.ahead()
        next_level = np.array([r[2] for r in self.online_id.rows])
        refit_seconds = time.perf_counter() - start
        # guided: the planner on the identified physics labels the levels the policy meets
        self.teacher_eval.params = ahead.as_core()
        metrics = self._guided_fit(next_level, interval)
        teach_seconds = time.perf_counter() - start - refit_seconds
        refused, self.teacher_eval.refused = self.teacher_eval.refused, 0  # this interval's
        rew, updates, errors = float("nan"), 0, 0
        if cfg.offline_steps:  # then PPO on the identified physics (also fits the critic)
            rew, updates, errors = _ppo_on_physics(self.ppo, cfg, ahead.as_core(), next_level,
                                                   interval)
        check_finite_state(self.ppo.policy.state_dict(),
                           f"policy weights after the offline phase of interval {interval}")
        return {**metrics, "model_one_step_rmse": rms, "offline_reward_per_step": rew,
                "offline_updates": updates, "refit_seconds": refit_seconds,
                "teach_seconds": teach_seconds,
                "offline_seconds": time.perf_counter() - start, "policy_swaps": 0,
                "guided_refits": self.refits, "detected_changes": self.online_id.changes,
                "mispredicted_steps": self.online_id.mispredicted,
                "checks": self.checks, "check_refits": self.check_refits,
                "offline_model_errors": errors, "refused_rollouts": refused}

    def _guided_fit(self, observed: np.ndarray, interval: int,
                    rounds: int | None = None) -> dict[str, Any]:
        """DAgger with the planner as the expert: start from a sample of the levels
        observed on the plant; each round, run the current policy (its actions
        sampled, or greedy with --no-teacher-sample) on the identified physics for
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
        cfg = self.cfg
        seed = offline_seed(cfg.seed, interval)
        rng = np.random.default_rng(seed)
        start = observed[rng.choice(len(observed), min(cfg.teacher_states // 2, len(observed)),
                                    replace=False)]
        # An interval's episodes all start from full tanks and repeat one another:
        # its 1,024-2,048 labelled levels held 55-124 distinct ones, each planned once
        plans: dict[bytes, np.ndarray] = {}  # this fit's labels (teacher_plans: how many)
        self.plan_cache.begin(self.teacher_eval)
        label = functools.partial(self.plan_cache.label, self.teacher, self.teacher_eval,
                                  plans=plans)
        carried = self.memory
        carried_labels = label(carried)
        states, labels = start, label(start)
        metrics: dict[str, Any] = {}
        env = PhysicsEnv(self.teacher_eval.params, 1, max_episode_steps=cfg.steps_per_interval,
                         seed=seed)
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

    def state_dict(self) -> dict[str, Any]:
        # model .. pending: PPOAgent's entries (world model, refit window, background
        # phase), empty here, which ppo-robust checkpoints carried when this class
        # inherited PPOAgent: still written, so checkpoints stay as they were; not read
        return {"ppo": self.online.state_dict(),
                "model": None, "model_fits": 0, "window": [], "pending": None,
                "identification": self.online_id.state_dict(),
                "teacher_memory": self.memory.tolist()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        missing = sorted({"ppo", "identification", "teacher_memory"} - set(state))
        if missing:
            raise CheckpointError(f"checkpoint lacks the agent's {', '.join(missing)}")
        self.online.load_state_dict(state["ppo"])
        self.online_id.load_state_dict(state["identification"])
        memory = np.asarray(state["teacher_memory"], dtype=np.float64)
        self.memory = memory.reshape(-1, NUM_TANKS)


def _ppo_on_physics(ppo: PPO, cfg: RobustConfig, params: dict, starts: np.ndarray,
                    interval: int) -> tuple[float, int, int]:
    """PPO for ``cfg.offline_steps`` steps on the identified physics ``params``
    (``cfg.branch_fraction`` of its episodes branched from ``starts``, levels
    (N, 6) observed on the plant), on a stream of its own and with the offline
    minibatch size, both restored after. Returns the mean reward per step, the
    number of updates and the steps the integrator refused."""
    env = PhysicsEnv(params, cfg.offline_envs, max_episode_steps=cfg.steps_per_interval,
                     starts=starts, branch_fraction=cfg.branch_fraction,
                     branch_steps=cfg.branch_steps, seed=offline_seed(cfg.seed, interval))
    online_config = ppo.config
    generator_state = ppo.generator.get_state()
    ppo.generator.manual_seed(offline_seed(cfg.seed, interval))
    ppo.config = dataclasses.replace(online_config, minibatch_size=cfg.offline_minibatch)
    try:
        stats, rew, _ = train_on_env(ppo, env, cfg.offline_steps, cfg.offline_rollout)
    finally:
        ppo.config = online_config
        ppo.generator.set_state(generator_state)
    return rew, len(stats), env.errors


class PlanCache:
    """The planner's labels by level for the parameters (and stuck valves) they
    were planned with: a refit after a check plans on the parameters of the fit
    before it, and would relabel that fit's levels (the memory) to the same labels."""

    def __init__(self) -> None:
        self.labels: dict[bytes, np.ndarray] = {}
        self.planned_for: tuple[dict | None, dict[int, int]] = (None, {})

    def begin(self, evaluate: ParamsEvaluator) -> None:
        """Keep the labels if ``evaluate`` plans as they were planned, else drop them."""
        planned_for = (evaluate.params, dict(evaluate.stuck))
        if not (_same_params(self.planned_for[0], planned_for[0])
                and self.planned_for[1] == planned_for[1]):
            self.labels, self.planned_for = {}, planned_for

    def label(self, planner: HoldPlanner, evaluate: ParamsEvaluator, states: np.ndarray,
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


def _same_params(a: dict | None, b: dict | None) -> bool:
    """Whether two parameter dicts (as ``_core`` takes them) hold equal values."""
    if a is None or b is None:
        return a is b
    return a is b or (a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a))


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


def regret(ppo: Any, planner: HoldPlanner, evaluate: ParamsEvaluator, level: np.ndarray) -> float:
    """Summed reward over the planner's horizon that the policy's deterministic
    choice at ``level`` loses against the planner's best (its hold-then-close
    candidates on ``evaluate``'s parameters; 0 when they agree)."""
    candidates = planner.candidates(planner.horizon)
    totals = evaluate(level, candidates)
    with torch.no_grad():
        mine, _, _ = ppo.act(torch.as_tensor(level, dtype=torch.float32)[None], deterministic=True)
    row = int(np.flatnonzero((candidates[:, 0] == mine[0].numpy()).all(axis=1))[0])
    loss = float(np.max(totals) - totals[row])
    return loss if np.isfinite(loss) else 0.0
