"""PPO building blocks against hand-computed values, determinism, and learning a
tiny known problem."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ftc.learning.buffer import RolloutBuffer
from ftc.learning.ppo import PPO, ActorCritic, PPOConfig, clipped_surrogate_loss, ppo_update

torch.set_num_threads(1)  # tiny networks: threads only add contention (and nondeterminism)


def _fill(buffer: RolloutBuffer, rewards, values, terminals, truncations, trunc_values):
    for t in range(len(rewards)):
        buffer.add(torch.zeros(1, 6), torch.zeros(1, 6), torch.zeros(1),
                   torch.tensor([values[t]]), torch.tensor([rewards[t]]),
                   torch.tensor([terminals[t]]), torch.tensor([truncations[t]]),
                   torch.tensor([trunc_values[t]]))


def test_gae_terminal_not_bootstrapped_truncation_bootstrapped():
    g, lam = 0.9, 0.5
    r = [1.0, 2.0, 3.0, 4.0]
    v = [0.5, 1.0, 1.5, 2.0]
    term = [False, True, False, False]     # episode A ends by termination at t=1
    trunc = [False, False, False, True]    # episode B truncated at t=3
    tv = [0.0, 0.0, 0.0, 10.0]             # V(final obs of B)
    buf = RolloutBuffer(4, 1)
    _fill(buf, r, v, term, trunc, tv)
    buf.compute_returns_and_advantages(torch.tensor([99.0]), g, lam)  # last value unused

    # by hand, backwards
    d3 = 4.0 + g * 10.0 - 2.0            # truncated: bootstrap from V(final) = 10
    a3 = d3
    d2 = 3.0 + g * 2.0 - 1.5
    a2 = d2 + g * lam * a3
    d1 = 2.0 + 0.0 - 1.0                 # terminal: no bootstrap, chain cut
    a1 = d1
    d0 = 1.0 + g * 1.0 - 0.5
    a0 = d0 + g * lam * a1
    expected = torch.tensor([a0, a1, a2, a3])
    assert torch.allclose(buf.advantages[:, 0], expected)
    assert torch.allclose(buf.returns[:, 0], expected + torch.tensor(v))


def test_gae_bootstraps_from_last_value_when_not_done_and_scales_rewards():
    buf = RolloutBuffer(2, 1)
    _fill(buf, [1.0, 1.0], [0.0, 0.0], [False, False], [False, False], [0.0, 0.0])
    buf.compute_returns_and_advantages(torch.tensor([5.0]), gamma=1.0, gae_lambda=1.0,
                                       reward_scale=0.5)
    # lambda = gamma = 1: advantage = discounted scaled return + last value - V
    assert torch.allclose(buf.advantages[:, 0], torch.tensor([6.0, 5.5]))
    assert torch.allclose(buf.returns[:, 0], torch.tensor([6.0, 5.5]))


def test_gae_vectorised_envs_are_independent():
    buf = RolloutBuffer(2, 2)
    for t in range(2):
        buf.add(torch.zeros(2, 6), torch.zeros(2, 6), torch.zeros(2), torch.zeros(2),
                torch.tensor([1.0, 2.0]), torch.tensor([t == 0, False]),
                torch.tensor([False, False]))
    buf.compute_returns_and_advantages(torch.tensor([0.0, 3.0]), 0.5, 1.0)
    # env 0: terminal at t=0 -> a0 = 1; t=1: 1 + 0.5*0 = 1
    # env 1: a1 = 2 + 0.5*3 = 3.5; a0 = 2 + 0.5*3.5 = 3.75
    assert torch.allclose(buf.advantages, torch.tensor([[1.0, 3.75], [1.0, 3.5]]))


def test_bernoulli_log_prob_and_entropy_summed_over_valves():
    p = torch.tensor([0.1, 0.5, 0.9, 0.2, 0.7, 0.5])
    logits = torch.log(p / (1 - p))
    a = torch.tensor([1.0, 0.0, 1.0, 0.0, 0.0, 1.0])
    logprob, entropy = ActorCritic.log_prob_entropy(logits, a)
    expected_lp = sum(math.log(pi if ai else 1 - pi) for pi, ai in zip(p.tolist(), a.tolist()))
    expected_h = sum(-(pi * math.log(pi) + (1 - pi) * math.log(1 - pi)) for pi in p.tolist())
    assert logprob.item() == pytest.approx(expected_lp, rel=1e-5)
    assert entropy.item() == pytest.approx(expected_h, rel=1e-5)
    assert entropy.item() <= 6 * math.log(2) + 1e-6


def test_fresh_policy_opens_valves_with_probability_one_half():
    torch.manual_seed(0)
    logits, _ = ActorCritic()(torch.rand(32, 6))
    assert torch.sigmoid(logits).sub(0.5).abs().max() < 0.05


def test_clipped_surrogate_gradients_by_hand():
    eps = 0.2
    old = torch.zeros(4)
    # ratios: 1.5 (A>0, clipped: no grad), 1.1 (A>0, inside: grad -A*r),
    #         0.5 (A<0, clipped: no grad), 0.5 (A>0, below range: unclipped side binds, grad)
    new = torch.log(torch.tensor([1.5, 1.1, 0.5, 0.5])).requires_grad_()
    adv = torch.tensor([1.0, 2.0, -1.0, 3.0])
    loss = clipped_surrogate_loss(new, old, adv, eps)
    loss.backward()
    # d/d logp of -A r = -A r (r = exp(logp)); averaged over 4 samples
    expected = torch.tensor([0.0, -2.0 * 1.1, 0.0, -3.0 * 0.5]) / 4
    assert torch.allclose(new.grad, expected, atol=1e-6)
    expected_loss = (-1.0 * 1.2 - 2.0 * 1.1 + 1.0 * 0.8 - 3.0 * 0.5) / 4
    assert loss.item() == pytest.approx(expected_loss, rel=1e-6)


def _random_batch_update(seed: int):
    ppo = PPO(PPOConfig(), seed=seed)
    buf = RolloutBuffer(32, 2)
    gen = torch.Generator().manual_seed(123)
    obs = torch.rand(2, 6, generator=gen)
    actions_seen = []
    for t in range(32):
        a, lp, v = ppo.act(obs)
        actions_seen.append(a)
        r = torch.rand(2, generator=gen) * 3
        buf.add(obs, a, lp, v, r, torch.tensor([t % 7 == 6, False]), torch.tensor([False, False]))
        obs = torch.rand(2, 6, generator=gen)
    stats = ppo.update(buf, ppo.value(obs))
    return torch.stack(actions_seen), stats, ppo.policy.state_dict()


def test_same_seed_same_actions_and_losses():
    a1, s1, p1 = _random_batch_update(7)
    a2, s2, p2 = _random_batch_update(7)
    assert torch.equal(a1, a2)
    assert s1 == s2
    assert all(torch.equal(p1[k], p2[k]) for k in p1)
    a3, _, _ = _random_batch_update(8)
    assert not torch.equal(a1, a3)


def test_target_kl_stops_early():
    ppo = PPO(PPOConfig(target_kl=1e-9, learning_rate=1e-2), seed=0)
    buf = RolloutBuffer(64, 1)
    for _ in range(64):
        obs = torch.rand(1, 6)
        a, lp, v = ppo.act(obs)
        buf.add(obs, a, lp, v, a.sum(-1), torch.tensor([False]), torch.tensor([False]))
    stats = ppo.update(buf, torch.zeros(1))
    assert stats.gradient_steps == 4  # one epoch of 64/16 minibatches, then stop


class ValvePuzzle:
    """Two-step puzzle, vectorised over N envs. Step 0 (obs zeros): each open valve
    costs 0.1. Step 1: obs[0] = whether valve 0 was opened at step 0; opening
    valve 1 then pays +1 (only if obs[0] = 1); each open valve still costs 0.1;
    then the episode terminates. Optimum: open valve 0 only, then valve 1 only
    (return 0.8); the greedy alternative (never open anything) earns 0."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.t = torch.zeros(n, dtype=torch.long)
        self.obs = torch.zeros(n, 6)

    def step(self, a: torch.Tensor):
        cost = -0.1 * a.sum(-1)
        first = self.t == 0
        bonus = torch.where(first, torch.zeros(self.n), a[:, 1] * self.obs[:, 0])
        terminal = ~first
        next_obs = torch.zeros(self.n, 6)
        next_obs[:, 0] = torch.where(first, a[:, 0], torch.zeros(self.n))
        next_obs[:, 5] = first.float()  # marks step 1
        self.obs = torch.where(terminal[:, None], torch.zeros(self.n, 6), next_obs)
        self.t = torch.where(terminal, torch.zeros_like(self.t), self.t + 1)
        return cost + bonus, terminal


