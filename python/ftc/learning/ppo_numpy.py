"""The PPO update of :func:`ftc.learning.ppo.ppo_update`, computed in NumPy.

Why: the actor-critic is tiny (6 -> 64 -> 64 -> two heads of 16 -> 16), and a
minibatch is 16 (online) or 64 (offline) samples, so a torch gradient step
costs dispatch and autograd bookkeeping, not arithmetic. The same step as
NumPy calls on float32 arrays is several times faster (``scripts/bench.py``:
``ppo_update_speedup``).

What is the same: the minibatch order (drawn from the PPO's torch generator,
so the generator's stream is unchanged), the loss (clipped surrogate, entropy
bonus, value loss), the global gradient-norm clip and Adam with torch's
formulae, whose moments live in the torch optimiser's state between updates
(so checkpoints, resume, the offline worker processes and torch-trained
phases such as behaviour cloning see one optimiser). What differs: float32
rounding (products sum in another order). Gradients are derived by hand
below; ``tests/python/test_ppo_numpy.py`` checks them against autograd.

Value clipping (``clip_vloss``) is not implemented here: :class:`~ftc.learning.ppo.PPO`
uses the torch update for it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

if TYPE_CHECKING:  # ppo.py imports this module; these are for annotations only
    from ftc.learning.ppo import ActorCritic, PPOConfig, UpdateStats


class _Net:
    """Float32 NumPy views of the actor-critic's layers, in parameter order.

    Each part is a list of (W (in, out), b (out,)); every layer but the last
    of each head is followed by tanh, as is every trunk layer.
    """

    def __init__(self, policy: ActorCritic) -> None:
        def linears(module: nn.Module) -> list[nn.Linear]:
            return [m for m in module.modules() if isinstance(m, nn.Linear)]

        self.modules = {"trunk": linears(policy.trunk), "pi": linears(policy.policy_head),
                        "v": linears(policy.value_head)}
        self.torch_params = [p for part in self.modules.values()
                             for layer in part for p in (layer.weight, layer.bias)]
        if len(self.torch_params) != len(list(policy.parameters())):
            raise ValueError("the NumPy PPO update supports Linear + tanh actor-critics only")
        self.layers = {name: [[layer.weight.detach().numpy().T.copy(),
                               layer.bias.detach().numpy().copy()] for layer in part]
                       for name, part in self.modules.items()}
        self.params = [p for part in self.layers.values() for layer in part for p in layer]

    def store(self) -> None:
        """Write the weights back into the torch modules."""
        for name, part in self.modules.items():
            for layer, (w, b) in zip(part, self.layers[name]):
                layer.weight.data.copy_(torch.from_numpy(np.ascontiguousarray(w.T)))
                layer.bias.data.copy_(torch.from_numpy(b))

    def forward(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
        """logits (B, 6), value (B,), and the activations the backward pass needs."""
        h = [2.0 * obs - 1.0]
        for w, b in self.layers["trunk"]:
            h.append(np.tanh(h[-1] @ w + b))
        cache = {"trunk": h}
        outs = []
        for name in ("pi", "v"):
            a = [h[-1]]
            layers = self.layers[name]
            for i, (w, b) in enumerate(layers):
                z = a[-1] @ w + b
                a.append(np.tanh(z) if i < len(layers) - 1 else z)
            cache[name] = a
            outs.append(a[-1])
        return outs[0], outs[1][:, 0], cache

    def backward(self, cache: dict, d_logits: np.ndarray, d_value: np.ndarray
                 ) -> list[np.ndarray]:
        """Gradients of the loss, in :attr:`params` order, from its gradients
        with respect to the logits (B, 6) and the value (B,)."""
        grads: dict[str, list[list[np.ndarray]]] = {}
        d_trunk_out = 0.0
        for name, d_out in (("pi", d_logits), ("v", d_value[:, None])):
            grads[name], d_in = _backward_mlp(self.layers[name], cache[name], d_out)
            d_trunk_out = d_trunk_out + d_in
        grads["trunk"], _ = _backward_mlp(self.layers["trunk"], cache["trunk"],
                                          d_trunk_out, tanh_last=True)
        return [g for name in ("trunk", "pi", "v") for layer in grads[name] for g in layer]


def _backward_mlp(layers: list[list[np.ndarray]], acts: list[np.ndarray], d_out: np.ndarray,
                  tanh_last: bool = False) -> tuple[list[list[np.ndarray]], np.ndarray]:
    """Backprop through x -> tanh(x W1 + b1) -> ... -> x Wn + bn (tanh too if
    ``tanh_last``); ``acts`` = [input, output of each layer]. Returns the
    [dW, db] of each layer and the gradient with respect to the input."""
    grads: list[list[np.ndarray]] = [[] for _ in layers]
    d = d_out
    for i in range(len(layers) - 1, -1, -1):
        if i < len(layers) - 1 or tanh_last:
            d = d * (1.0 - acts[i + 1] * acts[i + 1])
        grads[i] = [acts[i].T @ d, d.sum(axis=0)]
        d = d @ layers[i][0].T
    return grads, d


def _logsigmoid(x: np.ndarray) -> np.ndarray:
    return -np.logaddexp(0.0, -x)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return np.exp(_logsigmoid(x))


def log_prob_entropy(logits: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """As :meth:`ActorCritic.log_prob_entropy`: (B,) each, summed over valves."""
    log_p = actions * _logsigmoid(logits) + (1.0 - actions) * _logsigmoid(-logits)
    entropy = np.logaddexp(0.0, logits) - _sigmoid(logits) * logits
    return log_p.sum(-1), entropy.sum(-1)


class _Adam:
    """torch.optim.Adam's step on NumPy arrays, its moments read from and
    written back to the torch optimiser's state."""

    def __init__(self, optimizer: torch.optim.Optimizer, net: _Net) -> None:
        if len(optimizer.param_groups) != 1:
            raise ValueError("the NumPy PPO update expects one parameter group")
        group = optimizer.param_groups[0]
        if group.get("amsgrad") or group.get("weight_decay") or group.get("maximize"):
            raise ValueError("the NumPy PPO update supports plain Adam only")
        self.optimizer, self.net = optimizer, net
        self.lr, (self.beta1, self.beta2), self.eps = group["lr"], group["betas"], group["eps"]
        self.m, self.v, self.t = [], [], 0
        for p in net.torch_params:
            state = optimizer.state.get(p, {})
            if state:
                self.m.append(state["exp_avg"].numpy().T.copy() if p.dim() == 2
                              else state["exp_avg"].numpy().copy())
                self.v.append(state["exp_avg_sq"].numpy().T.copy() if p.dim() == 2
                              else state["exp_avg_sq"].numpy().copy())
                self.t = int(state["step"])
            else:
                self.m.append(np.zeros(p.shape[::-1] if p.dim() == 2 else p.shape, np.float32))
                self.v.append(np.zeros_like(self.m[-1]))

    def step(self, grads: list[np.ndarray]) -> None:
        self.t += 1
        step_size = self.lr / (1.0 - self.beta1 ** self.t)
        root_correction = math.sqrt(1.0 - self.beta2 ** self.t)
        for p, g, m, v in zip(self.net.params, grads, self.m, self.v):
            m *= self.beta1
            m += (1.0 - self.beta1) * g
            v *= self.beta2
            v += (1.0 - self.beta2) * (g * g)
            p -= step_size * (m / (np.sqrt(v) / root_correction + self.eps))

    def store(self) -> None:
        """Write the moments and step count back into the torch optimiser."""
        if self.t == 0:
            return
        for p, m, v in zip(self.net.torch_params, self.m, self.v):
            def back(a: np.ndarray) -> torch.Tensor:
                return torch.from_numpy(np.ascontiguousarray(a.T if p.dim() == 2 else a))
            self.optimizer.state[p] = {"step": torch.tensor(float(self.t)),
                                       "exp_avg": back(m), "exp_avg_sq": back(v)}


