"""The fast PPO engine (``--ppo-engine native``): acting, the update and
behaviour cloning of :class:`~ftc.learning.ppo.PPO` computed by the C++
kernels of ``ftc._learn`` (cpp/learning) on the torch policy's weights.

Why: the actor-critic is tiny (6 -> 64 -> 64 -> two heads of 16 -> 16), and a
minibatch is 16 (online) or 64 (offline) samples, so a torch gradient step
costs dispatch and autograd bookkeeping, not arithmetic (``scripts/bench.py``:
``offline_native_over_torch``, ``act_torch_over_native``).

What is the same as the torch engine (:mod:`ftc.learning.ppo`, the
reference): the minibatch order and the valve samples (drawn from the PPO's
torch generator, so its stream is unchanged), the loss (clipped surrogate,
entropy bonus, value loss), the global gradient-norm clip and Adam with
torch's formulae, whose moments live in the torch optimiser's state between
updates (so checkpoints, resume, the offline worker processes and a later
torch-engine phase see one optimiser). What differs: float32 rounding.
tests/python/oracles/ppo_numpy.py is the same arithmetic in NumPy, derived
by hand; the tests hold the C++ to it and it to torch.

Value clipping (``clip_vloss``) is not in the kernels: :class:`NativeEngine`
refuses it (:meth:`~ftc.learning.ppo_policy.PPOConfig.validate`).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch
from torch import nn

from ftc.learning.buffer import RolloutBatch
from ftc.learning.ppo_policy import ActorCritic, PPOConfig, UpdateStats, explained_variance


def _linears(module: nn.Module) -> list[nn.Linear]:
    return [m for m in module.modules() if isinstance(m, nn.Linear)]


class FlatParams:
    """Float32 copies of the actor-critic's parameters in one flat vector,
    :attr:`flat`, in parameter order (trunk, policy head, value head), each
    weight as (in, out) row-major then its bias: the layout of the C++
    kernels. :meth:`store` writes them back into the torch modules."""

    PARTS = ("trunk", "pi", "v")

    def __init__(self, policy: ActorCritic) -> None:
        self.modules = {"trunk": _linears(policy.trunk), "pi": _linears(policy.policy_head),
                        "v": _linears(policy.value_head)}
        self.torch_params = [p for part in self.modules.values()
                             for layer in part for p in (layer.weight, layer.bias)]
        if len(self.torch_params) != len(list(policy.parameters())):
            raise ValueError("the native PPO engine supports Linear + tanh actor-critics only")
        shapes = [p.shape[::-1] if p.dim() == 2 else p.shape for p in self.torch_params]
        sizes = [math.prod(shape) for shape in shapes]
        #: [start, end) of each parameter in the flat vectors, in parameter order
        self.bounds = [(sum(sizes[:i]), sum(sizes[:i + 1])) for i in range(len(sizes))]
        self.flat = np.empty(sum(sizes), np.float32)
        self.params = [self.flat[a:b].reshape(shape) for (a, b), shape in zip(self.bounds, shapes)]
        for view, p in zip(self.params, self.torch_params):
            view[...] = p.detach().numpy().T if p.dim() == 2 else p.detach().numpy()
        self.layers, i = {}, 0
        for name, part in self.modules.items():
            self.layers[name] = [[self.params[i + 2 * k], self.params[i + 2 * k + 1]]
                                 for k in range(len(part))]
            i += 2 * len(part)

    def size(self, *parts: str) -> int:
        """Length of the leading stretch of :attr:`flat` that holds ``parts``
        (a prefix of trunk, pi, v)."""
        if parts != self.PARTS[:len(parts)]:
            raise ValueError(f"parts must be a prefix of {self.PARTS}, not {parts}")
        n = sum(2 * len(self.modules[name]) for name in parts)
        return self.bounds[n - 1][1]

    def widths(self) -> dict[str, list[int]]:
        """Each part's input width, then its layers' output widths."""
        return {name: [layers[0][0].shape[0]] + [w.shape[1] for w, _ in layers]
                for name, layers in self.layers.items()}

    def store(self) -> None:
        """Write the weights back into the torch modules."""
        for name, part in self.modules.items():
            for layer, (w, b) in zip(part, self.layers[name]):
                layer.weight.data.copy_(torch.from_numpy(np.ascontiguousarray(w.T)))
                layer.bias.data.copy_(torch.from_numpy(b))


class AdamMoments:
    """The torch Adam's hyperparameters, moments and step count as flat vectors
    laid out as :attr:`FlatParams.flat`: read from the torch optimiser's state,
    stepped by the kernels, written back by :meth:`store`."""

    def __init__(self, optimizer: torch.optim.Optimizer, net: FlatParams) -> None:
        if len(optimizer.param_groups) != 1:
            raise ValueError("the native PPO engine expects one parameter group")
        group = optimizer.param_groups[0]
        if group.get("amsgrad") or group.get("weight_decay") or group.get("maximize"):
            raise ValueError("the native PPO engine supports plain Adam only")
        self.optimizer, self.net = optimizer, net
        self.lr, (self.beta1, self.beta2), self.eps = group["lr"], group["betas"], group["eps"]
        self.m, self.v, self.t = np.zeros_like(net.flat), np.zeros_like(net.flat), 0
        for p, (a, b) in zip(net.torch_params, net.bounds):
            state = optimizer.state.get(p, {})
            if state:
                self.m[a:b] = (state["exp_avg"].numpy().T if p.dim() == 2
                               else state["exp_avg"].numpy()).ravel()
                self.v[a:b] = (state["exp_avg_sq"].numpy().T if p.dim() == 2
                               else state["exp_avg_sq"].numpy()).ravel()
                self.t = int(state["step"])

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


#: one epoch of gradient steps: (net, opt, config, minibatch, order, obs, actions,
#: old_logprobs, advantages, returns) -> (approx_kl and clipfrac per minibatch,
#: the last policy and value losses, Adam's step count)
EpochFn = Callable[..., tuple[np.ndarray, np.ndarray, float, float, int]]


def native_epoch(net: FlatParams, opt: AdamMoments, config: PPOConfig, minibatch: int,
                 order: np.ndarray, obs: np.ndarray, actions: np.ndarray,
                 old_logprobs: np.ndarray, advantages: np.ndarray, returns: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, float, float, int]:
    """One epoch of PPO's gradient steps in C++ (``ftc._learn.ppo_epoch``)."""
    from ftc import _learn  # native: built beside ftc._core

    w = net.widths()
    return _learn.ppo_epoch(
        net.flat, opt.m, opt.v, opt.t, w["trunk"], w["pi"], w["v"], obs, actions,
        old_logprobs, advantages, returns, np.ascontiguousarray(order, dtype=np.int64),
        minibatch=minibatch, clip_coef=config.clip_coef, ent_coef=config.ent_coef,
        vf_coef=config.vf_coef, max_grad_norm=config.max_grad_norm, norm_adv=config.norm_adv,
        lr=opt.lr, beta1=opt.beta1, beta2=opt.beta2, eps=opt.eps)


