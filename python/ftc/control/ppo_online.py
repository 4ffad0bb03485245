"""PPO on the plant, the part every agent with a policy shares: a learner's
rollout collector, acting on the plant and updating every t_update real
steps, the interval's update statistics, nominal pretraining, and the
learner's entry of a checkpoint. Each agent holds its learner and one of
these, and adds its own offline phase: :class:`ftc.control.ppo_agent.PPOAgent`
(Algorithm 1, the world model), :class:`ftc.control.ppo_robust_agent.RobustPPOAgent`
(the identified physics and a planner).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ftc.common.errors import CheckpointError
from ftc.control import checkpoint
from ftc.control.agent import StepContext, Transition
from ftc.control.checkpoint import check_finite_state, check_update
from ftc.control.metrics import mean
from ftc.learning.ppo import PPO, UpdateStats
from ftc.learning.pretrain import PretrainSettings, pretrain_cached
from ftc.learning.rollout import RolloutCollector
from ftc.plant.link import PlantObservation

# what end_online reports: the means over the interval's updates
ONLINE_METRICS = ("entropy", "open_fraction", "approx_kl", "clipfrac", "explained_variance",
                  "value_loss")


def _obs(o: PlantObservation) -> torch.Tensor:
    return torch.as_tensor(o.level, dtype=torch.float32).unsqueeze(0)


class OnlinePPO:
    """``ppo`` on the plant (N = 1): ``act`` then ``observe`` for every
    operating step; every ``update_every`` steps ``observe`` updates the
    policy and returns the update's statistics (the agent reports them to its
    telemetry)."""

    def __init__(self, ppo: PPO, update_every: int) -> None:
        self.ppo = ppo
        self.collector = RolloutCollector(self.ppo, update_every, 1)
        self.stats: list[UpdateStats] = []  # the updates of the interval
        self._sample: tuple | None = None  # the last act's (obs, action, log-prob, value)
        self._where = ""

    def pretrain(self, settings: PretrainSettings, cache: str,
                 fresh_optimizer: bool) -> dict[str, Any]:
        """Nominal pretraining (from ``cache`` when it holds the result); Adam's
        state reset afterwards with ``fresh_optimizer``. Returns its info."""
        info = pretrain_cached(self.ppo, settings, cache)
        if fresh_optimizer:
            self.ppo.reset_optimizer()
        return info

    def begin_interval(self) -> None:
        self.stats = []

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        """Valves (6,) int8: sampled, or greedy in the evaluation episode."""
        x = _obs(obs)
        a, lp, v = self.ppo.act(x, deterministic=ctx.evaluation)
        self._sample = None if ctx.evaluation else (x, a, lp, v)
        self._where = f"interval {ctx.interval}, step {ctx.step + 1}"
        return a[0].numpy().astype(np.int8)

    def observe(self, t: Transition) -> UpdateStats | None:
        """Store the step; the update's statistics when the rollout was full."""
        x, a, lp, v = self._sample
        self.collector.add(x, a, lp, v, torch.tensor([t.reward]),
                           torch.tensor([t.next_obs.terminal]), torch.tensor([t.truncated]),
                           _obs(t.next_obs))
        if not self.collector.full:
            return None
        self.stats.append(self.collector.update(_obs(t.following)))
        check_update(self.ppo.policy, self.stats[-1], f"the PPO update at {self._where}")
        return self.stats[-1]

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
