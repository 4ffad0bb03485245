"""The test oracle of the native PPO engine: PPO's update, acting and
behaviour cloning in NumPy, with gradients derived by hand.

The native engine (python/ftc/learning/ppo_native.py) runs the same
arithmetic in C++ (cpp/learning). This NumPy version is what the tests hold
the C++ to (test_native_ppo.py, test_native_distill.py) and what they hold
to torch (test_ppo_numpy.py): readable formulae between autograd and the
kernels. It builds on the engine's own pieces (the flat parameter layout,
the Adam state shared with the torch optimiser, the update's loop) and on
the package's one NumPy Adam (ftc.learning.small_mlp.adam_step), so what it
checks is the arithmetic of an epoch, of acting and of a fit.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ftc.learning.ppo_native import AdamMoments, FlatParams, NativeActor, flat_ppo_update
from ftc.learning.ppo_policy import ActorCritic, PPOConfig, UpdateStats
from ftc.learning.small_mlp import AdamSettings, adam_step


class Net(FlatParams):
    """:class:`FlatParams` with a forward and a backward pass in NumPy.

    Each part is a list of (W (in, out), b (out,)) views of :attr:`flat`;
    every layer but the last of each head is followed by tanh, as is every
    trunk layer. :meth:`backward` writes the gradients into views of another
    flat vector, :attr:`grad`, so Adam and the gradient-norm clip are a few
    NumPy calls on whole vectors."""

    def __init__(self, policy: ActorCritic) -> None:
        super().__init__(policy)
        self.grad = np.zeros_like(self.flat)
        shapes = [p.shape for p in self.params]
        self.grads = [self.grad[a:b].reshape(shape) for (a, b), shape in zip(self.bounds, shapes)]
        self.layer_grads, i = {}, 0
        for name, part in self.modules.items():
            self.layer_grads[name] = [[self.grads[i + 2 * k], self.grads[i + 2 * k + 1]]
                                      for k in range(len(part))]
            i += 2 * len(part)

    def norm(self, n: int) -> float:
        """The global L2 norm of the first ``n`` entries of :attr:`grad` (whole
        parameters), summed per parameter in float32."""
        sq = self.grad[:n] * self.grad[:n]
        total = 0.0
        for a, b in self.bounds:
            if b > n:
                break
            total += float(np.add.reduce(sq[a:b]))
        return math.sqrt(total)

    def forward(self, obs: np.ndarray, value: bool = True
                ) -> tuple[np.ndarray, np.ndarray | None, dict]:
        """logits (B, 6), value (B,) (None unless ``value``), and the activations
        the backward pass needs."""
        h = [2.0 * obs - 1.0]
        for w, b in self.layers["trunk"]:
            h.append(np.tanh(h[-1] @ w + b))
        cache = {"trunk": h}
        outs = []
        for name in ("pi", "v") if value else ("pi",):
            a = [h[-1]]
            layers = self.layers[name]
            for i, (w, b) in enumerate(layers):
                z = a[-1] @ w + b
                a.append(np.tanh(z) if i < len(layers) - 1 else z)
            cache[name] = a
            outs.append(a[-1])
        return outs[0], outs[1][:, 0] if value else None, cache

    def backward(self, cache: dict, d_logits: np.ndarray, d_value: np.ndarray | None
                 ) -> np.ndarray:
        """Gradients of the loss into :attr:`grad` (returned), from its gradients
        with respect to the logits (B, 6) and the value (B,); ``d_value`` None: the
        loss does not depend on the value (the value head's gradients are left
        as they were, and the trunk's are the policy head's alone)."""
        heads = (("pi", d_logits),) if d_value is None else (("pi", d_logits),
                                                              ("v", d_value[:, None]))
        d_trunk_out = 0.0
        for name, d_out in heads:
            d_in = _backward_mlp(self.layers[name], cache[name], d_out, self.layer_grads[name])
            d_trunk_out = d_trunk_out + d_in
        _backward_mlp(self.layers["trunk"], cache["trunk"], d_trunk_out,
                      self.layer_grads["trunk"], tanh_last=True, input_grad=False)
        return self.grad


def _backward_mlp(layers: list[list[np.ndarray]], acts: list[np.ndarray], d_out: np.ndarray,
                  grads: list[list[np.ndarray]], tanh_last: bool = False,
                  input_grad: bool = True) -> np.ndarray | None:
    """Backprop through x -> tanh(x W1 + b1) -> ... -> x Wn + bn (tanh too if
    ``tanh_last``); ``acts`` = [input, output of each layer]. Writes each
    layer's [dW, db] into ``grads`` and returns the gradient with respect to
    the input (None unless ``input_grad``)."""
    d = d_out
    for i in range(len(layers) - 1, -1, -1):
        if i < len(layers) - 1 or tanh_last:
            d = d * (1.0 - acts[i + 1] * acts[i + 1])
        np.matmul(acts[i].T, d, out=grads[i][0])
        np.add.reduce(d, axis=0, out=grads[i][1])
        if i or input_grad:
            d = d @ layers[i][0].T
    return d if input_grad else None


def _logsigmoid(x: np.ndarray) -> np.ndarray:
    return -np.logaddexp(0.0, -x)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return np.exp(_logsigmoid(x))


def log_prob(logits: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """As :meth:`ActorCritic.log_prob`: (B,), summed over valves."""
    return (actions * _logsigmoid(logits) + (1.0 - actions) * _logsigmoid(-logits)).sum(-1)


def _clip(net: Net, n: int, max_grad_norm: float) -> None:
    """torch's clip_grad_norm_ of the first ``n`` entries of the gradient."""
    scale = max_grad_norm / (net.norm(n) + 1e-6)
    if scale < 1.0:
        net.grad[:n] *= np.float32(scale)