def flat_ppo_update(policy: ActorCritic, optimizer: torch.optim.Optimizer, batch: RolloutBatch,
                    config: PPOConfig, generator: torch.Generator | None,
                    epoch: EpochFn = native_epoch, net_type: type[FlatParams] = FlatParams
                    ) -> UpdateStats:
    """:func:`ftc.learning.ppo.ppo_update` on flat float32 parameters, each
    epoch's gradient steps by ``epoch`` (the C++ kernel; the NumPy oracle of
    the tests passes its own): the same minibatches, early stop and stats."""
    if config.clip_vloss:
        raise ValueError("the native PPO engine has no value clipping (clip_vloss): "
                         "use the torch engine")
    net = net_type(policy)
    opt = AdamMoments(optimizer, net)
    obs, actions, old_logprobs, _values, advantages, returns = (
        np.ascontiguousarray(t.detach().numpy(), dtype=np.float32) for t in batch)
    B = obs.shape[0]
    mb = min(config.minibatch_size, B)
    kls: list[float] = []
    clipfracs: list[float] = []
    steps, pg_loss, v_loss = 0, 0.0, 0.0
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
    with torch.no_grad():  # the statistics as the torch update computes them
        logits, _ = policy(batch.obs)
        _, entropy_all = policy.log_prob_entropy(logits, batch.actions)
    return UpdateStats(policy_loss=float(pg_loss), value_loss=float(v_loss),
                       entropy=float(entropy_all.mean()), approx_kl=float(np.mean(kls)),
                       clipfrac=float(np.mean(clipfracs)),
                       explained_variance=explained_variance(batch.values, batch.returns),
                       open_fraction=float(torch.sigmoid(logits).mean()),
                       gradient_steps=steps)


