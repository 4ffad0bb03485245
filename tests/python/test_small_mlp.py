"""The NumPy trainer of small MLPs (learning/small_mlp.py) computes the same
Adam steps as torch.optim.Adam on autograd's gradients, and a world-model fit
with it lands where the torch fit lands.

Tolerances: both compute in float32 (machine epsilon 1.2e-7); one step
differs only by the order of summation in the matrix products, so parameters
agree to ~1e-6 relative. Adam divides by sqrt(v) + eps, which amplifies
rounding in weights whose gradients are ~0, so the bounds are 1e-5 relative
plus 1e-6 absolute after one step and 1e-4 after 50 steps (measured max
differences: a few 1e-7 and a few 1e-6)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from ftc.learning.small_mlp import AdamSettings, SmallMLP
from ftc.learning.transitions import collect_nominal_dataset
from ftc.learning.world_model import WorldModel, WorldModelConfig


def _net(act: type[nn.Module], seed: int = 0) -> nn.Sequential:
    torch.manual_seed(seed)
    return nn.Sequential(nn.Linear(12, 32), act(), nn.Linear(32, 16), act(), nn.Linear(16, 6))


def _torch_steps(net: nn.Sequential, x: torch.Tensor, y: torch.Tensor, steps: int,
                 weight_decay: float) -> list[float]:
    opt = torch.optim.Adam(net.parameters(), lr=1e-2, weight_decay=weight_decay)
    losses = []
    for _ in range(steps):
        loss = torch.mean((net(x) - y) ** 2)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    return losses


@pytest.mark.parametrize("act", [nn.ReLU, nn.Tanh, nn.ELU])
@pytest.mark.parametrize("steps,tol", [(1, 1e-5), (50, 1e-4)])
@pytest.mark.parametrize("weight_decay", [0.0, 0.01])
def test_adam_steps_match_torch(act, steps, tol, weight_decay):
    gen = torch.Generator().manual_seed(1)
    x, y = torch.randn(40, 12, generator=gen), torch.randn(40, 6, generator=gen)
    reference, ours = _net(act), _net(act)
    mlp = SmallMLP(ours, AdamSettings(lr=1e-2, weight_decay=weight_decay))
    losses = [mlp.mse_step(x.numpy(), y.numpy()) for _ in range(steps)]
    expected = _torch_steps(reference, x, y, steps, weight_decay)
    np.testing.assert_allclose(losses, expected, rtol=tol)
    mlp.load_into(ours)
    moved = 0.0
    for (name, a), b, start in zip(reference.named_parameters(), ours.parameters(),
                                   _net(act).parameters()):
        torch.testing.assert_close(b, a, rtol=tol, atol=tol / 10, msg=name)
        moved = max(moved, float((a.detach() - start.detach()).abs().max()))
    assert moved > 1e-3  # the comparison is of weights that actually trained


def test_forward_and_mse_match_torch():
    net = _net(nn.Tanh)
    x = torch.randn(7, 12, generator=torch.Generator().manual_seed(2))
    mlp = SmallMLP(net)
    np.testing.assert_allclose(mlp.forward(x.numpy()), net(x).detach().numpy(), rtol=1e-5,
                               atol=1e-6)


def test_unsupported_layers_are_refused():
    with pytest.raises(ValueError, match="Dropout"):
        SmallMLP(nn.Sequential(nn.Linear(3, 3), nn.Dropout(0.1), nn.Linear(3, 1)))
    with pytest.raises(ValueError, match="alpha"):
        SmallMLP(nn.Sequential(nn.Linear(3, 3), nn.ELU(alpha=0.5), nn.Linear(3, 1)))


def test_world_model_fit_engines_agree():
    # The same minibatches and stopping rule: the two fits stop within a few
    # epochs of each other and reach the same held-out loss to 2% (measured
    # on 50 episodes: 110 epochs both, val loss 0.26248 vs 0.26277, change
    # R^2 0.7333 vs 0.7330).
    data = collect_nominal_dataset(12, seed=5)
    reports = {}
    for engine in ("torch", "numpy"):
        model = WorldModel(WorldModelConfig(seed=5, engine=engine, max_epochs=60))
        reports[engine] = model.fit(data, warm_start=False)
    t, n = reports["torch"], reports["numpy"]
    assert abs(t.epochs - n.epochs) <= 5
    assert n.val_loss == pytest.approx(t.val_loss, rel=0.02)
    assert n.r2_change == pytest.approx(t.r2_change, abs=0.01)
    assert n.val_loss < 0.7 * n.initial_val_loss  # it learned (measured: 0.45 from 0.74)


def test_unknown_engine_is_refused():
    with pytest.raises(ValueError, match="engine"):
        WorldModelConfig(engine="jax")