def numpy_epoch(net: Net, opt: AdamMoments, config: PPOConfig, minibatch: int,
                order: np.ndarray, obs: np.ndarray, actions: np.ndarray,
                old_logprobs: np.ndarray, advantages: np.ndarray, returns: np.ndarray):
    """One epoch of PPO's gradient steps in NumPy (the kernel's ppo_epoch)."""
    kls, clipfracs = [], []
    pg_loss = v_loss = 0.0
    adam = AdamSettings(lr=opt.lr, beta1=opt.beta1, beta2=opt.beta2, eps=opt.eps)
    for start in range(0, len(order), minibatch):
        idx = order[start:start + minibatch]
        n = len(idx)
        logits, value, cache = net.forward(obs[idx])
        a = actions[idx]
        logprob = log_prob(logits, a)
        log_ratio = logprob - old_logprobs[idx]
        ratio = np.exp(log_ratio)
        kls.append(float(np.mean((ratio - 1.0) - log_ratio)))
        clipfracs.append(float(np.mean(np.abs(ratio - 1.0) > config.clip_coef)))

        adv = advantages[idx]
        if config.norm_adv and n > 1:
            adv = (adv - adv.mean()) / (adv.std(ddof=1) + 1e-8)
        unclipped = -adv * ratio
        clipped = -adv * np.clip(ratio, 1.0 - config.clip_coef, 1.0 + config.clip_coef)
        pg_loss = float(np.mean(np.maximum(unclipped, clipped)))
        v_loss = float(0.5 * np.mean((value - returns[idx]) ** 2))

        # d loss / d logprob: through the ratio wherever the unclipped term is
        # the max (where the two are equal the clip is inactive: the same slope)
        d_logprob = np.where(unclipped >= clipped, unclipped, 0.0) / n
        sig = _sigmoid(logits)
        d_logits = d_logprob[:, None] * (a - sig) \
            + (config.ent_coef / n) * sig * (1.0 - sig) * logits
        d_value = config.vf_coef * (value - returns[idx]) / n
        grad = net.backward(cache, d_logits.astype(np.float32), d_value.astype(np.float32))
        _clip(net, len(grad), config.max_grad_norm)
        opt.t += 1
        adam_step(net.flat, grad, opt.m, opt.v, opt.t, adam)
    return np.array(kls), np.array(clipfracs), pg_loss, v_loss, opt.t


