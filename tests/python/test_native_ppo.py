"""The native engine's C++ kernels (ftc._learn: ppo_epoch, Actor, log_prob;
cpp/learning/ppo_update.cpp) against their NumPy oracle (oracles/ppo_numpy.py),
and the NumPy model env against the
torch one (learning/model_env.py).

What must be equal: the minibatches (drawn from the same torch generator), the
sampled valves, the Adam step count, episode ends. What may differ: float32
rounding (Eigen sums products in another order than OpenBLAS and has its own
tanh), ~1e-7 relative per operation; Adam's division by sqrt(v) + 1e-5
amplifies it where gradients are near zero, so weights after an update are
compared at 2e-5 absolute + 1e-4 relative (measured: ~1e-6), as
test_ppo_numpy.py compares NumPy with torch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ftc import _learn
from ftc.learning.buffer import RolloutBatch
from ftc.learning.model_env import ModelEnv
from ftc.learning.ppo import PPO, PPOConfig
from ftc.learning.ppo_native import FlatParams, NativeActor, flat_ppo_update
from ftc.learning.world_model import WorldModel, WorldModelConfig
from oracles.ppo_numpy import NumpyActor, numpy_ppo_update


def _batch(seed: int, n: int = 256) -> RolloutBatch:
    g = torch.Generator().manual_seed(seed)
    obs = torch.rand(n, 6, generator=g)
    actions = (torch.rand(n, 6, generator=g) < 0.5).float()
    logprobs = -4.16 + 0.3 * torch.randn(n, generator=g)  # near 6 log(0.5): ratios near 1
    values = torch.randn(n, generator=g)
    advantages = torch.randn(n, generator=g)
    return RolloutBatch(obs, actions, logprobs, values, advantages, values + advantages)


@pytest.mark.parametrize("config", [
    PPOConfig(engine="native"),
    PPOConfig(engine="native", ent_coef=0.05, minibatch_size=48),  # a short last minibatch
    PPOConfig(engine="native", max_grad_norm=0.01, norm_adv=False),  # the clip acts every step
    PPOConfig(engine="native", learning_rate=3e-3, target_kl=0.002),  # stops after an epoch
])
def test_the_native_update_is_the_numpy_one(config):
    batch = _batch(1)
    runs = []
    for update in (numpy_ppo_update, flat_ppo_update):
        ppo = PPO(config, seed=3)
        stats = [update(ppo.policy, ppo.optimizer, batch, ppo.config, ppo.generator)
                 for _ in range(3)]
        runs.append((ppo, stats))
    (ref, ref_stats), (nat, nat_stats) = runs
    start = PPO(config, seed=3).policy.state_dict()
    moved = 0.0
    for (name, a), b in zip(ref.policy.state_dict().items(), nat.policy.state_dict().values()):
        torch.testing.assert_close(b, a, atol=2e-5, rtol=1e-4, msg=name)
        moved = max(moved, float((a - start[name]).abs().max()))
    assert moved > 1e-3  # it trained
    for s_ref, s_nat in zip(ref_stats, nat_stats):
        assert s_nat.gradient_steps == s_ref.gradient_steps
        for field in ("policy_loss", "value_loss", "approx_kl", "clipfrac", "entropy"):
            assert getattr(s_nat, field) == pytest.approx(getattr(s_ref, field), rel=1e-3,
                                                          abs=1e-5), field
    if config.target_kl is not None:  # the early stop happened, and in the same epoch
        assert ref_stats[-1].gradient_steps < config.update_epochs * -(-256 // config.minibatch_size)
    # Adam's moments and step count went back into the torch optimiser alike
    for p_ref, p_nat in zip(ref.policy.parameters(), nat.policy.parameters()):
        s_ref, s_nat = ref.optimizer.state[p_ref], nat.optimizer.state[p_nat]
        assert int(s_nat["step"]) == int(s_ref["step"])
        torch.testing.assert_close(s_nat["exp_avg"], s_ref["exp_avg"], atol=1e-6, rtol=1e-3)
    # the generator advanced alike (one permutation per epoch run)
    assert torch.equal(ref.generator.get_state(), nat.generator.get_state())


def test_native_acting_is_the_numpy_acting():
    ppo = PPO(PPOConfig(engine="native"), seed=4)
    flat_ppo_update(ppo.policy, ppo.optimizer, _batch(6), ppo.config,
                    ppo.generator)  # trained weights, not the init's near-0.5 probabilities
    actors = NumpyActor(ppo.policy), NativeActor(ppo.policy)
    obs_gen = torch.Generator().manual_seed(7)
    for n in (1, 16):
        for deterministic in (False, True):
            for _ in range(25):
                obs = torch.rand(n, 6, generator=obs_gen)
                (a0, l0, v0), (a1, l1, v1) = (
                    actor.act(obs, torch.Generator().manual_seed(n), deterministic)
                    for actor in actors)
                assert torch.equal(a0, a1)
                assert l1.dtype == v1.dtype == torch.float32 and l1.shape == v1.shape == (n,)
                torch.testing.assert_close(l1, l0, atol=1e-5, rtol=1e-5)
                torch.testing.assert_close(v1, v0, atol=1e-6, rtol=1e-5)


def test_native_acting_reads_the_weights_where_torch_keeps_them():
    ppo = PPO(PPOConfig(engine="native"), seed=0)
    actor = NativeActor(ppo.policy)
    obs = torch.rand(4, 6, generator=torch.Generator().manual_seed(1))
    other = PPO(PPOConfig(engine="torch"), seed=1)
    ppo.policy.load_state_dict(other.policy.state_dict())  # copies in place
    _, _, value = actor.act(obs, None, deterministic=True)
    torch.testing.assert_close(value, other.policy.value(obs).detach(), atol=1e-6, rtol=1e-5)


def test_acting_follows_weights_whose_memory_moved():
    # Pickling a tensor for another process (the background offline worker)
    # moves its storage into shared memory and frees the old one; an actor
    # built before would read freed memory (it did: NaN valves probabilities).
    ppo = PPO(PPOConfig(engine="native"), seed=0)
    obs = torch.rand(4, 6, generator=torch.Generator().manual_seed(1))
    ppo.act(obs, deterministic=True)
    ppo.policy.share_memory()
    ppo.policy.load_state_dict(PPO(PPOConfig(), seed=1).policy.state_dict())
    for _ in range(3):  # reuse of the freed memory must not show either
        torch.zeros(64, 64).fill_(float("nan"))
        _, _, value = ppo.act(obs, deterministic=True)
        torch.testing.assert_close(value, ppo.policy.value(obs).detach(), atol=1e-6, rtol=1e-5)


def test_the_kernels_name_what_is_wrong():
    net = FlatParams(PPO(PPOConfig(), seed=0).policy)
    w = net.widths()
    n = 8
    obs, actions = np.zeros((n, 6), np.float32), np.zeros((n, 6), np.float32)
    vec = np.zeros(n, np.float32)
    m, v = np.zeros_like(net.flat), np.zeros_like(net.flat)
    kw = dict(minibatch=4, clip_coef=0.2, ent_coef=0.0, vf_coef=0.5, max_grad_norm=0.5,
              norm_adv=True, lr=1e-3, beta1=0.9, beta2=0.999, eps=1e-5)
    args = [net.flat, m, v, 0, w["trunk"], w["pi"], w["v"], obs, actions, vec, vec, vec,
            np.arange(n)]
    *_, t = _learn.ppo_epoch(*args, **kw)
    assert t == 2  # two minibatches of 4
    with pytest.raises(ValueError, match="params must be a float32 vector"):
        _learn.ppo_epoch(net.flat.astype(np.float64), *args[1:], **kw)
    with pytest.raises(ValueError, match="adam_m must be a writable"):
        frozen = m.copy()
        frozen.flags.writeable = False
        _learn.ppo_epoch(args[0], frozen, *args[2:], **kw)
    with pytest.raises(ValueError, match=r"actions must be \(8, 6\)"):
        _learn.ppo_epoch(*args[:8], actions[:, :5], *args[9:], **kw)
    with pytest.raises(ValueError, match=r"returns must be \(8,\)"):
        _learn.ppo_epoch(*args[:11], vec[:3], args[12], **kw)
    with pytest.raises(ValueError, match="row index 8 out of range for 8 rows"):
        _learn.ppo_epoch(*args[:12], np.arange(1, n + 1), **kw)
    with pytest.raises(ValueError, match="heads must take the trunk's output width"):
        _learn.ppo_epoch(*args[:5], [32, 16, 6], *args[6:], **kw)
    with pytest.raises(ValueError, match=r"obs must be \(N, 6\)"):
        NativeActor(PPO(PPOConfig(), seed=0).policy).forward(np.zeros((2, 5), np.float32))
    with pytest.raises(ValueError, match="layer weight 0 must be a contiguous float32"):
        _learn.Actor([6, 4], [4, 2], [4, 1], [np.zeros((6, 4), np.float32)] + [None] * 5)


def _model() -> WorldModel:
    torch.manual_seed(0)
    model = WorldModel(WorldModelConfig(seed=0))
    with torch.no_grad():  # a model that drains: a steady outflow plus the net's output
        model.out_mean.fill_(-0.02)
        model.out_std.fill_(0.01)
    return model


@pytest.mark.parametrize("random_start", [False, True])
def test_the_numpy_model_env_is_the_torch_one(random_start):
    # Episodes end by draining (terminal) and by the step limit (truncated); the
    # same generator draws the random starts in both. Levels agree to float32
    # rounding (1e-6 m); rewards to 1e-4 (torch sums the reward in float32, the
    # NumPy step in float64).
    model = _model()
    envs = [ModelEnv(model, 8, 0.05, max_episode_steps=50, seed=2, random_start=random_start,
                     engine=engine) for engine in ("torch", "numpy")]
    for env in envs:
        env.reset()
    g = torch.Generator().manual_seed(5)
    ends = {"terminal": 0, "truncated": 0}
    for _ in range(200):
        a = torch.bernoulli(torch.full((8, 6), 0.4), generator=g)
        t, n = (env.step(a) for env in envs)
        assert torch.equal(n.terminal, t.terminal) and torch.equal(n.truncated, t.truncated)
        torch.testing.assert_close(n.obs, t.obs, atol=1e-6, rtol=0)
        torch.testing.assert_close(n.final_obs, t.final_obs, atol=1e-6, rtol=0)
        torch.testing.assert_close(n.reward, t.reward, atol=1e-4, rtol=0)
        assert n.obs.dtype == n.reward.dtype == torch.float32
        ends["terminal"] += int(t.terminal.sum())
        ends["truncated"] += int(t.truncated.sum())
        assert torch.equal(envs[1].steps, envs[0].steps)
    # full starts drain in 53 steps (truncated at 50); random starts end both ways
    assert ends["truncated"] > 0 and (ends["terminal"] > 0 or not random_start)
    assert torch.equal(envs[0].generator.get_state(), envs[1].generator.get_state())


def test_the_numpy_model_env_sees_a_refit_and_refuses_what_it_cannot_step():
    model = _model()
    env = ModelEnv(model, 2, 0.05, engine="numpy")
    env.reset()
    before = env.step(torch.zeros(2, 6)).final_obs
    with torch.no_grad():
        model.out_mean.fill_(-0.05)  # the refit writes in place; the env reads it
    env.reset()
    after = env.step(torch.zeros(2, 6)).final_obs
    assert float((before - after).min()) == pytest.approx(0.03, abs=1e-3)
    model.share_memory()  # moves every tensor's memory (pickling for a worker does)
    torch.zeros(64, 64).fill_(float("nan"))
    env.reset()
    moved = env.step(torch.zeros(2, 6)).final_obs
    torch.testing.assert_close(moved, after)
    with pytest.raises(ValueError, match="engine must be torch or numpy"):
        ModelEnv(model, 2, 0.05, engine="jax")
    with pytest.raises(ValueError, match="float32 world model"):
        ModelEnv(_model().double(), 2, 0.05, engine="numpy")


@pytest.mark.parametrize("engine,model_step", [("torch", "torch"), ("native", "numpy")])
def test_the_offline_phase_steps_the_model_with_the_ppo_engine(engine, model_step, monkeypatch):
    from ftc.learning import offline
    from ftc.learning.transitions import Transitions
    from ftc.plant import CorePlant

    seen = []

    class Spy(ModelEnv):  # records the engine offline_phase asks for, then steps as ModelEnv
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            seen.append(self.engine)

    monkeypatch.setattr(offline, "ModelEnv", Spy)
    plant = CorePlant("scenarios/single.toml", 0)
    obs = [plant.reset()]
    rng = np.random.default_rng(0)
    for _ in range(64):
        obs.append(plant.step(rng.integers(0, 2, 6)))
    config = PPOConfig(engine=engine)
    result = offline.offline_phase(
        PPO(config, seed=0).state_dict(), config, _model().state_dict(), 0,
        Transitions.from_observations(obs),
        offline.OfflineSettings(seed=0, steps=128, envs=4, rollout=16), interval=1)
    assert seen == [model_step]
    assert result.metrics["offline_updates"] == 2  # 128 steps / (4 envs x 16)
