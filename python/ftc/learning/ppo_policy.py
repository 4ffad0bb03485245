"""What every PPO engine shares: the hyperparameters (:class:`PPOConfig`),
the actor-critic network and its Bernoulli-per-valve distribution
(:class:`ActorCritic`), an update's statistics (:class:`UpdateStats`) and the
engine interface (:class:`PPOEngine`).

A leaf of the PPO code: the torch engine (:mod:`ftc.learning.ppo`, the
reference) and the native engine (:mod:`ftc.learning.ppo_native`, C++ kernels)
both build on it, and neither imports the other's home for these.
"""

from __future__ import annotations

import math
import sys
from dataclasses import asdict, dataclass, field, fields
from functools import cache
from typing import Any, NamedTuple, Protocol

import torch
from torch import nn

from ftc.common.cli import at_least, between, positive
from ftc.learning.buffer import NUM_VALVES, OBS_DIM
from ftc.learning.torch_startup import skip_dynamo_import

skip_dynamo_import()  # 2 s of start-up: nothing here is compiled


ENGINES = ("native", "torch")
ENGINE_ALIASES = {"numpy": "native"}  # older name: the engine ran its inner loops in C++


@cache
def _warn_alias(name: str) -> None:
    print(f"warning: --ppo-engine {name} is a deprecated name of "
          f"--ppo-engine {ENGINE_ALIASES[name]}", file=sys.stderr)


@dataclass
class PPOConfig:
    """PPO hyperparameters. ``paper`` = the values the paper's authors used in the
    code behind their figures; ``measured`` = changed by a measurement of ours,
    recorded in docs/controller.md."""

    learning_rate: float = field(default=1e-3, metadata={"check": positive(1.0), "help": (
        "Adam step size. paper: 1e-2 (unstable: the deterministic policy collapsed); "
        "1e-3 measured here (single fault, online+offline, pretrained, 3-5 seeds): 1e-2 "
        "earns 2.42 per step in "
        "interval 0 and 2.03 over intervals 1-9, 1e-3 earns 2.60 and 2.28")})
    gamma: float = field(default=0.99, metadata={"check": between(0.0, 1.0), "help": "discount factor (paper)"})
    gae_lambda: float = field(default=0.95, metadata={"check": between(0.0, 1.0), "help": "GAE lambda (paper)"})
    clip_coef: float = field(default=0.2, metadata={"check": positive(10.0), "help": "surrogate clip range epsilon (paper)"})
    ent_coef: float = field(default=0.01, metadata={"check": between(0.0, 10.0), "help": "entropy bonus weight (paper)"})
    vf_coef: float = field(default=0.5, metadata={"check": between(0.0, 100.0), "help": "value-loss weight (CleanRL/SB3 default)"})
    clip_vloss: bool = field(default=False, metadata={"help": (
        "clip the value update around the old value (CleanRL option; torch engine only); "
        "off: with scaled rewards it only slows the critic")})
    max_grad_norm: float = field(default=0.5, metadata={"check": positive(1e6), "help": (
        "global gradient-norm clip (CleanRL/SB3 default)")})
    update_epochs: int = field(default=4, metadata={"check": at_least(1, 1000), "help": "passes over each rollout (paper)"})
    minibatch_size: int = field(default=16, metadata={"check": at_least(1, 1_000_000), "help": (
        "samples per gradient step (paper: 16 for the 128-step real rollouts)")})
    norm_adv: bool = field(default=True, metadata={"help": "normalise advantages per minibatch"})
    target_kl: float | None = field(default=None, metadata={"check": positive(), "help": (
        "stop the epochs of an update early once approx-KL exceeds this (None: never)")})
    reward_scale: float = field(default=0.01, metadata={"check": positive(1e6), "help": (
        "rewards are multiplied by this before GAE so critic targets are O(1) "
        "(rewards ~2.5/step, discounted returns ~100: unscaled, the value loss dominates "
        "the shared trunk)")})
    trunk_sizes: tuple[int, ...] = field(default=(64, 64), metadata={"check": at_least(1, 4096), "help": (
        "shared tanh trunk (paper)")})
    head_sizes: tuple[int, ...] = field(default=(16, 16), metadata={"check": at_least(1, 4096), "help": (
        "tanh layers of each of the policy and value heads (paper)")})
    engine: str = field(default="native", metadata={"choices": ENGINES, "help": (
        "how acting, updates and behaviour cloning are computed: native (C++ kernels, "
        "learning/ppo_native.py: 3-4x faster runs for these tiny networks; the same "
        "minibatches, loss, Adam and sampling stream; float32 rounding differs and PPO "
        "amplifies it: the benchmark suite's results are within seed noise of torch's, "
        "docs/benchmarks.md; no value clipping) or torch (autograd, the reference; "
        "tests/data/same_results pins it). numpy: a deprecated name of native")})

    def __post_init__(self) -> None:
        if self.engine in ENGINE_ALIASES:  # configs and command lines that name it so
            _warn_alias(self.engine)
            self.engine = ENGINE_ALIASES[self.engine]

    def validate(self) -> None:
        """Cross-field rules (ValueError naming the options)."""
        if self.clip_vloss and self.engine != "torch":
            raise ValueError("--ppo-clip-vloss needs --ppo-engine torch (the native engine "
                             "has no value clipping)")

    @classmethod
    def help(cls) -> dict[str, str]:
        """Field name -> help text (for --help and the docs)."""
        return {f.name: f.metadata.get("help", "") for f in fields(cls)}

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


