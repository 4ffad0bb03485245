"""DeferredAgent: a learning job off the control loop. While the job runs the
frozen policy acts and the agent's calls queue; when it is done its metrics
arrive late and the calls are replayed in order; a checkpoint taken meanwhile
is the state from before the job; without background learning the job runs
at once, as in lockstep; a job's error reaches the loop."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from ftc.control.agent import StepContext, Transition
from ftc.control.deferred import PENDING_KEY, DeferredAgent
from ftc.learning.ppo_policy import ActorCritic
from ftc.plant.link import PlantObservation


def _obs(level: float) -> PlantObservation:
    return PlantObservation(level=np.full(6, level), true_level=np.full(6, level),
                            valves=np.zeros(6, np.int8), deficit=np.zeros(2), age=0.0, step=1,
                            episode=0, operating_steps=1, terminal=False, truncated=False,
                            evaluation=False)


def _policy(open_all: bool) -> ActorCritic:
    torch.manual_seed(0)
    policy = ActorCritic()
    with torch.no_grad():
        head = [m for m in policy.policy_head.modules() if isinstance(m, torch.nn.Linear)][-1]
        head.weight.zero_()
        head.bias.fill_(50.0 if open_all else -50.0)  # every valve open / closed, surely
    return policy


class Recorder(DeferredAgent):
    """Records its calls; its policy closes every valve until a job opens them."""

    def __init__(self) -> None:
        super().__init__(seed=0)
        self.policy = _policy(open_all=False)
        self.calls: list[tuple] = []
        self.weights = 0  # what a job changes

    def acting_policy(self):
        return self.policy

    def _begin_interval(self, interval: int) -> None:
        self.calls.append(("begin", interval))

    def _act(self, obs, ctx):
        self.calls.append(("act", float(obs.level[0])))
        return np.ones(6, np.int8) if self.weights else np.zeros(6, np.int8)

    def _observe(self, t: Transition) -> None:
        self.calls.append(("observe", float(t.obs.level[0])))

    def _state_dict(self):
        return {"weights": self.weights}


def _step(level: float) -> Transition:
    o = _obs(level)
    return Transition(o, np.zeros(6, np.int8), 1.0, o, o)


CTX = StepContext(0, 0, 10)


def test_a_job_runs_at_once_without_background_learning():
    agent = Recorder()
    assert agent.learn(lambda: {"fit": 1.0}, interval=0) == {"fit": 1.0}
    assert not agent.learning and agent.late_metrics() == []


def test_while_a_job_runs_the_frozen_policy_acts_and_calls_queue_then_replay():
    agent = Recorder()
    agent.background_learning = True
    release = threading.Event()

    def job():
        release.wait(10)
        agent.weights = 1  # the fit's result: the agent's own policy now opens
        return {"fit": 2.0}

    assert agent.learn(job, interval=3) is None
    assert agent.learning
    # the frozen copy of the policy from before the job acts (it closes every valve)
    assert list(agent.act(_obs(0.5), CTX)) == [0] * 6
    agent.begin_interval(4)
    agent.observe(_step(0.4))
    agent.observe(_step(0.3))
    assert agent.calls == []  # queued, not run beside the job
    saved = agent.state_dict()
    assert saved == {"weights": 0, PENDING_KEY: 3}  # the state before the job, and which
    release.set()
    agent.end_online()  # waits for the job, then replays
    assert agent.calls == [("begin", 4), ("observe", 0.4), ("observe", 0.3)]
    assert agent.late_metrics() == [(3, {"fit": 2.0})]
    assert list(agent.act(_obs(0.2), CTX)) == [1] * 6  # the agent acts again, learned
    assert agent.state_dict() == {"weights": 1}
    agent.close()


def test_a_jobs_error_is_raised_in_the_loop():
    agent = Recorder()
    agent.background_learning = True

    def job():
        raise ValueError("non-finite weights after the fit")

    agent.learn(job, interval=0)
    with pytest.raises(ValueError, match="non-finite weights"):
        agent.finish()
    agent.close()