def numpy_ppo_update(policy: ActorCritic, optimizer: torch.optim.Optimizer, batch,
                     config: PPOConfig, generator: torch.Generator | None) -> UpdateStats:
    """The native engine's update with each epoch in NumPy."""
    return flat_ppo_update(policy, optimizer, batch, config, generator, epoch=numpy_epoch,
                           net_type=Net)


class NumpyActor(NativeActor):
    """:class:`NativeActor` with the forward pass in NumPy on views of the
    torch weights (W.T as a view, no copy)."""

    def __init__(self, policy: ActorCritic) -> None:
        super().__init__(policy)
        parts = [[m for m in part.modules() if isinstance(m, torch.nn.Linear)]
                 for part in (policy.trunk, policy.policy_head, policy.value_head)]
        self.trunk, self.pi, self.v = ([(m.weight.detach().numpy().T, m.bias.detach().numpy())
                                        for m in part] for part in parts)
        self._log_prob = lambda logits, a: log_prob(logits, a).astype(np.float32, copy=False)

    @staticmethod
    def _head(h: np.ndarray, layers: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        for w, b in layers[:-1]:
            h = np.tanh(h @ w + b)
        w, b = layers[-1]
        return h @ w + b

    def forward(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        h = 2.0 * obs - 1.0
        for w, b in self.trunk:
            h = np.tanh(h @ w + b)
        logits = self._head(h, self.pi)
        value = self._head(h, self.v)[:, 0]
        return logits, _sigmoid(logits), value.astype(np.float32, copy=False)


def numpy_distill(policy: ActorCritic, states: torch.Tensor, actions: torch.Tensor, *,
                  epochs: int, minibatch: int, lr: float, max_grad_norm: float,
                  generator: torch.Generator, stop_loss: float = 0.0,
                  weights: torch.Tensor | None = None) -> tuple[float, int]:
    """The native engine's behaviour cloning (ppo_native.native_distill) in
    NumPy: the same permutations, loss, clip (trunk and policy head) and a
    fresh Adam (eps 1e-5)."""
    net = Net(policy)
    k = net.size("trunk", "pi")  # the trunk then the policy head lead the flat vectors
    params, grad = net.flat[:k], net.grad[:k]
    m, v = np.zeros_like(params), np.zeros_like(params)
    adam = AdamSettings(lr=lr, eps=1e-5)
    x_all = states.detach().numpy().astype(np.float32, copy=False)
    y_all = actions.detach().numpy().astype(np.float32, copy=False)
    w_all = None if weights is None else weights.detach().numpy().astype(np.float32)
    n, t, loss, ran = len(x_all), 0, float("nan"), 0
    while ran < epochs:
        order = torch.randperm(n, generator=generator).numpy()
        total = 0.0
        for start in range(0, n, minibatch):
            idx = order[start:start + minibatch]
            logits, _, cache = net.forward(x_all[idx], value=False)
            y = y_all[idx]
            # BCE with logits: softplus(l) - y l; its slope sigmoid(l) - y
            bce = np.logaddexp(0.0, logits) - y * logits
            if w_all is None:
                loss = float(np.mean(bce))
                d_logits = ((_sigmoid(logits) - y) / logits.size).astype(np.float32)
            else:  # the weighted mean over rows of the mean over valves
                w = w_all[idx, None] / (w_all[idx].sum() * logits.shape[1])
                loss = float(np.sum(w * bce))
                d_logits = (w * (_sigmoid(logits) - y)).astype(np.float32)
            total += loss
            net.backward(cache, d_logits, None)
            _clip(net, k, max_grad_norm)
            t += 1
            adam_step(params, grad, m, v, t, adam)
        ran += 1
        if total / -(-n // minibatch) < stop_loss:
            break
    net.store()
    return loss, ran
