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

Where the NumPy calls themselves are the cost, the inner loops run in C++
(``ftc._learn``, cpp/learning): each epoch's gradient steps (``ppo_epoch``),
acting (``Actor``) and behaviour cloning (``distill``), with the same
minibatches, formulae and sampling; the NumPy versions here stay as the
reference the C++ is tested against (tests/python/test_native_ppo.py,
test_native_distill.py). An offline phase's 2,048 model steps run 7x faster
than the torch engine's (``scripts/bench.py``: ``offline_numpy_over_torch``).

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
    from ftc.learning.ppo_policy import ActorCritic, PPOConfig, UpdateStats


class _Net:
    """Float32 NumPy copies of the actor-critic's layers, in parameter order.

    Each part is a list of (W (in, out), b (out,)); every layer but the last
    of each head is followed by tanh, as is every trunk layer. The weights are
    views into one flat vector, :attr:`flat`, and :meth:`backward` writes the
    gradients into views of another, :attr:`grad`, so an optimiser step and the
    gradient-norm clip are a few NumPy calls on whole vectors instead of a few
    per layer: elementwise, so the arithmetic is the same (scripts/bench.py).
    """

    PARTS = ("trunk", "pi", "v")

    def __init__(self, policy: ActorCritic) -> None:
        def linears(module: nn.Module) -> list[nn.Linear]:
            return [m for m in module.modules() if isinstance(m, nn.Linear)]

        self.modules = {"trunk": linears(policy.trunk), "pi": linears(policy.policy_head),
                        "v": linears(policy.value_head)}
        self.torch_params = [p for part in self.modules.values()
                             for layer in part for p in (layer.weight, layer.bias)]
        if len(self.torch_params) != len(list(policy.parameters())):
            raise ValueError("the NumPy PPO update supports Linear + tanh actor-critics only")
        shapes = [p.shape[::-1] if p.dim() == 2 else p.shape for p in self.torch_params]
        sizes = [math.prod(shape) for shape in shapes]
        #: [start, end) of each parameter in the flat vectors, in parameter order
        self.bounds = [(sum(sizes[:i]), sum(sizes[:i + 1])) for i in range(len(sizes))]
        self.flat = np.empty(sum(sizes), np.float32)
        self.grad = np.zeros_like(self.flat)
        self.params = [self.flat[a:b].reshape(shape) for (a, b), shape in zip(self.bounds, shapes)]
        self.grads = [self.grad[a:b].reshape(shape) for (a, b), shape in zip(self.bounds, shapes)]
        for view, p in zip(self.params, self.torch_params):
            view[...] = p.detach().numpy().T if p.dim() == 2 else p.detach().numpy()
        self.layers, self.layer_grads, i = {}, {}, 0
        for name, part in self.modules.items():
            self.layers[name] = [[self.params[i + 2 * k], self.params[i + 2 * k + 1]]
                                 for k in range(len(part))]
            self.layer_grads[name] = [[self.grads[i + 2 * k], self.grads[i + 2 * k + 1]]
                                      for k in range(len(part))]
            i += 2 * len(part)

    def size(self, *parts: str) -> int:
        """Length of the leading stretch of :attr:`flat` that holds ``parts``
        (a prefix of trunk, pi, v)."""
        if parts != self.PARTS[:len(parts)]:
            raise ValueError(f"parts must be a prefix of {self.PARTS}, not {parts}")
        n = sum(2 * len(self.modules[name]) for name in parts)
        return self.bounds[n - 1][1]

    def norm(self, n: int) -> float:
        """The global L2 norm of the first ``n`` entries of :attr:`grad` (whole
        parameters), summed per parameter in float32 as the per-layer arrays were."""
        sq = self.grad[:n] * self.grad[:n]
        total, add = 0.0, np.add.reduce  # np.sum's own reduction, without its wrapper
        for a, b in self.bounds:
            if b > n:
                break
            total += float(add(sq[a:b]))
        return math.sqrt(total)

    def store(self) -> None:
        """Write the weights back into the torch modules."""
        for name, part in self.modules.items():
            for layer, (w, b) in zip(part, self.layers[name]):
                layer.weight.data.copy_(torch.from_numpy(np.ascontiguousarray(w.T)))
                layer.bias.data.copy_(torch.from_numpy(b))

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
        as they were, and the trunk's are the policy head's alone, as they would
        be with a zero ``d_value``)."""
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
        np.add.reduce(d, axis=0, out=grads[i][1])  # np.sum's reduction, without its wrapper
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


def log_prob_entropy(logits: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """As :meth:`ActorCritic.log_prob_entropy`: (B,) each, summed over valves."""
    entropy = np.logaddexp(0.0, logits) - _sigmoid(logits) * logits
    return log_prob(logits, actions), entropy.sum(-1)


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
        # the moments as flat vectors laid out as net.flat, so a step is whole-vector calls
        self.m, self.v, self.t = np.zeros_like(net.flat), np.zeros_like(net.flat), 0
        for p, (a, b) in zip(net.torch_params, net.bounds):
            state = optimizer.state.get(p, {})
            if state:
                self.m[a:b] = (state["exp_avg"].numpy().T if p.dim() == 2
                               else state["exp_avg"].numpy()).ravel()
                self.v[a:b] = (state["exp_avg_sq"].numpy().T if p.dim() == 2
                               else state["exp_avg_sq"].numpy()).ravel()
                self.t = int(state["step"])

    def step(self, grad: np.ndarray) -> None:
        """One Adam step of every parameter from the flat gradient ``grad``."""
        self.t += 1
        step_size = self.lr / (1.0 - self.beta1 ** self.t)
        root_correction = math.sqrt(1.0 - self.beta2 ** self.t)
        m, v = self.m, self.v
        m *= self.beta1
        m += (1.0 - self.beta1) * grad
        v *= self.beta2
        v += (1.0 - self.beta2) * (grad * grad)
        self.net.flat -= step_size * (m / (np.sqrt(v) / root_correction + self.eps))

    def store(self) -> None:
        """Write the moments and step count back into the torch optimiser."""
        if self.t == 0:
            return
        for p, (a, b) in zip(self.net.torch_params, self.net.bounds):
            def back(flat: np.ndarray) -> torch.Tensor:
                x = flat[a:b].reshape(p.shape[::-1] if p.dim() == 2 else p.shape)
                return torch.from_numpy(np.ascontiguousarray(x.T if p.dim() == 2 else x))
            self.optimizer.state[p] = {"step": torch.tensor(float(self.t)),
                                       "exp_avg": back(self.m), "exp_avg_sq": back(self.v)}


def _widths(net: _Net) -> dict[str, list[int]]:
    """Each part's input width, then its layers' output widths."""
    return {name: [layers[0][0].shape[0]] + [w.shape[1] for w, _ in layers]
            for name, layers in net.layers.items()}


def _native_epoch(net: _Net, opt: _Adam, config: PPOConfig, minibatch: int, order: np.ndarray,
                  obs: np.ndarray, actions: np.ndarray, old_logprobs: np.ndarray,
                  advantages: np.ndarray, returns: np.ndarray):
    """One epoch of numpy_ppo_update's gradient steps in C++: (approx_kl and
    clipfrac per minibatch, the last policy and value losses, Adam's step count)."""
    from ftc import _learn  # native: built beside ftc._core

    widths = _widths(net)
    return _learn.ppo_epoch(
        net.flat, opt.m, opt.v, opt.t, widths["trunk"], widths["pi"], widths["v"], obs, actions,
        old_logprobs, advantages, returns, np.ascontiguousarray(order, dtype=np.int64),
        minibatch=minibatch, clip_coef=config.clip_coef, ent_coef=config.ent_coef,
        vf_coef=config.vf_coef, max_grad_norm=config.max_grad_norm, norm_adv=config.norm_adv,
        lr=opt.lr, beta1=opt.beta1, beta2=opt.beta2, eps=opt.eps)


