"""The C++ behaviour cloning (ftc._learn.distill, cpp/learning/tanh_mlp.cpp)
against its NumPy oracle (oracles/ppo_numpy.py: numpy_distill): the
same minibatches, loss, clip and Adam, so the same fit up to float32 rounding
(products summed in another order, another tanh approximation). Measured: 3e-7
on the weights after 480 Adam steps; compared at 1e-5 (Adam's division by
sqrt(v) + 1e-5 amplifies rounding where gradients are near zero). test_ppo_numpy.py
checks the same fit, through ``distill``, against torch; the C++ tests
(test_learn_tanh_mlp.cpp) check gradients against finite differences."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ftc import _learn
from ftc.learning.ppo import ActorCritic
from ftc.learning.ppo_native import native_distill
from oracles.ppo_numpy import numpy_distill


def _data(n: int = 700):
    g = torch.Generator().manual_seed(4)
    states = torch.rand(n, 6, generator=g)
    labels = (states[:, :3] > states[:, 3:]).float().repeat(1, 2)
    weights = torch.randint(1, 6, (n,), generator=g).float()
    return states, labels, weights


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("max_grad_norm", [0.5, 0.01])  # 0.01: the clip acts on every step
def test_native_distillation_is_the_numpy_one(weighted, max_grad_norm):
    states, labels, weights = _data()
    fits = []
    for fit in (numpy_distill, native_distill):
        torch.manual_seed(1)
        policy = ActorCritic()
        start = [p.detach().clone() for p in policy.parameters()]
        loss, epochs = fit(policy, states, labels, epochs=8, minibatch=128, lr=1e-3,
                           max_grad_norm=max_grad_norm, generator=torch.Generator().manual_seed(0),
                           weights=weights if weighted else None)
        fits.append((loss, epochs, [p.detach().clone() for p in policy.parameters()], start))
    (loss_np, epochs_np, after_np, start), (loss_c, epochs_c, after_c, _) = fits
    assert epochs_c == epochs_np == 8
    assert loss_c == pytest.approx(loss_np, rel=1e-5)
    moved = max(float((a - s).abs().max()) for a, s in zip(after_np, start))
    assert moved > 1e-3  # it trained
    for a, b in zip(after_np, after_c):
        torch.testing.assert_close(b, a, rtol=0, atol=1e-5)


def test_native_distillation_stops_where_the_numpy_one_does():
    states, labels, _ = _data(300)
    ran = []
    for fit in (numpy_distill, native_distill):
        torch.manual_seed(1)
        _, epochs = fit(ActorCritic(), states, labels, epochs=200, minibatch=64, lr=3e-3,
                        max_grad_norm=0.5, generator=torch.Generator().manual_seed(0),
                        stop_loss=0.3)
        ran.append(epochs)
    assert 1 < ran[0] < 200
    assert ran[1] == ran[0]


def test_the_kernel_names_what_is_wrong():
    params = np.full(7 * 64 + 65, 0.1, np.float32)  # (6 + 1) x 64, then (64 + 1) x 1
    x, y = np.zeros((4, 6), np.float32), np.zeros((4, 1), np.float32)
    orders = np.tile(np.arange(4), (2, 1))
    args = dict(trunk=[6, 64], head=[64, 1], x=x, y=y, weights=None, orders=orders,
                minibatch=2, lr=1e-3, max_grad_norm=0.5)
    _learn.distill(params, **args)  # well-formed: runs
    assert np.any(params != np.float32(0.1))
    with pytest.raises(ValueError, match="params must be a float32 vector"):
        _learn.distill(params.astype(np.float64), **args)  # a converted copy would lose the fit
    with pytest.raises(ValueError, match="writable"):
        frozen = params.copy()
        frozen.flags.writeable = False
        _learn.distill(frozen, **args)
    with pytest.raises(ValueError, match=r"x must be \(N, 6\)"):
        _learn.distill(params, **{**args, "x": np.zeros((4, 5), np.float32)})
    with pytest.raises(ValueError, match=r"orders must be \(epochs, 4\)"):
        _learn.distill(params, **{**args, "orders": np.zeros((2, 3), np.int64)})
    with pytest.raises(ValueError, match="out of range"):
        _learn.distill(params, **{**args, "orders": orders + 1})
    with pytest.raises(ValueError, match=r"weights must be \(4,\)"):
        _learn.distill(params, **{**args, "weights": np.ones(3, np.float32)})


def test_the_fit_does_not_depend_on_where_the_weights_lie_in_memory():
    # Eigen's vectorised loops split their work by alignment: the kernel copies the
    # weights into its own aligned buffer, so the same fit from arrays at other
    # addresses is the same to the bit (it was not before: ppo-robust runs differed)
    states, labels, weights = _data(400)
    orders = np.stack([torch.randperm(400, generator=torch.Generator().manual_seed(e)).numpy()
                       for e in range(3)])
    torch.manual_seed(1)
    start = np.concatenate([p.detach().numpy().ravel() for p in ActorCritic().parameters()])
    results = set()
    for offset in range(5):  # float32 offsets: 4-byte steps through every alignment class
        buffer = np.zeros(len(start) + 16, np.float32)
        params = buffer[offset:offset + len(start)]
        params[:] = start
        _learn.distill(params, [6, 64, 64], [64, 16, 16, 6], states.numpy(), labels.numpy(),
                       weights.numpy(), orders, 128, 1e-3, 0.5)
        results.add(params.tobytes())
    assert len(results) == 1


def test_no_epochs_fit_nothing_as_the_numpy_fit():
    states, labels, _ = _data(50)
    for fit in (numpy_distill, native_distill):
        policy = ActorCritic()
        before = [p.detach().clone() for p in policy.parameters()]
        loss, epochs = fit(policy, states, labels, epochs=0, minibatch=16, lr=1e-3,
                           max_grad_norm=0.5, generator=torch.Generator().manual_seed(0))
        assert epochs == 0 and np.isnan(loss)
        assert all(torch.equal(a, b) for a, b in zip(before, policy.parameters()))