class NativeActor:
    """The actor-critic's forward pass for acting in C++ (``ftc._learn.Actor``),
    reading the torch parameters in place (so it always sees the current
    weights: updates, ``load_state_dict`` and optimiser steps all write in
    place). Sampling draws from the PPO's torch generator with
    ``torch.bernoulli``, as :meth:`ActorCritic.act` does; the probabilities,
    log-probabilities and values are float32 results whose rounding differs
    from torch's (~1e-7)."""

    def __init__(self, policy: ActorCritic) -> None:
        from ftc import _learn  # native: built beside ftc._core

        parts = [_linears(m) for m in (policy.trunk, policy.policy_head, policy.value_head)]
        self._params = [p for part in parts for m in part for p in (m.weight, m.bias)]
        self._pointers = self._addresses()
        widths = [[part[0].in_features] + [m.out_features for m in part] for part in parts]
        self.kernel = _learn.Actor(*widths, [p.detach().numpy() for p in self._params])
        self._log_prob = _learn.log_prob

    def _addresses(self) -> list[int]:
        return [p.data_ptr() for p in self._params]

    def stale(self) -> bool:
        """Whether a parameter's memory moved since this actor was built (torch
        moves a tensor's storage into shared memory when it is pickled for
        another process, ``share_memory_``; ``.data =`` replaces it): its views
        would read freed memory. 1.3 us per call for the 16 tensors."""
        return self._addresses() != self._pointers

    def forward(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """logits (N, 6), their sigmoids, values (N,) of obs (N, 6): float32."""
        return self.kernel.forward(obs)

    def act(self, obs: torch.Tensor, generator: torch.Generator | None,
            deterministic: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """As :meth:`ActorCritic.act`: actions (N, 6), log-probs (N,), values (N,),
        in the fewest calls (acting is once per plant step)."""
        logits, probs, value = self.forward(np.ascontiguousarray(obs.numpy(), dtype=np.float32))
        if deterministic:
            actions = (logits > 0).astype(np.float32)
        else:
            actions = torch.bernoulli(torch.from_numpy(probs), generator=generator).numpy()
        return (torch.from_numpy(actions), torch.from_numpy(self._log_prob(logits, actions)),
                torch.from_numpy(value))


def native_distill(policy: ActorCritic, states: torch.Tensor, actions: torch.Tensor, *,
                   epochs: int, minibatch: int, lr: float, max_grad_norm: float,
                   generator: torch.Generator, stop_loss: float = 0.0,
                   weights: torch.Tensor | None = None) -> tuple[float, int]:
    """Behaviour cloning in C++ (``ftc._learn.distill``, cpp/learning/tanh_mlp.cpp):
    binary cross-entropy of the policy's logits against ``actions`` (the
    weighted mean over rows of the mean over valves), the global norm clip over
    the trunk and policy head (the value head gets no gradient, as in torch),
    a fresh Adam (eps 1e-5), one permutation per epoch from ``generator``
    (drawn up front: the generator is the fit's own); it stops early after an
    epoch whose mean minibatch loss is below ``stop_loss``. Returns the last
    minibatch's loss and the epochs run."""
    from ftc import _learn  # native: built beside ftc._core

    if epochs <= 0:  # nothing to fit
        return float("nan"), 0
    net = FlatParams(policy)
    k = net.size("trunk", "pi")  # the trunk then the policy head lead the flat vector
    widths = net.widths()
    as32 = lambda t: np.ascontiguousarray(t.detach().numpy(), dtype=np.float32)  # noqa: E731
    n = len(states)
    orders = np.stack([torch.randperm(n, generator=generator).numpy() for _ in range(epochs)])
    loss, ran, _steps = _learn.distill(net.flat[:k], widths["trunk"], widths["pi"], as32(states),
                                       as32(actions), None if weights is None else as32(weights),
                                       orders, minibatch, lr, max_grad_norm, stop_loss)
    net.store()
    return loss, ran


class NativeEngine:
    """:class:`~ftc.learning.ppo_policy.PPOEngine` on the C++ kernels. Keeps
    no state of its own but the actor over the current policy's memory."""

    name = "native"

    def __init__(self) -> None:
        self._actor: NativeActor | None = None
        self._actor_of: ActorCritic | None = None

    def act(self, policy: ActorCritic, obs: torch.Tensor, generator: torch.Generator | None,
            deterministic: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        if obs.requires_grad:  # a caller differentiating through acting: torch's
            return policy.act(obs, generator, deterministic)
        if self._actor is None or self._actor_of is not policy or self._actor.stale():
            self._actor, self._actor_of = NativeActor(policy), policy
        return self._actor.act(obs, generator, deterministic)

    def update(self, policy: ActorCritic, optimizer: torch.optim.Optimizer, batch: RolloutBatch,
               config: PPOConfig, generator: torch.Generator | None) -> UpdateStats:
        return flat_ppo_update(policy, optimizer, batch, config, generator)

    def distill(self, policy: ActorCritic, states: torch.Tensor, actions: torch.Tensor, *,
                epochs: int, minibatch: int, lr: float, max_grad_norm: float,
                generator: torch.Generator, stop_loss: float = 0.0,
                weights: torch.Tensor | None = None) -> tuple[float, int]:
        return native_distill(policy, states, actions, epochs=epochs, minibatch=minibatch, lr=lr,
                              max_grad_norm=max_grad_norm, generator=generator,
                              stop_loss=stop_loss, weights=weights)
