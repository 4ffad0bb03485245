"""DeferredAgent: a learning job off the control loop. While the job runs the
frozen policy acts and the agent's calls queue; when it is done its metrics
arrive late, the runner's hook saves the state (before the queued calls), and
the calls are replayed in order; ppo-robust's state saved so equals the one a
lockstep run checkpoints; without background learning the job runs at once;
a job's error reaches the loop. Also Algorithm 1's own way off the loop: an
offline phase queued in real time survives a checkpoint."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from ftc.control.run.agent import StepContext, Transition
from ftc.control.run.deferred import DeferredAgent
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
    with pytest.raises(RuntimeError, match="a fit is running"):
        agent.state_dict()  # no state while it changes
    saved = []
    agent.on_learned = lambda k: saved.append((k, agent.state_dict(), list(agent.calls)))
    release.set()
    agent.end_online()  # waits for the job, then replays
    assert saved == [(3, {"weights": 1}, [])]  # after the job, before the queued calls
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


def _robust_interval(background: bool):
    """ppo-robust driven through one interval of 64 steps on the core plant, then
    its end_interval; returns (agent, the state saved after the fit)."""
    from ftc.tools.controller import make_agent, parse_args
    from ftc.plant.link import CorePlant
    from ftc.plant.reward import reward

    cfg, ppo = parse_args(["--method", "ppo-robust", "--offline-steps", "0", "--link", "core",
                           "--steps-per-interval", "64", "--update-every", "32",
                           "--teacher-check-every", "0", "--out", "unused"])
    torch.manual_seed(0)
    agent = make_agent(cfg, ppo)
    saved = []
    agent.on_learned = lambda k: saved.append(agent.state_dict())
    plant = CorePlant("scenarios/single.toml", 0, steps_per_interval=64)
    agent.begin_interval(0)
    # set after begin_interval: the interval's PPO updates stay inline (the same
    # steps either way), only the fit after it runs on the worker
    agent.background_learning = background
    o = plant.reset()
    agent.start_episode(o)
    for t in range(64):
        u = agent.act(o, StepContext(0, t, 64 - t))
        nxt = plant.step(u)
        following = plant.reset() if nxt.terminal and t < 63 else nxt
        agent.observe(Transition(o, u, float(reward(nxt.level, u)), nxt, following))
        o = following
    metrics = agent.end_interval(0, None)
    if background:
        assert metrics == {} and agent.learning  # the fit runs on the worker
        agent.finish()
        (interval, metrics), = agent.late_metrics()
        assert interval == 0
    else:
        saved.append(agent.state_dict())
    assert metrics["teacher_labels"] > 0
    return agent, saved[0]


def test_the_state_saved_after_a_background_fit_is_the_lockstep_checkpoint():
    """The runner checkpoints a real-time interval from on_learned: the agent's
    state then is the one a lockstep run saves after the same interval."""
    background, saved = _robust_interval(background=True)
    lockstep, expected = _robust_interval(background=False)
    policy, want = saved["ppo"]["policy"], expected["ppo"]["policy"]
    assert policy.keys() == want.keys()
    for name in want:
        assert torch.equal(policy[name], want[name]), name
    np.testing.assert_array_equal(saved["teacher_memory"], expected["teacher_memory"])
    background.close()
    lockstep.close()


def test_an_offline_phase_queued_in_real_time_survives_a_checkpoint():
    """Algorithm 1 on a real-time plant queues an interval's offline phase behind
    the one still running; a checkpoint keeps it, a resumed agent starts it."""
    from ftc.tools.controller import make_agent, parse_args

    cfg, ppo = parse_args(["--method", "ppo-offline", "--link", "core", "--out", "unused"])
    agent = make_agent(cfg, ppo)
    agent.queued = 4
    resumed = make_agent(cfg, ppo)
    resumed.load_state_dict(agent.state_dict())
    assert resumed.queued == 4
    agent.queued = None
    resumed.load_state_dict(agent.state_dict())
    assert resumed.queued is None