def numpy_ppo_update(policy: ActorCritic, optimizer: torch.optim.Optimizer, batch,
                     config: PPOConfig, generator: torch.Generator | None,
                     stats_type: type[UpdateStats]) -> UpdateStats:
    """:func:`ftc.learning.ppo.ppo_update` in NumPy (same arguments, same stats)."""
    net, opt = _Net(policy), None
    opt = _Adam(optimizer, net)
    obs, actions, old_logprobs, values, advantages, returns = (
        t.detach().numpy().astype(np.float32, copy=False) for t in batch)
    B = obs.shape[0]
    mb = min(config.minibatch_size, B)
    kls, clipfracs, steps = [], [], 0
    pg_loss = v_loss = 0.0
    for _epoch in range(config.update_epochs):
        order = torch.randperm(B, generator=generator).numpy()
        for start in range(0, B, mb):
            idx = order[start:start + mb]
            n = len(idx)
            logits, value, cache = net.forward(obs[idx])
            a = actions[idx]
            logprob, entropy = log_prob_entropy(logits, a)
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
            grads = net.backward(cache, d_logits.astype(np.float32),
                                 d_value.astype(np.float32))
            norm = math.sqrt(sum(float(np.sum(g * g)) for g in grads))
            scale = config.max_grad_norm / (norm + 1e-6)
            if scale < 1.0:
                grads = [g * np.float32(scale) for g in grads]
            opt.step(grads)
            steps += 1
        if config.target_kl is not None and np.mean(kls[-math.ceil(B / mb):]) > config.target_kl:
            break
    net.store()
    opt.store()

    logits, _, _ = net.forward(obs)
    _, entropy_all = log_prob_entropy(logits, actions)
    ev_var = float(np.var(returns))
    explained = float("nan") if ev_var == 0 else float(1.0 - np.var(returns - values) / ev_var)
    return stats_type(policy_loss=pg_loss, value_loss=v_loss,
                      entropy=float(entropy_all.mean()), approx_kl=float(np.mean(kls)),
                      clipfrac=float(np.mean(clipfracs)), explained_variance=explained,
                      open_fraction=float(_sigmoid(logits).mean()), gradient_steps=steps)


