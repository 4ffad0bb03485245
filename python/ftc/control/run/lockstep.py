"""The interval runner's loop on a lockstep plant: the plant takes one step per
command and waits for the next (:mod:`ftc.control.run.realtime` is the loop on a
plant that does not wait)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ftc.common.errors import RunError
from ftc.control.run.agent import Agent, StepContext, Transition
from ftc.control.run.checkpoint import finite_observation
from ftc.control.run.telemetry import Telemetry
from ftc.plant.link import PlantLink, PlantObservation
from ftc.plant.reward import reward


class LockstepLoop:
    """Drives ``agent`` on a lockstep ``plant`` for the interval runner;
    ``where`` is the position in the run, for error messages."""

    def __init__(self, plant: PlantLink | None, agent: Agent, telemetry: Telemetry) -> None:
        self.plant, self.agent, self.telemetry = plant, agent, telemetry
        self.where = "before the first step"

    def online(self, interval: int, steps: int, keep: bool
               ) -> tuple[dict[str, Any], list[PlantObservation]]:
        """Operating steps of one interval; returns its metrics and observations
        (for Transitions, when ``keep``)."""
        n, k, agent, plant = steps, interval, self.agent, self.plant
        rewards = np.zeros(n)
        observations: list[PlantObservation] = []
        self.where = f"interval {k}, step 0"
        o = finite_observation(plant.reset(), self.where)
        agent.start_episode(o)
        observations.append(o)
        episodes = 1
        for t in range(n):
            u = agent.act(o, StepContext(k, t, n - t))
            self.where = f"interval {k}, step {t + 1}"
            nxt = finite_observation(plant.step(u), self.where)
            observations.append(nxt)
            rewards[t] = reward(nxt.level, u)
            self.telemetry.step(nxt.level, u)
            last = t == n - 1
            if last and not nxt.done:
                raise RunError(f"plant did not end the interval after {t + 1} steps at "
                               f"{self.where} (is its steps_per_interval the same as ours?)")
            if nxt.truncated and not last:
                raise RunError(f"plant truncated the episode at {self.where}, before the "
                               "interval's end (is its steps_per_interval the same as ours?)")
            following = nxt
            if nxt.terminal and not last:
                following = finite_observation(plant.reset(), self.where)
                observations.append(following)
                episodes += 1
            agent.observe(Transition(o, u, float(rewards[t]), nxt, following))
            if following is not nxt:
                agent.start_episode(following)
            o = following
        metrics = {"reward_per_step": float(rewards.mean()), "episodes": episodes,
                   **agent.end_online()}
        return metrics, (observations if keep else [])

    def evaluate(self, interval: int, limit: int) -> tuple[float, int]:
        """The evaluation episode, cut off after ``limit`` steps."""
        k, plant = interval, self.plant
        self.where = f"interval {k}, evaluation step 0"
        o = finite_observation(plant.evaluate(), self.where)
        self.agent.start_episode(o)
        total, steps = 0.0, 0
        while not o.done and steps < limit:
            u = self.agent.act(o, StepContext(k, steps, None, evaluation=True))
            self.where = f"interval {k}, evaluation step {steps + 1}"
            o = finite_observation(plant.step(u), self.where)
            total += float(reward(o.level, u))
            steps += 1
        return total / max(steps, 1), steps