ITERATIONS = 60


def test_ppo_learns_two_step_valve_puzzle():
    cfg = PPOConfig(learning_rate=3e-3, minibatch_size=64, reward_scale=1.0, ent_coef=0.003)
    ppo = PPO(cfg, seed=0)
    env = ValvePuzzle(16)
    buf = RolloutBuffer(16, 16)
    for _ in range(ITERATIONS):
        for _t in range(16):
            obs = env.obs
            a, lp, v = ppo.act(obs)
            r, term = env.step(a)
            buf.add(obs, a, lp, v, r, term, torch.zeros(16, dtype=torch.bool))
        ppo.update(buf, ppo.value(env.obs))
    s0 = torch.zeros(1, 6)
    s1 = torch.tensor([[1.0, 0, 0, 0, 0, 1.0]])
    a0, _, _ = ppo.act(s0, deterministic=True)
    a1, _, _ = ppo.act(s1, deterministic=True)
    assert a0.tolist() == [[1, 0, 0, 0, 0, 0]]
    assert a1.tolist() == [[0, 1, 0, 0, 0, 0]]
    # the critic learned the optimal return from the start state
    assert ppo.value(s0).item() == pytest.approx(0.8 * cfg.gamma - 0.1, abs=0.1)


def test_ppo_update_returns_finite_stats():
    ppo = PPO(PPOConfig(), seed=1)
    buf = RolloutBuffer(128, 1)
    for _ in range(128):
        obs = torch.rand(1, 6)
        a, lp, v = ppo.act(obs)
        buf.add(obs, a, lp, v, torch.tensor([2.5]), torch.tensor([False]), torch.tensor([False]))
    buf.compute_returns_and_advantages(torch.zeros(1), 0.99, 0.95, 0.01)
    stats = ppo_update(ppo.policy, ppo.optimizer, buf.batch(), ppo.config, ppo.generator)
    assert stats.gradient_steps == 4 * 128 // 16
    assert all(math.isfinite(x) for x in stats)