class NumpyActor:
    """The actor-critic's forward pass for acting, on NumPy views that share
    memory with the torch parameters (so it always sees the current weights:
    updates, ``load_state_dict`` and optimiser steps all write in place).

    Sampling draws from the PPO's torch generator with ``torch.bernoulli``, as
    :meth:`ActorCritic.act` does, so the generator's stream is unchanged; the
    probabilities, log-probabilities and values are float32 NumPy results
    (rounding differs from torch's, ~1e-7).
    """

    def __init__(self, policy: ActorCritic) -> None:
        def views(module: nn.Module) -> list[tuple[np.ndarray, np.ndarray]]:
            return [(m.weight.detach().numpy(), m.bias.detach().numpy())
                    for m in module.modules() if isinstance(m, nn.Linear)]

        self.trunk, self.pi, self.v = (views(policy.trunk), views(policy.policy_head),
                                       views(policy.value_head))

    @staticmethod
    def _mlp(x: np.ndarray, layers: list[tuple[np.ndarray, np.ndarray]],
             tanh_last: bool) -> np.ndarray:
        for i, (w, b) in enumerate(layers):
            x = x @ w.T + b
            if tanh_last or i < len(layers) - 1:
                x = np.tanh(x)
        return x

    def act(self, obs: torch.Tensor, generator: torch.Generator | None,
            deterministic: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """As :meth:`ActorCritic.act`: actions (N, 6), log-probs (N,), values (N,)."""
        x = obs.numpy().astype(np.float32, copy=False)
        h = self._mlp(2.0 * x - 1.0, self.trunk, tanh_last=True)
        logits = self._mlp(h, self.pi, tanh_last=False)
        value = self._mlp(h, self.v, tanh_last=False)[:, 0]
        if deterministic:
            actions = (logits > 0).astype(np.float32)
        else:
            probs = torch.from_numpy(_sigmoid(logits))
            actions = torch.bernoulli(probs, generator=generator).numpy()
        logprob, _ = log_prob_entropy(logits, actions)
        return (torch.from_numpy(actions), torch.from_numpy(logprob.astype(np.float32)),
                torch.from_numpy(value.astype(np.float32)))


def numpy_distill(policy: ActorCritic, states: torch.Tensor, actions: torch.Tensor, *,
                  epochs: int, minibatch: int, lr: float, max_grad_norm: float,
                  generator: torch.Generator, stop_loss: float = 0.0,
                  weights: torch.Tensor | None = None) -> tuple[float, int]:
    """:func:`ftc.learning.distill.distill`'s fit in NumPy: binary cross-entropy
    of the policy's logits against ``actions`` (mean over samples and valves),
    the global norm clip over the trunk and policy head (the value head gets no
    gradient, as in torch, where its parameters have none), a fresh Adam
    (eps 1e-5); it stops early after an epoch whose mean minibatch loss is below
    ``stop_loss``; ``weights`` (N,) weight the rows' losses as distill's do.
    Returns the last minibatch's loss and the epochs run."""
    net = _Net(policy)
    n_trunk, n_pi = 2 * len(net.layers["trunk"]), 2 * len(net.layers["pi"])
    params = net.params[:n_trunk + n_pi]  # trunk then policy head, as backward orders them
    m = [np.zeros_like(p) for p in params]
    v = [np.zeros_like(p) for p in params]
    x_all = states.detach().numpy().astype(np.float32, copy=False)
    y_all = actions.detach().numpy().astype(np.float32, copy=False)
    w_all = None if weights is None else weights.detach().numpy().astype(np.float32)
    n, t, loss, ran = len(x_all), 0, float("nan"), 0
    while ran < epochs:
        order = torch.randperm(n, generator=generator).numpy()
        total = 0.0
        for start in range(0, n, minibatch):
            idx = order[start:start + minibatch]
            logits, value, cache = net.forward(x_all[idx])
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
            grads = net.backward(cache, d_logits, np.zeros_like(value))[:n_trunk + n_pi]
            norm = math.sqrt(sum(float(np.sum(g * g)) for g in grads))
            scale = max_grad_norm / (norm + 1e-6)
            if scale < 1.0:
                grads = [g * np.float32(scale) for g in grads]
            t += 1
            step_size = lr / (1.0 - 0.9 ** t)
            root_correction = math.sqrt(1.0 - 0.999 ** t)
            for p, g, mi, vi in zip(params, grads, m, v):
                mi *= 0.9
                mi += 0.1 * g
                vi *= 0.999
                vi += 0.001 * (g * g)
                p -= step_size * (mi / (np.sqrt(vi) / root_correction + 1e-5))
        ran += 1
        if total / -(-n // minibatch) < stop_loss:
            break
    net.store()
    return loss, ran