def _numpy_epoch(net: _Net, opt: _Adam, config: PPOConfig, minibatch: int, order: np.ndarray,
                 obs: np.ndarray, actions: np.ndarray, old_logprobs: np.ndarray,
                 advantages: np.ndarray, returns: np.ndarray):
    """:func:`_native_epoch` in NumPy: the reference."""
    kls, clipfracs = [], []
    pg_loss = v_loss = 0.0
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
        scale = config.max_grad_norm / (net.norm(len(grad)) + 1e-6)
        if scale < 1.0:
            grad *= np.float32(scale)
        opt.step(grad)
    return np.array(kls), np.array(clipfracs), pg_loss, v_loss, opt.t


def numpy_ppo_update(policy: ActorCritic, optimizer: torch.optim.Optimizer, batch,
                     config: PPOConfig, generator: torch.Generator | None,
                     stats_type: type[UpdateStats], *, native: bool = True) -> UpdateStats:
    """:func:`ftc.learning.ppo.ppo_update` in NumPy (same arguments, same stats).

    ``native``: each epoch's gradient steps run in C++ (``ftc._learn.ppo_epoch``,
    cpp/learning/ppo_update.cpp: the same minibatches, loss, clip and Adam,
    float32 rounding differs); False: in NumPy below, the reference that
    tests/python/test_native_ppo.py holds the C++ to."""
    net = _Net(policy)
    opt = _Adam(optimizer, net)
    obs, actions, old_logprobs, values, advantages, returns = (
        np.ascontiguousarray(t.detach().numpy(), dtype=np.float32) for t in batch)
    B = obs.shape[0]
    mb = min(config.minibatch_size, B)
    kls, clipfracs, steps = [], [], 0
    pg_loss = v_loss = 0.0
    epoch = _native_epoch if native else _numpy_epoch
    for _epoch in range(config.update_epochs):
        order = torch.randperm(B, generator=generator).numpy()
        kl, clipfrac, pg_loss, v_loss, opt.t = epoch(
            net, opt, config, mb, order, obs, actions, old_logprobs, advantages, returns)
        kls += kl.tolist()
        clipfracs += clipfrac.tolist()
        steps += len(kl)
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
    """The actor-critic's forward pass for acting, reading the torch parameters
    in place (so it always sees the current weights: updates,
    ``load_state_dict`` and optimiser steps all write in place).

    ``native`` (the default): the forward pass and the log-probabilities in C++
    (``ftc._learn.Actor``, cpp/learning/ppo_update.cpp), two calls per act;
    False: in NumPy on views of the weights, the reference. Sampling draws
    from the PPO's torch generator with ``torch.bernoulli``, as
    :meth:`ActorCritic.act` does, so the generator's stream is unchanged; the
    probabilities, log-probabilities and values are float32 results whose
    rounding differs from torch's (~1e-7).
    """

    def __init__(self, policy: ActorCritic, native: bool = True) -> None:
        def linears(module: nn.Module) -> list[nn.Linear]:
            return [m for m in module.modules() if isinstance(m, nn.Linear)]

        parts = [linears(m) for m in (policy.trunk, policy.policy_head, policy.value_head)]
        self._params = [p for part in parts for m in part for p in (m.weight, m.bias)]
        self._pointers = self._addresses()
        self._native = None
        if not native:  # W.T as a view (no copy): the same operands x @ W.T always saw
            self.trunk, self.pi, self.v = ([(m.weight.detach().numpy().T,
                                             m.bias.detach().numpy()) for m in part]
                                           for part in parts)
        else:
            from ftc import _learn  # native: built beside ftc._core

            widths = [[part[0].in_features] + [m.out_features for m in part] for part in parts]
            self._native = _learn.Actor(*widths, [p.detach().numpy() for p in self._params])
            self._log_prob = _learn.log_prob

    def _addresses(self) -> list[int]:
        return [p.data_ptr() for p in self._params]

    def stale(self) -> bool:
        """Whether a parameter's memory moved since this actor was built (torch
        moves a tensor's storage into shared memory when it is pickled for
        another process, ``share_memory_``; ``.data =`` replaces it): its views
        would read freed memory. 1.3 us per call for the 16 tensors."""
        return self._addresses() != self._pointers

    @staticmethod
    def _head(h: np.ndarray, layers: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        for w, b in layers[:-1]:
            h = np.tanh(h @ w + b)
        w, b = layers[-1]
        return h @ w + b

    def _forward(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """logits (N, 6), their sigmoids, values (N,): float32."""
        if self._native is not None:
            return self._native.forward(obs)
        h = 2.0 * obs - 1.0
        for w, b in self.trunk:
            h = np.tanh(h @ w + b)
        logits = self._head(h, self.pi)
        return logits, _sigmoid(logits), self._head(h, self.v)[:, 0]

    def act(self, obs: torch.Tensor, generator: torch.Generator | None,
            deterministic: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """As :meth:`ActorCritic.act`: actions (N, 6), log-probs (N,), values (N,).
        Acting is once per plant step, so this is the fewest calls that compute
        it (no entropy, no copies): ``scripts/bench.py``'s
        ``online_numpy_policy_over_echo``."""
        logits, probs, value = self._forward(
            np.ascontiguousarray(obs.numpy(), dtype=np.float32))
        if deterministic:
            actions = (logits > 0).astype(np.float32)
        else:
            actions = torch.bernoulli(torch.from_numpy(probs), generator=generator).numpy()
        if self._native is not None:
            logprob = self._log_prob(logits, actions)
        else:
            logprob = log_prob(logits, actions).astype(np.float32, copy=False)
        return (torch.from_numpy(actions), torch.from_numpy(logprob),
                torch.from_numpy(value.astype(np.float32, copy=False)))


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
    k = net.size("trunk", "pi")  # the trunk then the policy head lead the flat vectors
    params, grad = net.flat[:k], net.grad[:k]
    m, v = np.zeros_like(params), np.zeros_like(params)
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
            scale = max_grad_norm / (net.norm(k) + 1e-6)
            if scale < 1.0:
                grad *= np.float32(scale)
            t += 1
            step_size = lr / (1.0 - 0.9 ** t)
            root_correction = math.sqrt(1.0 - 0.999 ** t)
            m *= 0.9
            m += 0.1 * grad
            v *= 0.999
            v += 0.001 * (grad * grad)
            params -= step_size * (m / (np.sqrt(v) / root_correction + 1e-5))
        ran += 1
        if total / -(-n // minibatch) < stop_loss:
            break
    net.store()
    return loss, ran


def native_distill(policy: ActorCritic, states: torch.Tensor, actions: torch.Tensor, *,
                   epochs: int, minibatch: int, lr: float, max_grad_norm: float,
                   generator: torch.Generator, stop_loss: float = 0.0,
                   weights: torch.Tensor | None = None) -> tuple[float, int]:
    """:func:`numpy_distill` in C++ (``ftc._learn``,
    cpp/learning/tanh_mlp.cpp): the same minibatches (one permutation per epoch
    from ``generator``, drawn up front: the generator is the fit's own), loss,
    clip and Adam; float32 rounding differs (tests/python/test_native_distill.py).
    Returns the last minibatch's loss and the epochs run."""
    from ftc import _learn  # native: built beside ftc._core

    if epochs <= 0:  # nothing to fit (numpy_distill's answer)
        return float("nan"), 0
    net = _Net(policy)
    k = net.size("trunk", "pi")  # the trunk then the policy head lead the flat vectors
    widths = _widths(net)
    as32 = lambda t: np.ascontiguousarray(t.detach().numpy(), dtype=np.float32)  # noqa: E731
    n = len(states)
    orders = np.stack([torch.randperm(n, generator=generator).numpy() for _ in range(epochs)])
    loss, ran, _steps = _learn.distill(net.flat[:k], widths["trunk"], widths["pi"], as32(states),
                                       as32(actions), None if weights is None else as32(weights),
                                       orders, minibatch, lr, max_grad_norm, stop_loss)
    net.store()
    return loss, ran