def test_acting_is_bit_identical_to_the_module_forward_and_log_prob_entropy():
    """act() skips nn.Module's call machinery and the unused entropy (1.4x per
    row); it must compute exactly what forward + log_prob_entropy compute."""
    policy = ActorCritic()
    rng = np.random.default_rng(2)
    g_act, g_ref = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    for i in range(60):
        obs = torch.as_tensor(rng.random((1 + i % 5, 6)), dtype=torch.float32)
        for deterministic in (False, True):
            actions, logprob, value = policy.act(obs, g_act, deterministic)
            with torch.no_grad():
                logits, ref_value = policy(obs)
                ref_actions = ((logits > 0).float() if deterministic
                               else torch.bernoulli(torch.sigmoid(logits), generator=g_ref))
                ref_logprob, _ = policy.log_prob_entropy(logits, ref_actions)
            assert torch.equal(actions, ref_actions) and torch.equal(value, ref_value)
            assert torch.equal(logprob, ref_logprob)


def test_stored_configs_of_older_runs_still_resume(tmp_path, capsys):
    """A config.json that names the native engine numpy, or holds a retired
    option at the value the controller now always uses, reads as today's
    config; a retired option at another value is refused in one line."""
    import dataclasses
    import json

    from ftc.common.errors import CheckpointError
    from ftc.tools.run_cli import read_run_configs
    from ftc.control.agents.ppo import ControllerConfig

    parts = {"controller": ControllerConfig, "ppo": PPOConfig}
    controller = {**dataclasses.asdict(ControllerConfig()), "pretrain_sim": "core",
                  "pretrain_deterministic_closed": False}
    ppo = {**dataclasses.asdict(PPOConfig()), "engine": "numpy"}
    (tmp_path / "config.json").write_text(json.dumps({"controller": controller, "ppo": ppo}))
    configs = read_run_configs(str(tmp_path), parts)
    assert configs["ppo"].engine == "native"
    assert configs["controller"] == ControllerConfig()
    (tmp_path / "config.json").write_text(json.dumps(
        {"controller": {**controller, "pretrain_sim": "model"}, "ppo": ppo}))
    with pytest.raises(CheckpointError, match="--pretrain-sim 'model', which this controller "
                                              "no longer offers"):
        read_run_configs(str(tmp_path), parts)
