"""PPO on the plant, the part every agent with a policy shares: a learner's
rollout collector, acting on the plant and updating every t_update real
steps, the interval's update statistics, nominal pretraining, and the
learner's entry of a checkpoint. Each agent holds its learner and one of
these, and adds its own offline phase: :class:`ftc.control.agents.ppo.PPOAgent`
(Algorithm 1, the world model), :class:`ftc.control.agents.physics.ppo_robust.RobustPPOAgent`
(the identified physics and a planner).
"""

from __future__ import annotations

import concurrent.futures
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch

from ftc.common.cli import NONZERO, at_least, between, positive
from ftc.common.constants import DEFAULT_LCM_URL
from ftc.common.errors import CheckpointError
from ftc.control.run import checkpoint
from ftc.control.run.agent import StepContext, Transition
from ftc.control.run.checkpoint import check_finite_state, check_update
from ftc.control.run.config import MAX_STEPS_PER_INTERVAL, RunConfig
from ftc.control.run.metrics import mean
from ftc.learning.buffer import RolloutBuffer
from ftc.learning.ppo import PPO, UpdateStats
from ftc.learning.pretrain import PretrainSettings, pretrain_cached
from ftc.plant.lcm_link import check_loopback_url
from ftc.plant.signing import load_key
from ftc.learning.rollout import RolloutCollector
from ftc.plant.link import PlantObservation

# what end_online reports: the means over the interval's updates
ONLINE_METRICS = ("entropy", "open_fraction", "approx_kl", "clipfrac", "explained_variance",
                  "value_loss")



@dataclass
class PolicyConfig(RunConfig):
    """The options of every method with a PPO policy (ppo and its variants,
    ppo-robust, ppo-learned), beside its PPO hyperparameters (--ppo-*:
    :class:`ftc.learning.ppo.PPOConfig`): updates, the offline phase's PPO,
    pretraining, pushing the policy."""

    #: options no longer offered (they measured worse: docs/controller.md), with the
    #: value that does what the controller does now: a stored config.json that
    #: holds that value resumes, any other is refused (tools/run_cli.py)
    RETIRED_FIELDS: ClassVar[dict[str, Any]] = {"pretrain_deterministic_closed": False,
                                                "pretrain_sim": "core"}
    #: options that act only with another's value (ftc.common.cli.unmet)
    NEEDS: ClassVar[dict[str, Any]] = {**{name: ("pretrain", True) for name in (
        "pretrain_cache", "fresh_optimizer", "pretrain_open_fraction", "pretrain_max_steps",
        "pretrain_envs", "pretrain_ent_coef", "pretrain_lr", "pretrain_minibatch",
        "pretrain_rollout")}, "push_key_file": ("push_policy", NONZERO)}

    method: str = field(default="ppo", metadata={"help": "the method (--help lists them)"})
    update_every: int = field(default=128, metadata={"check": at_least(1, MAX_STEPS_PER_INTERVAL), "help": (
        "t_update: real steps between PPO updates (paper: 128)")})
    offline_steps: int = field(default=2048, metadata={"check": at_least(0, 100_000_000), "help": (
        "t_offline: model steps of offline PPO per interval (paper: 2048; ppo-robust, "
        "ppo-learned: 0 keeps only the guided fit)")})
    offline_envs: int = field(default=16, metadata={"check": at_least(1, 100_000), "help": (
        "model rollouts run side by side (one batch through the world model)")})
    offline_rollout: int = field(default=64, metadata={"check": at_least(1, 1_000_000), "help": (
        "model steps per env between offline PPO updates (update batch = envs x rollout)")})
    offline_minibatch: int = field(default=64, metadata={"check": at_least(1, 1_000_000), "help": (
        "PPO minibatch size for offline updates (online uses --ppo-minibatch-size)")})
    pretrain: bool = field(default=False, metadata={"help": (
        "pretrain the policy on the nominal plant in simulation (in-process core) "
        "before interval 0, stopped while it still explores (see --pretrain-open-fraction)")})
    pretrain_open_fraction: float = field(default=0.05, metadata={"check": between(0.0, 1.0), "help": (
        "pretraining stops once the mean valve-open probability over the last rollout "
        "falls to this (~5% keeps enough exploration to adapt; trained to convergence the "
        "policy barely adapts)")})
    pretrain_max_steps: int = field(default=200_000, metadata={"check": at_least(1, 1_000_000_000), "help": (
        "upper bound on pretraining simulation steps")})
    pretrain_envs: int = field(default=16, metadata={"check": at_least(1, 10_000), "help": "nominal plants simulated side by side"})
    pretrain_ent_coef: float = field(default=0.0, metadata={"check": between(0.0, 10.0), "help": (
        "entropy bonus while pretraining; 0: the stop rule, not the bonus, decides how "
        "much exploration is left (with 0.01 the open fraction stalls near 0.15)")})
    pretrain_lr: float | None = field(default=None, metadata={"check": positive(1.0), "help": (
        "Adam step size while pretraining (None: the PPO learning rate)")})
    pretrain_minibatch: int = field(default=256, metadata={"check": at_least(1, 1_000_000), "help": (
        "PPO minibatch size while pretraining (large batches of cheap simulated steps)")})
    pretrain_rollout: int = field(default=64, metadata={"check": at_least(1, 1_000_000), "help": "steps per plant between updates"})
    pretrain_cache: str = field(default="~/.cache/ftc/pretrain", metadata={"run_local": True, "help": (
        "directory of pretrained policies and world models, keyed by a hash of everything "
        "pretraining depends on (seed, pretrain, PPO and model settings, code); a hit skips "
        "pretraining with the same result ('' disables)")})
    fresh_optimizer: bool = field(default=True, metadata={"help": (
        "reset Adam's state when adaptation starts, after pretraining (narrows the spread "
        "across seeds)")})
    push_policy: str | None = field(default=None, metadata={"run_local": True, "help": (
        "after every interval, push the acting policy's weights (policy_t, the version "
        "the time in ms) to a policy node (build/policy_node) listening on this channel "
        "prefix at --push-url: learn here, fly there (docs/deploy.md). PPO methods only "
        "(None: no push)")})
    push_url: str = field(default=DEFAULT_LCM_URL, metadata={"run_local": True, "help": (
        "with --push-policy: the node's LCM URL (ttl=0)")})
    push_key_file: str | None = field(default=None, metadata={"run_local": True, "help": (
        "with --push-policy: sign every push with the node's bus key in this file (hex, "
        "mode 600; the node's --key-file), and take only its signed answer (None: unsigned)")})

    def validate(self) -> None:
        super().validate()
        if self.push_policy is not None and not self.push_policy.strip():
            raise ValueError("--push-policy must name the node's channel prefix, got ''")
        try:
            check_loopback_url(self.push_url)
        except ValueError as e:
            raise ValueError(f"--push-url: {e}") from None
        if self.push_policy is None and self.push_url != DEFAULT_LCM_URL:
            raise ValueError("--push-url is where --push-policy sends the policy: give "
                             "--push-policy PREFIX with it")
        if self.push_key_file is not None:
            if self.push_policy is None:
                raise ValueError("--push-key-file has no effect without --push-policy: it "
                                 "signs --push-policy's pushes")
            try:
                load_key(self.push_key_file)
            except ValueError as e:
                raise ValueError(f"--push-key-file {e}") from None
        if self.steps_per_interval % self.update_every:
            raise ValueError("--steps-per-interval must be a multiple of --update-every")

    def pretrain_settings(self) -> PretrainSettings:
        return PretrainSettings(
            seed=self.seed, steps_per_interval=self.steps_per_interval, envs=self.pretrain_envs,
            rollout=self.pretrain_rollout, minibatch=self.pretrain_minibatch,
            max_steps=self.pretrain_max_steps, open_fraction=self.pretrain_open_fraction,
            ent_coef=self.pretrain_ent_coef, lr=self.pretrain_lr)


