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
from typing import Any, Callable

import numpy as np

from ftc.common.constants import offline_seed
from ftc.common.errors import CheckpointError
from ftc.control.run.agent import Transition
from ftc.control.agents.learned.guided_ppo import GuidedConfig, GuidedPPOAgent
from ftc.control.planning.physics.evaluators import ParamsEvaluator
from ftc.learning.identify import Identifier, OnlineIdentification
from ftc.learning.physics_env import PhysicsEnv
from ftc.learning.ppo import PPO, PPOConfig
from ftc.learning.rollout import train_on_env
from ftc.learning.stuck import StuckValves



class RobustPPOAgent(GuidedPPOAgent):
    """Guided PPO (:class:`GuidedPPOAgent`) whose planner plans on the plant's
    physics with parameters identified from the observed steps, extrapolated one
    interval ahead at each interval's end (the module's docstring)."""

    name = "ppo-robust"

    def __init__(self, cfg: GuidedConfig, ppo_config: PPOConfig) -> None:
        from ftc import _core  # native: the plant's integrator for the teacher's rollouts

        super().__init__(cfg, ppo_config)
        self.online_id = OnlineIdentification(Identifier(seed=cfg.seed), trigger=1e-4, every=0)
        self.teacher_eval = ParamsEvaluator(_core.BatchRollout(rtol=1e-6, atol=1e-8,
                                                             exact_active_conduit=True))
        self.stuck = StuckValves()
        self.teacher_eval.stuck = self.stuck.stuck  # the teacher plans them as they will be

    def _begin_interval(self, interval: int) -> None:
        super()._begin_interval(interval)
        self.online_id.begin()

    def watch(self, t: Transition) -> bool:
        stuck = self.stuck.observe(t.valves, t.next_obs.valves, t.obs.operating_steps)
        refitted = self.online_id.add(t.obs.level, t.next_obs.valves, t.next_obs.level,
                                      t.next_obs.deficit)  # the valves the plant applied
        if stuck:
            # a valve newly stuck changes every plan the teacher makes: refit the policy
            # at once, outside the --teacher-refits budget (a change's refits may have
            # spent it; at most six valves can stick)
            self.on_change()
            self._refit(self.interval * 1000 + 500 + len(self.stuck.detections))
            return False
        return refitted

    def observed_levels(self) -> np.ndarray:
        return np.array([r[2] for r in self.online_id.rows])

    def steps_seen(self) -> int:
        return len(self.online_id.rows)

    def teacher_ready(self) -> bool:
        return self.teacher_eval.params is not None  # identified at least once

    def on_change(self) -> None:
        self.teacher_eval.params = self.online_id.params.as_core()

    def plan_key(self) -> tuple[Any, Callable[[Any, Any], bool]]:
        return (self.teacher_eval.params, dict(self.teacher_eval.stuck)), _same_plan

    def rollout_env(self, seed: int) -> PhysicsEnv:
        return PhysicsEnv(self.teacher_eval.params, 1,
                          max_episode_steps=self.cfg.steps_per_interval, seed=seed,
                          stuck=self.stuck.stuck)

    def end_model(self, interval: int) -> dict[str, Any]:
        params, rms = self.online_id.end()
        self.ahead = self.online_id.ahead()
        self.teacher_eval.params = self.ahead.as_core()
        return {"model_one_step_rmse": rms, "detected_changes": self.online_id.changes,
                "mispredicted_steps": self.online_id.mispredicted, **self.stuck.metrics()}

    def offline(self, interval: int, observed: np.ndarray) -> tuple[float, int, int]:
        if not self.cfg.offline_steps:  # then PPO on the identified physics (also fits the critic)
            return float("nan"), 0, 0
        return _ppo_on_physics(self.ppo, self.cfg, self.ahead.as_core(), observed, interval,
                               self.stuck.stuck)

    def take_refused(self) -> int:
        refused, self.teacher_eval.refused = self.teacher_eval.refused, 0
        return refused

    def model_state(self) -> dict[str, Any]:
        # model .. pending: PPOAgent's entries (world model, refit window, background
        # phase), empty here, which ppo-robust checkpoints carried when this class
        # inherited PPOAgent: still written, so checkpoints stay as they were; not read
        return {"model": None, "model_fits": 0, "window": [], "pending": None,
                "identification": self.online_id.state_dict(), "stuck": self.stuck.state_dict()}

    def load_model_state(self, state: dict[str, Any]) -> None:
        if "identification" not in state:
            raise CheckpointError("checkpoint lacks the agent's identification")
        self.online_id.load_state_dict(state["identification"])
        self.stuck.load_state_dict(state.get("stuck", {}))  # none in older checkpoints


def _ppo_on_physics(ppo: PPO, cfg: GuidedConfig, params: dict, starts: np.ndarray,
                    interval: int, stuck: dict[int, int]) -> tuple[float, int, int]:
    """PPO for ``cfg.offline_steps`` steps on the identified physics ``params``
    (``cfg.branch_fraction`` of its episodes branched from ``starts``, levels
    (N, 6) observed on the plant; valves ``stuck`` as they will be), on a
    stream of its own and with the offline minibatch size, both restored after. Returns the mean reward per step, the
    number of updates and the steps the integrator refused."""
    env = PhysicsEnv(params, cfg.offline_envs, max_episode_steps=cfg.steps_per_interval,
                     starts=starts, branch_fraction=cfg.branch_fraction,
                     branch_steps=cfg.branch_steps, seed=offline_seed(cfg.seed, interval),
                     stuck=stuck)
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


def _same_plan(a: tuple[dict | None, dict[int, int]], b: tuple[dict | None, dict[int, int]]
               ) -> bool:
    """Whether two (parameters, stuck valves) plan the same: equal values."""
    return _same_params(a[0], b[0]) and a[1] == b[1]


def _same_params(a: dict | None, b: dict | None) -> bool:
    """Whether two parameter dicts (as ``_core`` takes them) hold equal values."""
    if a is None or b is None:
        return a is b
    return a is b or (a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a))
