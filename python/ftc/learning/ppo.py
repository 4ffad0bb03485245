"""PPO for six binary valves: config, actor-critic, update (buffer: :mod:`ftc.learning.buffer`).

Responsibilities are split as in Stable-Baselines3, and each part reads top to
bottom as in CleanRL:

* :class:`PPOConfig`     every hyperparameter, with help text and the source of its default
* :class:`ActorCritic`   the networks and the Bernoulli-per-valve distribution
* :class:`RolloutBuffer` preallocated (T, N, ...) storage; GAE and returns (buffer.py)
* :func:`ppo_update`     epochs x minibatches of the clipped-surrogate update
* :class:`PPO`           the algorithm: owns policy, optimiser and generator;
                         acts, fills a buffer, updates

The same code drives the real plant (N = 1 environment) and batched rollouts
on the learned world model (N environments at once).

Episode ends follow the plant: *termination* (fuel exhausted) is not
bootstrapped; *truncation* (interval boundary, model rollout cut short) is
bootstrapped from the critic's value of the final observation.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import nn

from ftc.common.cli import at_least, between, positive
from ftc.learning.buffer import NUM_VALVES, OBS_DIM, RolloutBatch, RolloutBuffer
from ftc.learning.ppo_numpy import NumpyActor, numpy_ppo_update
from ftc.learning.torch_startup import skip_dynamo_import

skip_dynamo_import()  # 2 s of start-up: nothing here is compiled


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
        "clip the value update around the old value (CleanRL option); off: with scaled "
        "rewards it only slows the critic")})
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
    engine: str = field(default="numpy", metadata={"choices": ("numpy", "torch"), "help": (
        "how acting and updates are computed: numpy (learning/ppo_numpy.py: "
        "hand-derived gradients, inner loops in C++, ftc._learn; 3-4x faster runs for "
        "these tiny networks; the same minibatches, loss, Adam and sampling stream; "
        "float32 rounding differs and PPO amplifies it: the benchmark suite's results are "
        "within seed noise of torch's, docs/benchmarks.md) or torch "
        "(autograd, the reference; tests/data/same_results pins it); clip_vloss "
        "uses torch")})

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


# --------------------------------------------------------------------------
# The update
# --------------------------------------------------------------------------

class UpdateStats(NamedTuple):
    policy_loss: float
    value_loss: float
    entropy: float           # mean over samples, nats (summed over the 6 valves)
    approx_kl: float         # mean (r - 1) - log r estimator over all minibatches
    clipfrac: float          # fraction of samples with |r - 1| > clip
    explained_variance: float
    open_fraction: float     # mean valve-open probability over the batch
    gradient_steps: int


def clipped_surrogate_loss(new_logprob: torch.Tensor, old_logprob: torch.Tensor,
                           advantages: torch.Tensor, clip_coef: float) -> torch.Tensor:
    """PPO's clipped surrogate, as a loss to minimise (scalar):
    mean(max(-A r, -A clip(r, 1 - eps, 1 + eps))), r = exp(new - old)."""
    ratio = (new_logprob - old_logprob).exp()
    return torch.max(-advantages * ratio,
                     -advantages * ratio.clamp(1.0 - clip_coef, 1.0 + clip_coef)).mean()


def explained_variance(pred: torch.Tensor, target: torch.Tensor) -> float:
    """1 - Var(target - pred) / Var(target); nan when the target is constant."""
    var = target.var(unbiased=False)
    return float("nan") if var == 0 else float(1.0 - (target - pred).var(unbiased=False) / var)


def ppo_update(policy: ActorCritic, optimizer: torch.optim.Optimizer, batch: RolloutBatch,
               config: PPOConfig, generator: torch.Generator | None = None) -> UpdateStats:
    """config.update_epochs passes over the batch in shuffled minibatches of
    config.minibatch_size; stops early when approx-KL exceeds config.target_kl."""
    B = batch.obs.shape[0]
    mb = min(config.minibatch_size, B)
    kls, clipfracs, steps = [], [], 0
    pg_loss = v_loss = entropy_mean = torch.zeros(())
    for _epoch in range(config.update_epochs):
        order = torch.randperm(B, generator=generator)
        for start in range(0, B, mb):
            idx = order[start:start + mb]
            logprob, entropy, value = policy.evaluate_actions(batch.obs[idx], batch.actions[idx])
            log_ratio = logprob - batch.logprobs[idx]
            with torch.no_grad():
                ratio = log_ratio.exp()
                kls.append(float(((ratio - 1.0) - log_ratio).mean()))
                clipfracs.append(float(((ratio - 1.0).abs() > config.clip_coef).float().mean()))

            adv = batch.advantages[idx]
            if config.norm_adv and adv.numel() > 1:
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            pg_loss = clipped_surrogate_loss(logprob, batch.logprobs[idx], adv, config.clip_coef)

            target = batch.returns[idx]
            if config.clip_vloss:
                clipped = batch.values[idx] + (value - batch.values[idx]).clamp(
                    -config.clip_coef, config.clip_coef)
                v_loss = 0.5 * torch.max((value - target) ** 2, (clipped - target) ** 2).mean()
            else:
                v_loss = 0.5 * ((value - target) ** 2).mean()
            entropy_mean = entropy.mean()
            loss = pg_loss - config.ent_coef * entropy_mean + config.vf_coef * v_loss

            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(policy.parameters(), config.max_grad_norm)
            optimizer.step()
            steps += 1
        if config.target_kl is not None and np.mean(kls[-math.ceil(B / mb):]) > config.target_kl:
            break

    with torch.no_grad():
        logits, values = policy(batch.obs)
        open_fraction = float(torch.sigmoid(logits).mean())
        _, entropy_all = policy.log_prob_entropy(logits, batch.actions)
    return UpdateStats(
        policy_loss=float(pg_loss.detach()), value_loss=float(v_loss.detach()),
        entropy=float(entropy_all.mean()), approx_kl=float(np.mean(kls)),
        clipfrac=float(np.mean(clipfracs)),
        explained_variance=explained_variance(batch.values, batch.returns),
        open_fraction=open_fraction, gradient_steps=steps)


# --------------------------------------------------------------------------
# The algorithm
# --------------------------------------------------------------------------

class PPO:
    """Owns the policy, its optimiser and the torch generator used for sampling
    actions and shuffling minibatches, so a run is reproducible from its seed and
    resumable from :meth:`state_dict`."""

    def __init__(self, config: PPOConfig = PPOConfig(), seed: int = 0) -> None:
        self.config = config
        torch.manual_seed(seed)  # network initialisation
        self.policy = ActorCritic(config.trunk_sizes, config.head_sizes)
        self.generator = torch.Generator().manual_seed(seed)
        self.optimizer = self.new_optimizer()
        self._actor: NumpyActor | None = None  # NumPy views of self.policy (engine numpy)
        self._actor_of: ActorCritic | None = None

    def new_optimizer(self) -> torch.optim.Adam:
        return torch.optim.Adam(self.policy.parameters(), lr=self.config.learning_rate, eps=1e-5)

    def reset_optimizer(self) -> None:
        """A fresh optimiser state (at the start of adaptation: it narrows the spread
        across seeds)."""
        self.optimizer = self.new_optimizer()

    def act(self, obs: torch.Tensor, deterministic: bool = False
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Actions (N, 6), log-probs (N,), values (N,) for obs (N, 6)."""
        if self.config.engine == "numpy" and not obs.requires_grad:
            if self._actor is None or self._actor_of is not self.policy or self._actor.stale():
                self._actor, self._actor_of = NumpyActor(self.policy), self.policy
            return self._actor.act(obs, self.generator, deterministic)
        return self.policy.act(obs, self.generator, deterministic)

    @torch.no_grad()
    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.policy.value(obs)

    def update(self, buffer: RolloutBuffer, last_values: torch.Tensor) -> UpdateStats:
        """GAE on the buffer, then the PPO update; leaves the buffer emptied."""
        c = self.config
        buffer.compute_returns_and_advantages(last_values, c.gamma, c.gae_lambda, c.reward_scale)
        if c.engine == "numpy" and not c.clip_vloss:
            stats = numpy_ppo_update(self.policy, self.optimizer, buffer.batch(), c,
                                     self.generator, UpdateStats)
        else:
            stats = ppo_update(self.policy, self.optimizer, buffer.batch(), c, self.generator)
        buffer.reset()
        return stats

    def state_dict(self) -> dict[str, Any]:
        """Tensors and plain containers only (loadable with weights_only=True)."""
        return {"policy": self.policy.state_dict(), "optimizer": self.optimizer.state_dict(),
                "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.policy.load_state_dict(state["policy"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