# --------------------------------------------------------------------------
# Policy: networks and distribution
# --------------------------------------------------------------------------

def _layer(n_in: int, n_out: int, gain: float) -> nn.Linear:
    """A linear layer with orthogonal weights of the given gain and zero bias."""
    layer = nn.Linear(n_in, n_out)
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)
    return layer


def _mlp(n_in: int, sizes: tuple[int, ...]) -> tuple[nn.Sequential, int]:
    layers: list[nn.Module] = []
    for n in sizes:
        layers += [_layer(n_in, n, math.sqrt(2.0)), nn.Tanh()]
        n_in = n
    return nn.Sequential(*layers), n_in


class ActorCritic(nn.Module):
    """Shared tanh trunk, then a policy head (6 Bernoulli logits) and a value head.

    Input: tank levels (..., 6) in metres, mapped to [-1, 1] (tank heights are 1 m).
    Output of :meth:`forward`: logits (..., 6) and value (...,), in scaled-reward units.
    Output layers use the usual small orthogonal gains (0.01 policy, 1 value), so
    a fresh policy opens each valve with probability ~0.5.
    """

    def __init__(self, trunk_sizes: tuple[int, ...] = (64, 64),
                 head_sizes: tuple[int, ...] = (16, 16)) -> None:
        super().__init__()
        self.trunk, n = _mlp(OBS_DIM, tuple(trunk_sizes))
        pi_body, n_pi = _mlp(n, tuple(head_sizes))
        v_body, n_v = _mlp(n, tuple(head_sizes))
        self.policy_head = nn.Sequential(pi_body, _layer(n_pi, NUM_VALVES, 0.01))
        self.value_head = nn.Sequential(v_body, _layer(n_v, 1, 1.0))

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.trunk(2.0 * obs - 1.0)
        return self.policy_head(h), self.value_head(h).squeeze(-1)

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        """Critic value (...,) of observations (..., 6)."""
        return self.forward(obs)[1]

    @staticmethod
    def log_prob_entropy(logits: torch.Tensor,
                         actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Log-probability and entropy of valve actions (..., 6) under independent
        Bernoullis with the given logits, each summed over the valves -> (...,)."""
        # closed forms (faster than torch.distributions on single steps):
        # log p(a) = a log s(l) + (1 - a) log s(-l);  H = softplus(l) - s(l) l
        # (the order of these operations is the order autograd sums the gradients
        # of the two paths into the logits: reordering them changes the 7th digit)
        log_p = actions * nn.functional.logsigmoid(logits) \
            + (1.0 - actions) * nn.functional.logsigmoid(-logits)
        entropy = nn.functional.softplus(logits) - torch.sigmoid(logits) * logits
        return log_p.sum(-1), entropy.sum(-1)

    @staticmethod
    def log_prob(logits: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """The log-probability of :meth:`log_prob_entropy` alone (for acting, where
        the entropy is not used), computed by the same operations."""
        log_p = actions * nn.functional.logsigmoid(logits) \
            + (1.0 - actions) * nn.functional.logsigmoid(-logits)
        return log_p.sum(-1)

    def _acting_forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`forward` without nn.Module's per-call machinery (hooks, dispatch),
        for acting: the same functions on the same weights in the same order
        (F.linear, tanh), so bit-identical, in 40% of the time for one row."""
        def run(x: torch.Tensor, seq: nn.Sequential) -> torch.Tensor:
            for m in seq:
                if isinstance(m, nn.Sequential):
                    x = run(x, m)
                elif isinstance(m, nn.Linear):
                    x = nn.functional.linear(x, m.weight, m.bias)
                elif isinstance(m, nn.Tanh):
                    x = torch.tanh(x)
                else:
                    x = m(x)
            return x

        h = run(2.0 * obs - 1.0, self.trunk)
        return run(h, self.policy_head), run(h, self.value_head).squeeze(-1)

    @torch.no_grad()
    def act(self, obs: torch.Tensor, generator: torch.Generator | None = None,
            deterministic: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Sample valves for observations (N, 6).

        Returns actions (N, 6) float in {0, 1}, their log-probabilities (N,) and
        values (N,). Deterministic: valve open iff p > 0.5 (logit > 0).
        """
        logits, value = self._acting_forward(obs)
        if deterministic:
            actions = (logits > 0).to(obs.dtype)
        else:
            actions = torch.bernoulli(torch.sigmoid(logits), generator=generator)
        return actions, self.log_prob(logits, actions), value

    def evaluate_actions(self, obs: torch.Tensor, actions: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Log-prob (B,), entropy (B,) and value (B,) of actions (B, 6) at obs (B, 6)."""
        logits, value = self.forward(obs)
        logprob, entropy = self.log_prob_entropy(logits, actions)
        return logprob, entropy, value


class UpdateStats(NamedTuple):
    policy_loss: float
    value_loss: float
    entropy: float           # mean over samples, nats (summed over the 6 valves)
    approx_kl: float         # mean (r - 1) - log r estimator over all minibatches
    clipfrac: float          # fraction of samples with |r - 1| > clip
    explained_variance: float
    open_fraction: float     # mean valve-open probability over the batch
    gradient_steps: int


def explained_variance(pred: torch.Tensor, target: torch.Tensor) -> float:
    """1 - Var(target - pred) / Var(target); nan when the target is constant."""
    var = target.var(unbiased=False)
    return float("nan") if var == 0 else float(1.0 - (target - pred).var(unbiased=False) / var)


class PPOEngine(Protocol):
    """How a :class:`~ftc.learning.ppo.PPO` computes (``PPOConfig.engine``):
    torch (:class:`~ftc.learning.ppo.TorchEngine`) or native
    (:class:`~ftc.learning.ppo_native.NativeEngine`). An engine works on the
    PPO's torch policy, optimiser and generator and keeps no state a
    checkpoint needs (Adam's moments live in the torch optimiser for both), so
    :meth:`PPO.state_dict` is the checkpoint of either and a run resumes with
    either."""

    name: str

    def act(self, policy: ActorCritic, obs: torch.Tensor, generator: torch.Generator | None,
            deterministic: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """As :meth:`ActorCritic.act`: actions (N, 6), log-probs (N,), values (N,)."""
        ...

    def update(self, policy: ActorCritic, optimizer: torch.optim.Optimizer, batch: Any,
               config: PPOConfig, generator: torch.Generator | None) -> UpdateStats:
        """config.update_epochs passes over the batch (a RolloutBatch) in shuffled
        minibatches; stops early when approx-KL exceeds config.target_kl."""
        ...

    def distill(self, policy: ActorCritic, states: torch.Tensor, actions: torch.Tensor, *,
                epochs: int, minibatch: int, lr: float, max_grad_norm: float,
                generator: torch.Generator, stop_loss: float = 0.0,
                weights: torch.Tensor | None = None) -> tuple[float, int]:
        """Behaviour cloning of 0/1 valve labels into the policy's logits (binary
        cross-entropy, a fresh Adam): the last minibatch's loss and the epochs run."""
        ...