def _obs(o: PlantObservation) -> torch.Tensor:
    return torch.as_tensor(o.level, dtype=torch.float32).unsqueeze(0)


class OnlinePPO:
    """``ppo`` on the plant (N = 1): ``act`` then ``observe`` for every
    operating step; every ``update_every`` steps ``observe`` updates the
    policy and returns the update's statistics (the agent reports them to its
    telemetry).

    With ``background = True`` (a real-time plant) the update runs on a worker
    thread, on a clone of the learner, while the current policy goes on
    acting and filling the next rollout (its log-probs are the acting
    policy's, so PPO's ratio stays correct); the updated weights and Adam's
    state are loaded at the first ``observe`` after it finished, between two
    steps, and that call returns its statistics."""

    def __init__(self, ppo: PPO, update_every: int) -> None:
        self.ppo = ppo
        self.collector = RolloutCollector(self.ppo, update_every, 1)
        self.stats: list[UpdateStats] = []  # the updates of the interval
        self._sample: tuple | None = None  # the last act's (obs, action, log-prob, value)
        self._where = ""
        self.background = False
        self._worker: concurrent.futures.ThreadPoolExecutor | None = None
        self._pending: tuple[concurrent.futures.Future, PPO, str] | None = None

    def pretrain(self, settings: PretrainSettings, cache: str,
                 fresh_optimizer: bool) -> dict[str, Any]:
        """Nominal pretraining (from ``cache`` when it holds the result); Adam's
        state reset afterwards with ``fresh_optimizer``. Returns its info."""
        info = pretrain_cached(self.ppo, settings, cache)
        if fresh_optimizer:
            self.ppo.reset_optimizer()
        return info

    def begin_interval(self, background: bool = False) -> None:
        self.stats = []
        self.background = background

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        """Valves (6,) int8: sampled, or greedy in the evaluation episode."""
        x = _obs(obs)
        a, lp, v = self.ppo.act(x, deterministic=ctx.evaluation)
        self._sample = None if ctx.evaluation else (x, a, lp, v)
        self._where = f"interval {ctx.interval}, step {ctx.step + 1}"
        return a[0].numpy().astype(np.int8)

    def observe(self, t: Transition) -> UpdateStats | None:
        """Store the step; the update's statistics when the rollout was full
        (in the background: when an update has just been taken in)."""
        x, a, lp, v = self._sample_of(t)
        self.collector.add(x, a, lp, v, torch.tensor([t.reward]),
                           torch.tensor([t.next_obs.terminal]), torch.tensor([t.truncated]),
                           _obs(t.next_obs))
        taken = self._take_update(wait=False) if self._pending is not None else None
        if not self.collector.full:
            return taken
        if self.background:
            if self._pending is not None:  # an update slower than a whole rollout
                taken = self._take_update(wait=True)
            self._start_update(_obs(t.following))
            return taken
        self.stats.append(self.collector.update(_obs(t.following)))
        check_update(self.ppo.policy, self.stats[-1], f"the PPO update at {self._where}")
        return self.stats[-1]

    def _sample_of(self, t: Transition) -> tuple:
        """The last act's sample if the plant applied it to this step; else (a
        real-time step the controller was late for) the applied valves' log-prob
        and value under the acting policy."""
        if self._sample is not None:
            x, a, lp, v = self._sample
            if (np.array_equal(x[0].numpy(), np.asarray(t.obs.level, dtype=np.float32))
                    and np.array_equal(a[0].numpy(), t.valves)):
                return self._sample
        x = _obs(t.obs)
        a = torch.as_tensor(np.asarray(t.valves), dtype=torch.float32).unsqueeze(0)
        with torch.no_grad():
            lp, _entropy, v = self.ppo.policy.evaluate_actions(x, a)
        return x, a, lp, v

    def _start_update(self, next_obs: torch.Tensor) -> None:
        learner, buffer = self.ppo.clone(), self.collector.buffer
        self.collector.buffer = RolloutBuffer(buffer.num_steps, buffer.num_envs)
        last_values = self.ppo.value(next_obs)
        if self._worker is None:
            self._worker = concurrent.futures.ThreadPoolExecutor(1, "ppo-update")
        future = self._worker.submit(learner.update, buffer, last_values)
        self._pending = (future, learner, self._where)

    def _take_update(self, wait: bool) -> UpdateStats | None:
        """Load a finished background update into the acting learner (the
        acting generator keeps its own stream); its statistics, or None."""
        future, learner, where = self._pending
        if not (wait or future.done()):
            return None
        self._pending = None
        stats = future.result()
        check_update(learner.policy, stats, f"the PPO update at {where}")
        self.ppo.policy.load_state_dict(learner.policy.state_dict())
        self.ppo.optimizer.load_state_dict(learner.optimizer.state_dict())
        self.stats.append(stats)
        return stats

    @property
    def updating(self) -> bool:
        """A background update is in flight (the acting weights are about to change)."""
        return self._pending is not None

    def finish(self) -> UpdateStats | None:
        """Wait for a background update in flight and take it in."""
        return self._take_update(wait=True) if self._pending is not None else None

    def close(self) -> None:
        if self._worker is not None:
            self._worker.shutdown(wait=True, cancel_futures=True)
            self._worker = None

    def drop_rollout(self) -> None:
        """Forget the steps stored since the last update (the policy that took
        them was replaced: they would be used off-policy)."""
        self.collector.buffer.reset()

    def end_online(self) -> dict[str, Any]:
        if not self.stats:
            return {}
        return {name: mean([getattr(s, name) for s in self.stats]) for name in ONLINE_METRICS}

    def state_dict(self) -> dict[str, Any]:
        return self.ppo.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """The learner's entry of a checkpoint, checked (network shapes, finite
        weights) before it is loaded; raises CheckpointError saying why not."""
        checkpoint.check_network_shapes_of(self.ppo.policy.state_dict(),
                                           state.get("policy", {}), "network")
        try:
            check_finite_state(state["policy"], "policy weights in the checkpoint")
        except Exception as e:  # NonFiniteError: a checkpoint that cannot be resumed
            raise CheckpointError(str(e)) from None
        try:
            self.ppo.load_state_dict(state)
        except (KeyError, RuntimeError, ValueError) as e:
            raise CheckpointError(f"policy or optimiser state does not load: "
                                  f"{str(e).splitlines()[0]}") from None
