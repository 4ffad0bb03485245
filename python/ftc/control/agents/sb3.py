"""A Stable-Baselines3 PPO or A2C model fine-tuned on the plant as it runs
(``sb3:PATH.zip`` with ``--sb3-learn``; :mod:`ftc.control.agents.plugins`).

SB3's ``learn()`` steps an env of its own; here the runner steps the plant,
so the agent does what ``learn()`` would around it: it samples the model's
actions (with their values and log-probabilities), fills a rollout buffer of
the model's ``n_steps`` plant steps (one env), bootstraps a step cut off by
the interval's end with the value of where it ended (as SB3 does for a
truncated episode), and then calls the model's own ``train()``. The
evaluation episode acts deterministically. Its checkpoint holds the policy's
weights (the optimiser restarts on --resume).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ftc.control.run.agent import Agent, StepContext, Transition
from ftc.plant.link import PlantObservation


class SB3Agent(Agent):
    """``model`` (SB3 PPO or A2C on the levels, MultiBinary(6) valves) learning
    on the plant; see the module doc."""

    evaluates = True
    extra_columns = ("sb3_updates",)

    def __init__(self, name: str, model: Any) -> None:
        from stable_baselines3.common.buffers import RolloutBuffer
        from stable_baselines3.common.logger import Logger

        self.name, self.model = name, model
        model.n_envs = 1  # the plant is one env, whatever the model was trained on
        model.rollout_buffer = RolloutBuffer(
            model.n_steps, model.observation_space, model.action_space, device="cpu",
            gamma=model.gamma, gae_lambda=model.gae_lambda, n_envs=1)
        model.set_logger(Logger(folder=None, output_formats=[]))
        self.updates = 0
        self._updates_before = 0
        self._sample: tuple | None = None
        self._episode_start = True

    def begin_interval(self, interval: int) -> None:
        self._updates_before = self.updates

    def start_episode(self, obs: PlantObservation) -> None:
        self._episode_start = True

    def _obs(self, obs: PlantObservation) -> torch.Tensor:
        return torch.as_tensor(np.asarray(obs.level, np.float32)[None])

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        if ctx.evaluation:
            return np.asarray(self.model.predict(np.asarray(obs.level, np.float32),
                                                 deterministic=True)[0], np.int8)
        x = self._obs(obs)
        with torch.no_grad():
            actions, values, log_probs = self.model.policy(x)
        self._sample = (x.numpy(), actions.numpy(), values, log_probs)
        return actions.numpy()[0].astype(np.int8)

    def _value(self, obs: PlantObservation) -> torch.Tensor:
        with torch.no_grad():
            return self.model.policy.predict_values(self._obs(obs))

    def observe(self, t: Transition) -> None:
        x, a, values, log_probs = self._sample
        reward = float(t.reward)
        if t.truncated:  # cut off by the interval, not ended: SB3's bootstrap
            reward += self.model.gamma * float(self._value(t.next_obs))
        buffer = self.model.rollout_buffer
        buffer.add(x, a, np.array([reward], np.float32), np.array([self._episode_start]),
                   values, log_probs)
        self._episode_start = False
        if buffer.full:
            buffer.compute_returns_and_advantage(last_values=self._value(t.following),
                                                 dones=np.array([t.next_obs.done]))
            self.model._current_progress_remaining = 1.0  # schedules at their start values
            self.model.train()
            buffer.reset()
            self.updates += 1

    def end_online(self) -> dict[str, Any]:
        return {"sb3_updates": self.updates - self._updates_before}

    def state_dict(self) -> dict[str, Any]:
        return {"policy": self.model.policy.state_dict(), "updates": self.updates}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.model.policy.load_state_dict(state["policy"])
        self.updates = int(state["updates"])
