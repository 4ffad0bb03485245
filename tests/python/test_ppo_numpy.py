"""The NumPy oracle of the native engine (oracles/ppo_numpy.py) and the native
engine itself (learning/ppo_native.py) are the torch update
(learning/ppo.py: ppo_update) up to float32 rounding: the same minibatches
from the same generator, the same clipped loss, gradient-norm clip and Adam.

Tolerances: float32 (epsilon 1.2e-7) with products summed in another order
gives ~1e-7 relative differences per step; Adam's division by sqrt(v) + eps
(eps = 1e-5) amplifies them in weights whose gradients are near zero, so
after a whole update (4 epochs x 8 minibatches = 32 steps) parameters are
compared at 2e-5 absolute + 1e-4 relative (measured: ~1e-6)."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch

from ftc.learning.buffer import RolloutBatch
from ftc.learning.distill import distill
from ftc.learning.ppo import PPO, PPOConfig, UpdateStats, ppo_update
from oracles.ppo_numpy import Net, numpy_ppo_update


def _batch(seed: int, n: int = 128, adv_scale: float = 1.0) -> RolloutBatch:
    g = torch.Generator().manual_seed(seed)
    obs = torch.rand(n, 6, generator=g)
    actions = (torch.rand(n, 6, generator=g) < 0.5).float()
    logprobs = -4.16 + 0.3 * torch.randn(n, generator=g)  # near 6 log(0.5): ratios near 1
    values = torch.randn(n, generator=g)
    advantages = adv_scale * torch.randn(n, generator=g)
    return RolloutBatch(obs, actions, logprobs, values, advantages, values + advantages)


def _both(config: PPOConfig, batch: RolloutBatch, updates: int = 1):
    torch_ppo = PPO(dataclasses.replace(config, engine="torch"), seed=3)
    numpy_ppo = PPO(dataclasses.replace(config, engine="native"), seed=3)
    stats = []
    for _ in range(updates):
        st = ppo_update(torch_ppo.policy, torch_ppo.optimizer, batch, torch_ppo.config,
                        torch_ppo.generator)
        sn = numpy_ppo_update(numpy_ppo.policy, numpy_ppo.optimizer, batch, numpy_ppo.config,
                              numpy_ppo.generator)
        stats.append((st, sn))
    return torch_ppo, numpy_ppo, stats


def _assert_same_policy(a: PPO, b: PPO, tol: float = 2e-5) -> None:
    moved = 0.0
    start = PPO(a.config, seed=3).policy.state_dict()
    for (name, pa), pb in zip(a.policy.state_dict().items(), b.policy.state_dict().values()):
        torch.testing.assert_close(pb, pa, atol=tol, rtol=1e-4, msg=name)
        moved = max(moved, float((pa - start[name]).abs().max()))
    assert moved > 1e-3  # the weights actually trained


@pytest.mark.parametrize("ent_coef", [0.0, 0.01, 0.5])
def test_update_matches_torch(ent_coef):
    config = PPOConfig(ent_coef=ent_coef)
    a, b, stats = _both(config, _batch(0))
    _assert_same_policy(a, b)
    (st, sn), = stats
    assert sn.gradient_steps == st.gradient_steps == 4 * 128 // 16
    for field in ("policy_loss", "value_loss", "entropy", "approx_kl", "explained_variance",
                  "open_fraction"):
        assert getattr(sn, field) == pytest.approx(getattr(st, field), rel=1e-3, abs=1e-5), field
    assert sn.clipfrac == pytest.approx(st.clipfrac, abs=1 / (128 * 4))


@pytest.mark.parametrize("lr,updates", [(2e-2, 1), (1e-3, 3)])
def test_clipping_and_gradient_norm_clip_are_active_and_match(lr, updates):
    # large advantages: ratios leave [0.8, 1.2] (clip fraction > 0.5) and the
    # gradient norm exceeds max_grad_norm, so both clips are exercised. At
    # lr 2e-2 over 3 updates the rounding differences grow to 2e-3 (a sample
    # crossing a clip boundary changes the step), so the large step is
    # compared over one update (measured 2.2e-6) and lr 1e-3 over three (1.2e-7).
    config = PPOConfig(learning_rate=lr, max_grad_norm=0.05)
    a, b, stats = _both(config, _batch(1, adv_scale=20.0), updates=updates)
    st, sn = stats[-1]
    assert sn.clipfrac == st.clipfrac > 0.5
    _assert_same_policy(a, b)


def test_optimizer_state_round_trips_through_torch():
    # the NumPy update leaves Adam's moments in the torch optimiser: a torch
    # update after a NumPy one continues from them exactly as after a torch one
    config = PPOConfig()
    a, b, _ = _both(config, _batch(2))
    for pa, pb in zip(a.optimizer.state.values(), b.optimizer.state.values()):
        assert float(pa["step"]) == float(pb["step"]) == 32
        torch.testing.assert_close(pb["exp_avg"], pa["exp_avg"], atol=1e-6, rtol=1e-3)
    state = copy.deepcopy(b.state_dict())
    c = PPO(dataclasses.replace(config, engine="torch"), seed=9)
    c.load_state_dict(state)  # loadable as any checkpoint
    ppo_update(a.policy, a.optimizer, _batch(4), a.config, a.generator)
    ppo_update(c.policy, c.optimizer, _batch(4), c.config, c.generator)
    _assert_same_policy(a, c, tol=5e-5)


def test_target_kl_stops_both_after_the_same_epoch():
    config = PPOConfig(learning_rate=2e-2, target_kl=1e-3)
    _, _, stats = _both(config, _batch(5, adv_scale=5.0))
    (st, sn), = stats
    assert sn.gradient_steps == st.gradient_steps < 4 * 8


def test_value_clipping_is_torch_only_and_off_by_default():
    # torch's update clips the value only when asked (PPOConfig's default is off),
    # the native kernels never: the native engine refuses the option rather
    # than train differently from what the config says
    assert PPOConfig().clip_vloss is False and PPOConfig().engine == "native"
    with pytest.raises(ValueError, match="--ppo-clip-vloss needs --ppo-engine torch"):
        PPO(PPOConfig(clip_vloss=True), seed=0)
    ppo = PPO(PPOConfig(), seed=0)
    ppo.config = dataclasses.replace(ppo.config, clip_vloss=True)  # past the check: still refused
    with pytest.raises(ValueError, match="no value clipping"):
        ppo.engine.update(ppo.policy, ppo.optimizer, _batch(0), ppo.config, ppo.generator)
    # torch with it: a different critic step from torch without it
    runs = []
    for clip in (False, True):
        t = PPO(PPOConfig(engine="torch", clip_vloss=clip), seed=0)
        ppo_update(t.policy, t.optimizer, _batch(0, adv_scale=5.0), t.config, t.generator)
        runs.append(t.policy.value_head.state_dict())
    assert any(not torch.equal(runs[0][k], runs[1][k]) for k in runs[0])


def test_numpy_is_a_deprecated_name_of_the_native_engine(capsys):
    assert PPOConfig(engine="native").engine == "native"
    assert "deprecated name of --ppo-engine native" in capsys.readouterr().err \
        or PPOConfig(engine="native").engine == "native"  # warned once per process


def test_numpy_acting_draws_the_same_valves_as_torch():
    # the same generator stream and probabilities equal to ~1e-7: a uniform draw
    # would have to fall within 1e-7 of p to flip a valve (none in 6,000 here)
    torch_ppo = PPO(PPOConfig(engine="torch"), seed=4)
    numpy_ppo = PPO(PPOConfig(engine="native"), seed=4)
    ppo_update(torch_ppo.policy, torch_ppo.optimizer, _batch(6), torch_ppo.config,
               torch_ppo.generator)  # trained weights, not the init's near-0.5 probabilities
    numpy_ppo.load_state_dict(torch_ppo.state_dict())
    obs_gen = torch.Generator().manual_seed(7)
    for n in (1, 16):
        for deterministic in (False, True):
            for _ in range(25):
                obs = torch.rand(n, 6, generator=obs_gen)
                at, lt, vt = torch_ppo.act(obs, deterministic)
                an, ln, vn = numpy_ppo.act(obs, deterministic)
                assert torch.equal(at, an)
                torch.testing.assert_close(ln, lt, atol=1e-5, rtol=1e-5)
                torch.testing.assert_close(vn, vt, atol=1e-6, rtol=1e-5)


def test_numpy_acting_sees_weights_loaded_later():
    ppo = PPO(PPOConfig(engine="native"), seed=0)
    obs = torch.rand(4, 6, generator=torch.Generator().manual_seed(1))
    before = ppo.act(obs, deterministic=True)[2]
    other = PPO(PPOConfig(engine="torch"), seed=1)
    ppo.load_state_dict(other.state_dict())
    after = ppo.act(obs, deterministic=True)[2]
    torch.testing.assert_close(after, other.policy.value(obs).detach(), atol=1e-6, rtol=1e-5)
    assert not torch.allclose(before, after)


@pytest.mark.parametrize("max_grad_norm", [0.5, 0.01])
def test_distillation_matches_torch(max_grad_norm):
    # behaviour cloning of planner labels (ppo-robust): the same minibatches,
    # BCE, norm clip (0.01: active on every step) and Adam; the value head
    # is not touched by either
    g = torch.Generator().manual_seed(8)
    states = torch.rand(300, 6, generator=g)
    labels = (states[:, :1] > states[:, 1:2]).float().expand(-1, 6).contiguous()
    a = PPO(PPOConfig(engine="torch", max_grad_norm=max_grad_norm), seed=2)
    b = PPO(PPOConfig(engine="native", max_grad_norm=max_grad_norm), seed=2)
    value_before = {k: v.clone() for k, v in b.policy.value_head.state_dict().items()}
    ra = distill(a, states, labels, epochs=3, seed=5)
    rb = distill(b, states, labels, epochs=3, seed=5)
    _assert_same_policy(a, b)
    assert rb["distill_loss"] == pytest.approx(ra["distill_loss"], rel=1e-4)
    assert rb["distill_agreement"] == ra["distill_agreement"]
    for k, v in b.policy.value_head.state_dict().items():
        assert torch.equal(v, value_before[k]), k


@pytest.mark.parametrize("engine", ["torch", "native"])
def test_distillation_stops_once_an_epoch_is_below_the_stop_loss(engine):
    # a label that is one valve's own input threshold: learnable; the epoch-mean
    # BCE starts near log 2 = 0.69 (a fresh policy opens with p ~ 0.5)
    g = torch.Generator().manual_seed(8)
    states = torch.rand(256, 6, generator=g)
    labels = (states > 0.5).float()
    runs = {}
    for stop in (0.0, 0.6, 1.0):
        ppo = PPO(PPOConfig(engine=engine), seed=2)
        runs[stop] = distill(ppo, states, labels, epochs=40, seed=5, stop_loss=stop)
    assert runs[0.0]["distill_epochs"] == 40           # 0: never stops early
    assert runs[1.0]["distill_epochs"] == 1            # above any epoch's loss: one epoch
    assert 1 < runs[0.6]["distill_epochs"] < 40        # stops when it crosses 0.6
    assert runs[0.6]["distill_loss"] > runs[0.0]["distill_loss"]
    assert runs[0.0]["distill_agreement"] > 0.8  # learnt (chance: 0.5)


@pytest.mark.parametrize("engine", ["torch", "native"])
def test_distinct_rows_weighted_by_count_are_the_same_objective(engine):
    # 40 distinct states, each repeated 1-5 times (as an interval's episodes repeat
    # levels): with one minibatch holding all the rows, a step on the repeated rows
    # and a step on the distinct ones weighted by their counts have the same loss
    # and gradient, so two epochs leave the same policy (float32 rounding of the
    # sums in another order: 1e-5 on the weights, measured ~1e-7)
    from ftc.learning.distill import distinct

    g = torch.Generator().manual_seed(3)
    base = torch.rand(40, 6, generator=g)
    repeats = torch.randint(1, 6, (40,), generator=g)
    states = base.repeat_interleave(repeats, dim=0)
    labels = (states > 0.4).float()
    rows, acts, counts = distinct(states.numpy(), labels.numpy())
    assert len(rows) == 40 and float(counts.sum()) == len(states)
    full = PPO(PPOConfig(engine=engine), seed=2)
    weighted = PPO(PPOConfig(engine=engine), seed=2)
    ra = distill(full, states, labels, epochs=2, minibatch=len(states), seed=5)
    rb = distill(weighted, rows, acts, epochs=2, minibatch=len(states), seed=5, weights=counts)
    assert rb["distill_loss"] == pytest.approx(ra["distill_loss"], rel=1e-5)
    assert rb["distill_agreement"] == pytest.approx(ra["distill_agreement"], abs=1e-6)
    for (k, va), vb in zip(full.policy.state_dict().items(), weighted.policy.state_dict().values()):
        torch.testing.assert_close(vb, va, rtol=0, atol=1e-5, msg=k)


def test_weighted_distillation_matches_torch():
    g = torch.Generator().manual_seed(8)
    states = torch.rand(300, 6, generator=g)
    labels = (states[:, :1] > states[:, 1:2]).float().expand(-1, 6).contiguous()
    weights = torch.randint(1, 9, (300,), generator=g).float()
    a = PPO(PPOConfig(engine="torch"), seed=2)
    b = PPO(PPOConfig(engine="native"), seed=2)
    ra = distill(a, states, labels, epochs=3, seed=5, weights=weights)
    rb = distill(b, states, labels, epochs=3, seed=5, weights=weights)
    _assert_same_policy(a, b)
    assert rb["distill_loss"] == pytest.approx(ra["distill_loss"], rel=1e-4)
    # a logit within rounding of 0 may fall either side: at most one valve decision
    # (weight <= 8 of the 6 x sum(weights) weighted decisions) may differ
    one_decision = 8.0 / (6 * float(weights.sum()))
    assert rb["distill_agreement"] == pytest.approx(ra["distill_agreement"], abs=one_decision)


def test_flat_parameters_are_the_layers_and_the_norm_is_summed_per_layer():
    """Net keeps every weight in one flat vector (so Adam and the clip are
    whole-vector calls): the layers must be views of it in parameter order,
    backward must fill the flat gradient, and the clip's norm must be the
    per-layer float32 sums added in order, bit for bit, as before the flat
    layout (a different summation order would change results in the 7th digit)."""
    ppo = PPO(PPOConfig(engine="native"), seed=4)
    net = Net(ppo.policy)
    for view, p in zip(net.params, ppo.policy.parameters()):
        assert np.shares_memory(view, net.flat)
        np.testing.assert_array_equal(view, p.detach().numpy().T if p.dim() == 2
                                      else p.detach().numpy())
    x = np.random.default_rng(0).random((32, 6)).astype(np.float32)
    logits, value, cache = net.forward(x)
    grad = net.backward(cache, np.ones_like(logits) / logits.size, value / len(value))
    assert grad is net.grad and np.all(np.isfinite(grad)) and np.count_nonzero(grad) > 0.9 * grad.size
    per_layer = sum(float(np.sum(g * g)) for g in (a.copy() for a in net.grads))
    assert net.norm(len(grad)) == np.sqrt(per_layer)
    # the policy-only pass leaves the value head's gradient alone and gives the
    # trunk the policy head's gradient alone (what a zero value gradient gives)
    before_v = net.grad[net.size("trunk", "pi"):].copy()
    net.backward(cache, np.ones_like(logits) / logits.size, None)
    only_pi = net.grad.copy()
    np.testing.assert_array_equal(only_pi[net.size("trunk", "pi"):], before_v)
    net.backward(cache, np.ones_like(logits) / logits.size, np.zeros_like(value))
    k = net.size("trunk", "pi")
    np.testing.assert_array_equal(only_pi[:k], net.grad[:k])
