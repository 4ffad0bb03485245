"""Training of small MLPs in NumPy, outside torch's per-call overhead.

The world model (2 x 64 ReLU, minibatches of 64 rows) is refitted after every
interval, and a refit is several hundred Adam steps. At these sizes each
torch step is dominated by dispatch, autograd bookkeeping and the optimiser's
per-parameter loop (about 1 ms per step on this machine), not by arithmetic;
the same step written as a dozen NumPy calls on preallocated arrays is several
times faster (``scripts/bench.py``: ``world_model_fit_speedup``).

:class:`SmallMLP` holds a float32 copy of an ``nn.Sequential`` of ``Linear``
layers and element-wise activations, computes the forward pass, the gradient
of the mean squared error by hand, and applies Adam with torch's formulae
(L2 weight decay added to the gradient, bias-corrected moments, ``eps``
outside the square root), so a fit follows the same algorithm, minibatches
and early stopping as the torch loop; only float32 rounding differs
(matrix products sum in another order), which tests bound.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

_ACTIVATIONS = (nn.ReLU, nn.Tanh, nn.ELU)


@dataclass
class AdamSettings:
    """torch.optim.Adam's hyperparameters (its defaults)."""

    lr: float = 1e-3
    beta1: float = 0.9
    beta2: float = 0.999
    eps: float = 1e-8
    weight_decay: float = 0.0


class SmallMLP:
    """A NumPy float32 copy of ``net`` (Linear and ReLU/Tanh/ELU layers only).

    Weights are stored transposed, (in, out), so a forward pass is x @ W + b.
    :meth:`load_into` writes the (trained) weights back into a torch module
    of the same structure.
    """

    def __init__(self, net: nn.Sequential, adam: AdamSettings | None = None, *,
                 share: bool = False) -> None:
        """``share``: the weights are views of ``net``'s float32 parameters
        instead of copies, so :meth:`forward` always computes with the module's
        current weights (for acting or predicting; training would write into it)."""
        def array(t: torch.Tensor) -> np.ndarray:
            a = t.detach().numpy()
            if share and a.dtype != np.float32:
                raise ValueError(f"SmallMLP(share=True) needs float32 parameters, got {a.dtype}")
            return a if share else a.astype(np.float32)

        self.weights: list[np.ndarray] = []
        self.biases: list[np.ndarray] = []
        self.activations: list[type[nn.Module] | None] = []
        for layer in net:
            if isinstance(layer, nn.Linear):
                self.weights.append(array(layer.weight.T))
                self.biases.append(array(layer.bias))
                self.activations.append(None)
            elif isinstance(layer, _ACTIVATIONS) and self.activations \
                    and self.activations[-1] is None:
                if isinstance(layer, nn.ELU) and layer.alpha != 1.0:
                    raise ValueError("SmallMLP supports ELU with alpha = 1 only")
                self.activations[-1] = type(layer)
            else:
                raise ValueError(f"SmallMLP cannot train a {type(layer).__name__} layer")
        self.adam = adam or AdamSettings()
        params = self.parameters()
        self._m = [np.zeros_like(p) for p in params]
        self._v = [np.zeros_like(p) for p in params]
        self._t = 0

    def parameters(self) -> list[np.ndarray]:
        """Weights then biases, layer by layer (the arrays themselves)."""
        return [*self.weights, *self.biases]

    def snapshot(self) -> list[np.ndarray]:
        return [p.copy() for p in self.parameters()]

    def restore(self, snapshot: list[np.ndarray]) -> None:
        for p, saved in zip(self.parameters(), snapshot):
            p[...] = saved

    def load_into(self, net: nn.Sequential) -> None:
        """Copy the weights into ``net`` (the module this copy was made from)."""
        linears = [m for m in net if isinstance(m, nn.Linear)]
        for layer, w, b in zip(linears, self.weights, self.biases):
            layer.weight.data.copy_(_tensor(w.T))
            layer.bias.data.copy_(_tensor(b))

    # -- forward and backward ----------------------------------------------------
    def forward(self, x: np.ndarray) -> np.ndarray:
        """Output (B, out) of inputs (B, in), float32."""
        return self._forward(x)[-1]

    def _forward(self, x: np.ndarray) -> list[np.ndarray]:
        """Inputs of every layer, then the output."""
        h = [x]
        for w, b, act in zip(self.weights, self.biases, self.activations):
            z = h[-1] @ w
            z += b
            if act is nn.ReLU:
                np.maximum(z, 0.0, out=z)
            elif act is nn.Tanh:
                np.tanh(z, out=z)
            elif act is nn.ELU:
                z = np.where(z > 0.0, z, np.expm1(np.minimum(z, 0.0)))
            h.append(z)
        return h

    def mse(self, x: np.ndarray, y: np.ndarray) -> float:
        """Mean over rows and outputs of (f(x) - y)^2."""
        d = self.forward(x) - y
        return float(np.mean(d * d))

    def mse_step(self, x: np.ndarray, y: np.ndarray) -> float:
        """One Adam step on the mean squared error of the batch; returns the
        loss before the step (as the torch loop's ``loss``)."""
        h = self._forward(x)
        d = h[-1] - y
        loss = float(np.mean(d * d))
        grad = d * np.float32(2.0 / d.size)  # d loss / d output
        n = len(self.weights)
        grads_w: list[np.ndarray] = [None] * n  # type: ignore[list-item]
        grads_b: list[np.ndarray] = [None] * n  # type: ignore[list-item]
        for i in range(n - 1, -1, -1):
            grads_w[i] = h[i].T @ grad
            grads_b[i] = grad.sum(axis=0)
            if i:
                grad = grad @ self.weights[i].T
                grad *= _activation_slope(self.activations[i - 1], h[i])
        self._adam_step([*grads_w, *grads_b])
        return loss

    def _adam_step(self, grads: list[np.ndarray]) -> None:
        self._t += 1
        for p, g, m, v in zip(self.parameters(), grads, self._m, self._v):
            adam_step(p, g, m, v, self._t, self.adam)


def adam_step(p: np.ndarray, g: np.ndarray, m: np.ndarray, v: np.ndarray, t: int,
              a: AdamSettings) -> None:
    """torch.optim.Adam's update of ``p`` in place from its gradient ``g``, with
    moments ``m``, ``v`` (updated in place) at step ``t`` (1 for the first): L2
    weight decay added to the gradient, bias-corrected moments, ``eps`` outside
    the square root."""
    step_size = a.lr / (1.0 - a.beta1 ** t)
    root_correction = np.sqrt(1.0 - a.beta2 ** t)
    if a.weight_decay:
        g = g + a.weight_decay * p
    m *= a.beta1
    m += (1.0 - a.beta1) * g
    v *= a.beta2
    v += (1.0 - a.beta2) * (g * g)
    denom = np.sqrt(v)
    denom /= root_correction
    denom += a.eps
    p -= step_size * (m / denom)


def _activation_slope(act: type[nn.Module] | None, out: np.ndarray) -> np.ndarray | float:
    """d act(z) / dz expressed through the activation's output ``out``."""
    if act is nn.ReLU:
        return (out > 0.0).astype(np.float32)
    if act is nn.Tanh:
        return 1.0 - out * out
    if act is nn.ELU:  # out = z (z > 0) or e^z - 1: slope 1 or out + 1
        return np.where(out > 0.0, np.float32(1.0), out + 1.0)
    return 1.0


def _tensor(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a))
