"""The adaptive controller (the paper's Algorithm 1): PPO online on the real plant,
offline on a world model refitted from real experience, interval by interval.

    python -m ftc.controller --scenario scenarios/single.toml --seed 0 --out runs/s0

Data flow of one interval k (t_online = 512 real steps):

    plant (own process, LCM) --levels--> policy --valves--> plant      x 512
         |                                  ^
         +-- cache (level, valves, next) ---|-- PPO update every t_update = 128 steps
         |
         +-- deterministic evaluation episode (plant.evaluate(), age frozen)
         |
    offline (sequential or in a background process):
         world model  <- refit from the cache (warm start), cache cleared
         PPO on ModelEnv(world model) for t_offline = 2048 model steps
         -> improved policy (swapped in when ready)

The plant degrades itself at every interval boundary; the controller is never
told the fault parameters (the model env's fuel demand is estimated from the
observed consumption). Baselines (all closed, all open, random valves) run
through the same loop and plant.

Outputs in --out DIR: config.json (resolved config, seed, git revision),
metrics.csv (one row per interval, rewritten atomically after each), a
checkpoint after every interval (checkpoint.pt, torch.load(weights_only=True)),
done.json when the run has finished; plant.pid while a launched plant runs.

Failures (one line on stderr, "ftc.controller: error: ..."; nothing written
after the last finished interval, so metrics.csv and checkpoint.pt stay those
of that interval and --resume continues from it):

    exit 2  bad input: a flag, or a --resume directory whose config.json or
            checkpoint.pt is corrupt, truncated or from another configuration
    exit 3  the plant stopped answering (retried with back-off for
            --link-give-up-timeout seconds): "plant gone at interval K, step T: ..."
    exit 4  a non-finite number: observation, PPO loss, gradient or weights
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np
import torch

from ftc.cli import add_dataclass_options
from ftc.plant import NUM_TANKS, PlantError, PlantGoneError, PlantLink, PlantObservation
from ftc.ppo import PPO, PPOConfig, RolloutBuffer, UpdateStats
from ftc.reward import reward

METHODS = ("ppo", "closed", "open", "random")


@dataclass
class ControllerConfig:
    """Everything a run depends on (with --ppo-* fields of :class:`PPOConfig`)."""

    method: str = field(default="ppo", metadata={"help": (
        "ppo: the adaptive controller; closed / open / random: baselines (all valves "
        "closed, all open, each valve open with p=0.5) through the same loop and plant")})
    scenario: str | None = field(default="scenarios/single.toml", metadata={"help": (
        "fault scenario TOML given to the plant (empty string: nominal plant)")})
    seed: int = field(default=0, metadata={"help": (
        "seeds the policy, the world model, model rollouts and the random baseline")})
    out: str = field(default="runs/controller", metadata={"help": "output directory"})
    intervals: int = field(default=10, metadata={"help": "number of intervals (paper: 10)"})
    steps_per_interval: int = field(default=512, metadata={"help": (
        "t_online: real steps per interval; forwarded to the plant so its degradation "
        "interval matches (paper: 512)")})
    update_every: int = field(default=128, metadata={"help": (
        "t_update: real steps between PPO updates (paper: 128)")})
    offline: bool = field(default=True, metadata={"help": (
        "after each online interval refit the world model and train PPO on it")})
    offline_mode: str = field(default="sequential", metadata={"help": (
        "sequential: offline phase between intervals; background: in a separate "
        "process while online control continues with the current policy, the improved "
        "policy swapped in at the next update boundary after it is ready (not "
        "reproducible step for step: the swap point depends on timing)")})
    offline_steps: int = field(default=2048, metadata={"help": (
        "t_offline: model steps of offline PPO per interval (paper: 2048)")})
    offline_envs: int = field(default=16, metadata={"help": (
        "model rollouts run side by side (one batch through the world model)")})
    offline_rollout: int = field(default=64, metadata={"help": (
        "model steps per env between offline PPO updates (update batch = envs x rollout)")})
    offline_minibatch: int = field(default=64, metadata={"help": (
        "PPO minibatch size for offline updates (online uses --ppo-minibatch-size)")})
    model_window: int = field(default=1, metadata={"help": (
        "intervals of real data each refit trains on: 1 = only the interval just run "
        "(Algorithm 1: the cache is cleared after each refit); k > 1 keeps the last k")})
    model_episodes: int = field(default=50, metadata={"help": (
        "nominal random-valve episodes for world-model pretraining (paper: 50)")})
    pretrain: bool = field(default=False, metadata={"help": (
        "pretrain the policy on the nominal plant in simulation (in-process core) "
        "before interval 0, stopped while it still explores (see --pretrain-open-fraction)")})
    pretrain_open_fraction: float = field(default=0.05, metadata={"help": (
        "pretraining stops once the mean valve-open probability over the last rollout "
        "falls to this (controller-notes item 1: ~5% keeps enough exploration to adapt)")})
    pretrain_deterministic_closed: bool = field(default=False, metadata={"help": (
        "also require the deterministic policy to keep every valve closed on every "
        "state of the last rollout before stopping (measured: that comes only at ~1.7% "
        "open, too little exploration left to adapt)")})
    pretrain_max_steps: int = field(default=200_000, metadata={"help": (
        "upper bound on pretraining simulation steps")})
    pretrain_sim: str = field(default="core", metadata={"help": (
        "where the policy is pretrained: core = the C++ physics of the nominal plant in "
        "process; model = batched rollouts of the pretrained world model (fast, but "
        "measured: the nominal model drifts on long all-closed runs, 87-step episodes "
        "at 1.80/step instead of 59 at 2.69, so PPO learns to open valves)")})
    pretrain_envs: int = field(default=16, metadata={"help": "nominal plants simulated side by side"})
    pretrain_ent_coef: float = field(default=0.0, metadata={"help": (
        "entropy bonus while pretraining; 0: the stop rule, not the bonus, decides how "
        "much exploration is left (with 0.01 the open fraction stalls near 0.15)")})
    pretrain_lr: float | None = field(default=None, metadata={"help": (
        "Adam step size while pretraining (None: the PPO learning rate)")})
    pretrain_minibatch: int = field(default=256, metadata={"help": (
        "PPO minibatch size while pretraining (large batches of cheap simulated steps)")})
    pretrain_rollout: int = field(default=64, metadata={"help": "steps per plant between updates"})
    pretrain_cache: str = field(default="~/.cache/ftc/pretrain", metadata={"help": (
        "directory of pretrained policies keyed by a hash of everything pretraining "
        "depends on (seed, pretrain and PPO settings); a hit skips pretraining with the "
        "same result ('' disables)")})
    fresh_optimizer: bool = field(default=True, metadata={"help": (
        "reset Adam's state when adaptation starts, after pretraining (controller-notes item 3)")})
    link: str = field(default="lcm", metadata={"help": (
        "lcm: the real plant process over LCM (launched, or --attach); core: the same "
        "physics in this process (fast experiments)")})
    attach: bool = field(default=False, metadata={"help": (
        "drive a plant already running (./build/plant) on --lcm-url/--prefix instead "
        "of launching one")})
    lcm_url: str | None = field(default=None, metadata={"help": (
        "LCM URL of the plant (default: a private loopback port when launching; "
        "the plant's default with --attach)")})
    prefix: str | None = field(default=None, metadata={"help": (
        "LCM channel prefix (default: a private one when launching; FTC_ with --attach)")})
    resume: str | None = field(default=None, metadata={"help": (
        "continue the stopped run in this directory from its last checkpoint")})
    link_retry_timeout: float = field(default=0.05, metadata={"help": (
        "seconds before an unanswered plant message is re-sent (LCM on loopback answers "
        "in well under 1 ms; a lost message costs this much)")})
    link_backoff: float = field(default=2.0, metadata={"help": (
        "the re-send wait grows by this factor after each unanswered re-send of one message")})
    link_give_up_timeout: float = field(default=5.0, metadata={"help": (
        "seconds without an answer after which the plant counts as gone (exit 3)")})
    quiet: bool = field(default=False, metadata={"help": "no progress lines on the console"})

    def validate(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"--method must be one of {METHODS}, got {self.method!r}")
        if self.offline_mode not in ("sequential", "background"):
            raise ValueError(f"--offline-mode must be sequential|background")
        if self.pretrain_sim not in ("model", "core"):
            raise ValueError("--pretrain-sim must be model|core")
        if self.link not in ("lcm", "core"):
            raise ValueError("--link must be lcm|core")
        if self.steps_per_interval % self.update_every:
            raise ValueError("--steps-per-interval must be a multiple of --update-every")
        if not (0 < self.link_retry_timeout <= self.link_give_up_timeout):
            raise ValueError("--link-retry-timeout must be > 0 and <= --link-give-up-timeout")
        if self.link_backoff < 1.0:
            raise ValueError(f"--link-backoff must be >= 1, got {self.link_backoff}")

    def link_config(self) -> "LinkConfig":
        from ftc.plant import LinkConfig

        return LinkConfig(retry_timeout=self.link_retry_timeout,
                          give_up_timeout=self.link_give_up_timeout, backoff=self.link_backoff)


# Fields that do not change a run's results: a checkpoint written under other values
# of these may be resumed (everything else must match, see Controller.restore).
RUN_LOCAL_FIELDS = ("out", "resume", "lcm_url", "prefix", "attach", "quiet", "link_retry_timeout",
                    "link_backoff", "link_give_up_timeout", "pretrain_cache")


class ControllerError(RuntimeError):
    """A run stopped; ``exit_code`` is what the command line exits with."""

    exit_code = 1


class CheckpointError(ControllerError):
    """A --resume directory's checkpoint or config is corrupt or does not match."""

    exit_code = 2


class PlantLostError(ControllerError):
    """The plant stopped answering during the run."""

    exit_code = 3


class NonFiniteError(ControllerError):
    """A non-finite observation, loss, gradient or weight."""

    exit_code = 4


# --------------------------------------------------------------------------
# Plant links
# --------------------------------------------------------------------------

def open_plant(cfg: ControllerConfig, start_step: int) -> PlantLink:
    """The plant this run drives, at ``start_step`` operating steps (resume)."""
    from ftc import plant

    scenario = cfg.scenario or None
    if cfg.link == "core":
        return plant.CorePlant(scenario, cfg.seed, steps_per_interval=cfg.steps_per_interval,
                               start_step=start_step)
    if cfg.attach:
        link = plant.LcmPlant(cfg.lcm_url or plant.DEFAULT_LCM_URL,
                              cfg.prefix or plant.DEFAULT_PREFIX, config=cfg.link_config())
        at = link.hello().operating_steps
        if at != start_step:
            link.close()
            raise RuntimeError(f"attached plant is at operating step {at}, the run needs "
                               f"{start_step}: start it with --start-step {start_step}")
        return link
    extra = ["--steps-per-interval", str(cfg.steps_per_interval)]
    if start_step:
        extra += ["--start-step", str(start_step)]
    return plant.launch(scenario, cfg.seed, lcm_url=cfg.lcm_url, prefix=cfg.prefix,
                        extra_args=extra, config=cfg.link_config())


class VecCorePlant:
    """N in-process nominal plants as one batched environment (pretraining).

    Same step interface as :class:`ftc.model_env.ModelEnv`: reset() -> obs (N, 6);
    step(actions (N, 6)) -> StepBatch, finished envs reset automatically.
    """

    def __init__(self, num_envs: int, seed: int, scenario: str | None = None) -> None:
        from ftc.plant import CorePlant

        self.plants = [CorePlant(scenario, seed + i) for i in range(num_envs)]
        self.num_envs = num_envs
        self.levels = [np.ones(NUM_TANKS)] * num_envs
        self.errors = 0  # steps the core refused (see step)

    def reset(self) -> torch.Tensor:
        self.levels = [p.reset().level for p in self.plants]
        return torch.tensor(np.stack(self.levels), dtype=torch.float32)

    def step(self, actions: torch.Tensor) -> "StepBatch":
        """A step the core refuses (it raises, e.g. on chattering) is counted in
        ``errors`` and ends that episode as a truncation at the last good state
        (reward 0): one bad simulated step must not end a pretraining run, and
        the count is reported so it cannot go unnoticed."""
        u = actions.numpy().astype(np.int8)
        obs, final, rew, term, trunc = [], [], [], [], []
        for i, (plant, a) in enumerate(zip(self.plants, u)):
            try:
                o = plant.step(a)
                level, r, t, tr = o.level, float(reward(o.level, a)), o.terminal, o.truncated
            except RuntimeError:
                self.errors += 1
                level, r, t, tr = self.levels[i], 0.0, False, True
            final.append(level)
            rew.append(r)
            term.append(t)
            trunc.append(tr and not t)
            self.levels[i] = plant.reset().level if (t or tr) else level
            obs.append(self.levels[i])
        f = lambda x: torch.tensor(np.stack(x), dtype=torch.float32)  # noqa: E731
        return StepBatch(f(obs), torch.tensor(rew), torch.tensor(term), torch.tensor(trunc),
                         f(final))


class StepBatch(NamedTuple):
    obs: torch.Tensor        # (N, 6) next observation (after auto-reset)
    reward: torch.Tensor     # (N,)
    terminal: torch.Tensor   # (N,) bool
    truncated: torch.Tensor  # (N,) bool
    final_obs: torch.Tensor  # (N, 6) observation before any reset (bootstrap of truncation)


# --------------------------------------------------------------------------
# Training on a batched simulated environment (pretraining and offline)
# --------------------------------------------------------------------------

def train_on_env(ppo: PPO, env: Any, total_steps: int, rollout: int,
                 stop: Callable[[UpdateStats, torch.Tensor], bool] | None = None
                 ) -> tuple[list[UpdateStats], float, int]:
    """PPO on a batched env (reset() -> (N, 6); step(a) -> obs, reward, terminal,
    truncated, final_obs) for up to ``total_steps`` env steps, updating every
    ``rollout`` steps per env; stops early when ``stop(stats, obs)`` is true
    (obs: (rollout, N, 6) the observations of the update's rollout).

    Returns the update stats, the mean reward per step and the steps taken.
    """
    n = env.num_envs
    buffer = RolloutBuffer(rollout, n)
    obs = env.reset()
    stats: list[UpdateStats] = []
    reward_sum, steps = 0.0, 0
    while steps + rollout * n <= max(total_steps, rollout * n):
        for _ in range(rollout):
            actions, logprobs, values = ppo.act(obs)
            s = env.step(actions)
            trunc_values = torch.where(s.truncated, ppo.value(s.final_obs), 0.0)
            buffer.add(obs, actions, logprobs, values, s.reward, s.terminal, s.truncated,
                       trunc_values)
            reward_sum += float(s.reward.sum())
            obs = s.obs
        steps += rollout * n
        stats.append(ppo.update(buffer, ppo.value(obs)))
        if stop is not None and stop(stats[-1], buffer.obs):
            break
        if steps >= total_steps:
            break
    return stats, reward_sum / max(steps, 1), steps


def pretrain_policy(ppo: PPO, cfg: ControllerConfig, model: Any = None,
                    demand: float = 0.0) -> dict[str, float]:
    """Nominal pretraining in simulation, stopped while the policy still explores.

    Stop rule (explicit and measured): after an update, the mean valve-open
    probability over the rollout is <= cfg.pretrain_open_fraction and the
    deterministic policy (open iff p > 0.5) keeps every valve closed on every
    state of the rollout (states a nominal closed-loop run visits; off that
    distribution, e.g. at random levels, the policy is not asked to be closed).
    Returns what was measured at the stop.
    """
    if model is None:
        env = VecCorePlant(cfg.pretrain_envs, cfg.seed * 1000 + 17)
    else:
        from ftc.model_env import ModelEnv

        env = ModelEnv(model, cfg.pretrain_envs, demand, max_episode_steps=cfg.steps_per_interval,
                       seed=cfg.seed * 1000 + 17)
    probe: dict[str, float] = {}

    def stop(s: UpdateStats, obs: torch.Tensor) -> bool:
        with torch.no_grad():
            logits, _ = ppo.policy(obs.reshape(-1, 6))
        det_open = float((logits > 0).float().mean())
        probe.update(open_fraction=s.open_fraction, entropy=s.entropy,
                     deterministic_open_fraction=det_open)
        if s.open_fraction > cfg.pretrain_open_fraction:
            return False
        return det_open == 0.0 or not cfg.pretrain_deterministic_closed

    start = time.perf_counter()
    online_config = ppo.config
    ppo.config = dataclasses.replace(online_config, ent_coef=cfg.pretrain_ent_coef,
                                     minibatch_size=cfg.pretrain_minibatch)
    if cfg.pretrain_lr is not None:
        for group in ppo.optimizer.param_groups:
            group["lr"] = cfg.pretrain_lr
    try:
        stats, rew, steps = train_on_env(ppo, env, cfg.pretrain_max_steps, cfg.pretrain_rollout,
                                         stop)
    finally:
        ppo.config = online_config
        for group in ppo.optimizer.param_groups:
            group["lr"] = online_config.learning_rate
    return {"pretrain_steps": steps, "pretrain_plant_errors": getattr(env, "errors", 0), "pretrain_updates": len(stats),
            "pretrain_reward_per_step": rew, "pretrain_open_fraction": probe["open_fraction"],
            "pretrain_entropy": probe["entropy"],
            "pretrain_deterministic_open_fraction": probe["deterministic_open_fraction"],
            "pretrain_seconds": time.perf_counter() - start}


class OfflineResult(NamedTuple):
    ppo_state: dict
    model_state: dict
    model_fits: int
    metrics: dict


def offline_phase(ppo_state: dict, ppo_config: PPOConfig, model_state: dict, model_fits: int,
                  data: Any, cfg: ControllerConfig, interval: int) -> OfflineResult:
    """Refit the world model on ``data`` (warm start), then PPO on the model env.

    A pure function of its arguments (state dicts in, state dicts out) so it can
    run in this process or in a background worker with the same result.
    """
    from ftc.model_env import ModelEnv, estimate_demand
    from ftc.world_model import WorldModel, WorldModelConfig, evaluate_model

    torch.set_num_threads(1)
    start = time.perf_counter()
    model = WorldModel(WorldModelConfig(seed=cfg.seed))
    model.load_state_dict(model_state)
    model.fits = model_fits
    # the model's error on the interval just run, before it has trained on it
    prior = evaluate_model(model, data)
    report = model.fit(data, warm_start=True)
    demand = estimate_demand(data)
    refit_seconds = time.perf_counter() - start

    ppo = PPO(ppo_config, seed=cfg.seed)
    ppo.load_state_dict(ppo_state)
    ppo.generator.manual_seed(cfg.seed * 7919 + interval)  # reproducible in any process
    ppo.config = dataclasses.replace(ppo_config, minibatch_size=cfg.offline_minibatch)
    env = ModelEnv(model, cfg.offline_envs, demand, max_episode_steps=cfg.steps_per_interval,
                   seed=cfg.seed * 7919 + interval)
    stats, rew, steps = train_on_env(ppo, env, cfg.offline_steps, cfg.offline_rollout)
    ppo.config = ppo_config
    metrics = {"model_r2": report.r2, "model_prior_r2": prior["r2"],
               "model_one_step_rmse": prior["one_step_rmse"],
               "model_ten_step_rmse": prior["ten_step_rmse"], "model_fit_epochs": report.epochs,
               "demand_estimate": demand, "offline_reward_per_step": rew,
               "offline_updates": len(stats), "refit_seconds": refit_seconds,
               "offline_seconds": time.perf_counter() - start}
    return OfflineResult(ppo.state_dict(), model.state_dict(), model.fits, metrics)


# --------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------

METRIC_COLUMNS = [
    "interval", "reward_per_step", "eval_reward_per_step", "episodes", "model_r2",
    "model_prior_r2", "model_one_step_rmse", "model_ten_step_rmse", "demand_estimate",
    "offline_reward_per_step", "entropy", "open_fraction", "approx_kl", "clipfrac",
    "explained_variance", "value_loss", "policy_swaps", "online_seconds", "offline_seconds",
    "wall_time"]


def _mean(values: Sequence[float]) -> float:
    return float(np.mean(values)) if len(values) else float("nan")


class Controller:
    """Algorithm 1 over a :class:`PlantLink`; see the module docstring."""

    def __init__(self, cfg: ControllerConfig, ppo_config: PPOConfig) -> None:
        cfg.validate()
        self.cfg, self.ppo_config = cfg, ppo_config
        self.out = Path(cfg.out)
        self.rows: list[dict[str, Any]] = []
        self.interval = 0
        self.info: dict[str, Any] = {}
        self.rng = np.random.default_rng(cfg.seed)  # random baseline
        self.ppo = PPO(ppo_config, seed=cfg.seed) if cfg.method == "ppo" else None
        self.model_state: dict | None = None
        self.model_fits = 0
        self.window: list[Any] = []  # real transitions of recent intervals
        self.executor = None
        self.pending = None
        self.pending_data: tuple[int, Any] | None = None  # (interval, data) of the job in flight
        self.swaps = 0
        self.where = "before the first step"  # position in the run, for error messages

    # -- setup ----------------------------------------------------------------
    def prepare(self) -> None:
        """Pretrain the world model (offline on) and the policy (--pretrain)."""
        if self.cfg.method != "ppo":
            return
        model, demand = None, 0.0
        if self.cfg.offline or (self.cfg.pretrain and self.cfg.pretrain_sim == "model"):
            from ftc.model_env import estimate_demand
            from ftc.world_model import (WorldModel, WorldModelConfig,
                                         collect_nominal_dataset)

            start = time.perf_counter()
            data = collect_nominal_dataset(self.cfg.model_episodes, seed=self.cfg.seed)
            model = WorldModel(WorldModelConfig(seed=self.cfg.seed))
            report = model.fit(data, warm_start=False)
            demand = estimate_demand(data)
            self.model_state, self.model_fits = model.state_dict(), model.fits
            self.info.update(model_pretrain_r2=report.r2,
                             model_pretrain_seconds=time.perf_counter() - start)
        if self.cfg.pretrain:
            self._pretrain(model if self.cfg.pretrain_sim == "model" else None, demand)
            if self.cfg.fresh_optimizer:
                self.ppo.reset_optimizer()
        self._say(" ".join(f"{k}={v:.4g}" for k, v in self.info.items()))

    def _pretrain(self, model: Any, demand: float) -> None:
        """Pretrain the policy, or load the identical result from the cache."""
        import hashlib

        cfg = self.cfg
        key_fields = {k: v for k, v in dataclasses.asdict(cfg).items()
                      if k.startswith("pretrain") and k != "pretrain_cache"}
        key_fields.update(seed=cfg.seed, steps_per_interval=cfg.steps_per_interval,
                          ppo=dataclasses.asdict(self.ppo_config), version=1)
        if cfg.pretrain_sim == "model":
            key_fields.update(model_episodes=cfg.model_episodes)
        key = hashlib.sha256(json.dumps(key_fields, sort_keys=True).encode()).hexdigest()[:16]
        path = Path(os.path.expanduser(cfg.pretrain_cache)) / f"{key}.pt" \
            if cfg.pretrain_cache else None
        if path is not None and path.exists():
            cached = torch.load(path, weights_only=True)
            self.ppo.load_state_dict(cached["ppo"])
            self.info.update(cached["info"], pretrain_cached=1)
            return
        info = pretrain_policy(self.ppo, cfg, model, demand)
        self.info.update(info, pretrain_cached=0)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
            torch.save({"ppo": self.ppo.state_dict(), "info": info, "key": key_fields}, tmp)
            os.replace(tmp, path)

    # -- one interval ---------------------------------------------------------
    def _valves(self, obs: np.ndarray, deterministic: bool = False
                ) -> tuple[np.ndarray, tuple | None]:
        method = self.cfg.method
        if method == "closed":
            return np.zeros(NUM_TANKS, np.int8), None
        if method == "open":
            return np.ones(NUM_TANKS, np.int8), None
        if method == "random":
            return self.rng.integers(0, 2, NUM_TANKS).astype(np.int8), None
        x = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
        a, lp, v = self.ppo.act(x, deterministic=deterministic)
        return a[0].numpy().astype(np.int8), (x, a, lp, v)

    def online(self, plant: PlantLink) -> dict[str, Any]:
        """t_online real steps with a PPO update every t_update; caches transitions."""
        from ftc.world_model import Transitions

        cfg = self.cfg
        buffer = RolloutBuffer(cfg.update_every, 1)
        stats: list[UpdateStats] = []
        rewards = np.zeros(cfg.steps_per_interval)
        observations: list[PlantObservation] = []
        k = self.interval
        self.where = f"interval {k}, step 0"
        o = _finite_observation(plant.reset(), self.where)
        observations.append(o)
        episodes = 1
        for t in range(cfg.steps_per_interval):
            u, sample = self._valves(o.level)
            self.where = f"interval {k}, step {t + 1}"
            nxt = _finite_observation(plant.step(u), self.where)
            observations.append(nxt)
            rewards[t] = reward(nxt.level, u)
            last = t == cfg.steps_per_interval - 1
            if last and not nxt.done:
                raise RuntimeError(f"plant did not end the interval after {t + 1} steps "
                                   "(is its steps_per_interval the same as ours?)")
            if nxt.done and not last and nxt.truncated:
                raise RuntimeError(f"plant truncated at step {t + 1} of the interval")
            if sample is not None:
                x, a, lp, v = sample
                trunc = nxt.truncated and not nxt.terminal
                tv = self.ppo.value(_obs(nxt)) if trunc else None
                buffer.add(x, a, lp, v, torch.tensor([rewards[t]]), torch.tensor([nxt.terminal]),
                           torch.tensor([trunc]), tv)
            o = nxt
            if nxt.terminal and not last:
                o = _finite_observation(plant.reset(), self.where + " (reset)")
                observations.append(o)
                episodes += 1
            if sample is not None and buffer.full:
                stats.append(self.ppo.update(buffer, self.ppo.value(_obs(o))))
                _check_update(self.ppo, stats[-1], f"the PPO update at {self.where}")
                self._maybe_swap()
        row: dict[str, Any] = {"reward_per_step": float(rewards.mean()), "episodes": episodes}
        if stats:
            row.update(entropy=_mean([s.entropy for s in stats]),
                       open_fraction=_mean([s.open_fraction for s in stats]),
                       approx_kl=_mean([s.approx_kl for s in stats]),
                       clipfrac=_mean([s.clipfrac for s in stats]),
                       explained_variance=_mean([s.explained_variance for s in stats]),
                       value_loss=_mean([s.value_loss for s in stats]))
        if self.ppo is not None and cfg.offline:
            self.window.append(Transitions.from_observations(observations))
        return row

    def evaluate(self, plant: PlantLink) -> float:
        """Deterministic policy (open iff p > 0.5) for one evaluation episode."""
        k = self.interval
        self.where = f"interval {k}, evaluation step 0"
        o = _finite_observation(plant.evaluate(), self.where)
        total, steps = 0.0, 0
        while not o.done:
            u, _ = self._valves(o.level, deterministic=True)
            self.where = f"interval {k}, evaluation step {steps + 1}"
            o = _finite_observation(plant.step(u), self.where)
            total += float(reward(o.level, u))
            steps += 1
        return total / max(steps, 1)

    # -- offline ---------------------------------------------------------------
    def _offline_inputs(self, interval: int) -> tuple:
        from ftc.world_model import Transitions

        self.window = self.window[-self.cfg.model_window:]
        data = Transitions.concat(self.window)
        if self.cfg.model_window <= 1:
            self.window = []  # Algorithm 1: clear the cache
        return (self.ppo.state_dict(), self.ppo_config, self.model_state, self.model_fits, data,
                self.cfg, interval)

    def _apply(self, result: OfflineResult, interval: int, swap: bool) -> None:
        what = f"the offline phase of interval {interval}"
        _check_finite_state(result.ppo_state["policy"], f"policy weights after {what}")
        _check_finite_state(result.model_state, f"world-model weights after {what}")
        if swap:
            self.ppo.load_state_dict(result.ppo_state)
        self.model_state, self.model_fits = result.model_state, result.model_fits
        self.rows[interval].update(result.metrics)

    def offline(self, interval: int) -> None:
        if self.cfg.offline_mode == "sequential":
            self._apply(offline_phase(*self._offline_inputs(interval)), interval, swap=True)
            return
        self._wait_pending()  # the previous phase's model is the next refit's start
        self._submit(self._offline_inputs(interval))

    def _submit(self, inputs: tuple) -> None:
        """Start an offline phase in the background worker."""
        interval, data = inputs[-1], inputs[4]
        if self.executor is None:
            import concurrent.futures
            import multiprocessing

            self.executor = concurrent.futures.ProcessPoolExecutor(
                1, mp_context=multiprocessing.get_context("spawn"))
        generator_state = self.ppo.generator.get_state()
        self.pending = (self.executor.submit(offline_phase, *inputs), interval)
        self.pending_data = (interval, data)
        self.ppo.generator.set_state(generator_state)

    def _maybe_swap(self) -> None:
        if self.pending is not None and self.pending[0].done():
            self._take_pending()

    def _take_pending(self) -> None:
        future, interval = self.pending
        self.pending, self.pending_data = None, None
        result = future.result()
        # the online generator keeps its own stream; only weights and Adam state swap in
        generator_state = self.ppo.generator.get_state()
        self._apply(result, interval, swap=True)
        self.ppo.generator.set_state(generator_state)
        self.swaps += 1

    def _wait_pending(self) -> None:
        if self.pending is not None:
            self._take_pending()

    # -- persistence -----------------------------------------------------------
    def checkpoint(self) -> None:
        """Everything needed to continue after interval ``self.interval - 1``."""
        state = {"interval": self.interval, "rows": self.rows, "info": self.info,
                 "np_rng": self.rng.bit_generator.state, "torch_rng": torch.get_rng_state(),
                 "model": self.model_state, "model_fits": self.model_fits,
                 "window": [_transitions_state(w) for w in self.window],
                 # a background offline phase in flight: its data, to start it again on resume
                 "pending": None if self.pending_data is None else {
                     "interval": self.pending_data[0],
                     "data": _transitions_state(self.pending_data[1])},
                 "ppo": self.ppo.state_dict() if self.ppo else None,
                 "format": CHECKPOINT_FORMAT, "config": self._config_stamp()}
        tmp = self.out / "checkpoint.pt.tmp"
        torch.save(state, tmp)
        os.replace(tmp, self.out / "checkpoint.pt")

    def _config_stamp(self) -> dict[str, Any]:
        """What a checkpoint must agree with to be resumed by this configuration."""
        ctrl = {k: v for k, v in dataclasses.asdict(self.cfg).items() if k not in RUN_LOCAL_FIELDS}
        ppo = dataclasses.asdict(self.ppo_config)
        ppo.update(trunk_sizes=list(ppo["trunk_sizes"]), head_sizes=list(ppo["head_sizes"]))
        return {"controller": ctrl, "ppo": ppo}

    def _load_checkpoint(self) -> dict[str, Any]:
        """checkpoint.pt, checked against this run's configuration before anything
        of it is used; raises CheckpointError saying why it cannot be resumed."""
        path = self.out / "checkpoint.pt"
        if not path.is_file():
            raise CheckpointError(f"{path}: no checkpoint (the run stopped before its first "
                                  "interval finished; start it again without --resume)")
        try:
            state = torch.load(path, weights_only=True)
        except Exception as e:  # noqa: BLE001 - any failure to read means corrupt
            reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise CheckpointError(f"{path}: corrupt or truncated checkpoint "
                                  f"({type(e).__name__}: {reason[:200]})") from None
        if not isinstance(state, dict) or "format" not in state:
            raise CheckpointError(f"{path}: not a controller checkpoint of this version "
                                  "(no format record)")
        if state["format"] != CHECKPOINT_FORMAT:
            raise CheckpointError(f"{path}: checkpoint format {state['format']!r}, this "
                                  f"controller reads format {CHECKPOINT_FORMAT}")
        missing = sorted(CHECKPOINT_KEYS - set(state))
        if missing:
            raise CheckpointError(f"{path}: checkpoint lacks {', '.join(missing)}")
        if (self.ppo is None) != (state["ppo"] is None):
            raise CheckpointError(f"{path}: checkpoint of a run "
                                  f"{'without' if state['ppo'] is None else 'with'} a policy, "
                                  f"this run's --method is {self.cfg.method}")
        if self.ppo is not None:
            ours = self.ppo.policy.state_dict()
            theirs = state["ppo"].get("policy", {}) if isinstance(state["ppo"], dict) else {}
            if set(ours) != set(theirs):
                raise CheckpointError(f"{path}: network layers differ from this run's "
                                      f"(checkpoint {len(theirs)} tensors, here {len(ours)})")
            for name, tensor in ours.items():
                if tuple(theirs[name].shape) != tuple(tensor.shape):
                    raise CheckpointError(
                        f"{path}: network sizes differ: {name} is {tuple(theirs[name].shape)} "
                        f"in the checkpoint, {tuple(tensor.shape)} in this run's configuration")
        mine = self._config_stamp()
        diffs = [f"{part}.{key} {state['config'].get(part, {}).get(key)!r} in the checkpoint, "
                 f"{value!r} here" for part in ("controller", "ppo")
                 for key, value in mine[part].items()
                 if state["config"].get(part, {}).get(key) != value]
        if diffs:
            raise CheckpointError(f"{path}: written by a run with another configuration: "
                                  + "; ".join(diffs[:4]) + (" ..." if len(diffs) > 4 else ""))
        interval = state["interval"]
        if not (isinstance(interval, int) and 0 < interval <= self.cfg.intervals
                and len(state["rows"]) == interval):
            raise CheckpointError(f"{path}: inconsistent checkpoint (interval {interval!r}, "
                                  f"{len(state['rows'])} metrics rows, {self.cfg.intervals} "
                                  "intervals configured)")
        try:
            if state["ppo"] is not None:
                _check_finite_state(state["ppo"]["policy"], "policy weights in the checkpoint")
            if state["model"] is not None:
                _check_finite_state(state["model"], "world-model weights in the checkpoint")
        except NonFiniteError as e:
            raise CheckpointError(f"{path}: {e}") from None
        return state

    def restore(self) -> None:
        from ftc.world_model import Transitions

        state = self._load_checkpoint()
        self.interval, self.rows, self.info = state["interval"], state["rows"], state["info"]
        self.rng.bit_generator.state = state["np_rng"]
        torch.set_rng_state(state["torch_rng"])
        self.model_state, self.model_fits = state["model"], state["model_fits"]
        self.window = [Transitions(**{k: v.numpy() for k, v in w.items()}) for w in state["window"]]
        if self.ppo is not None:
            try:
                self.ppo.load_state_dict(state["ppo"])
            except (KeyError, RuntimeError, ValueError) as e:
                raise CheckpointError(f"{self.out / 'checkpoint.pt'}: policy or optimiser state "
                                      f"does not load: {str(e).splitlines()[0]}") from None
        if state.get("pending") is not None:  # restart the phase that was in flight
            p = state["pending"]
            data = Transitions(**{k: v.numpy() for k, v in p["data"].items()})
            self._submit((self.ppo.state_dict(), self.ppo_config, self.model_state,
                          self.model_fits, data, self.cfg, p["interval"]))

    def write_metrics(self) -> None:
        buf = io.StringIO()
        writer = csv.DictWriter(buf, METRIC_COLUMNS, extrasaction="ignore", lineterminator="\n")
        writer.writeheader()
        for row in self.rows:
            writer.writerow({k: _fmt(row.get(k)) for k in METRIC_COLUMNS})
        _atomic_write(self.out / "metrics.csv", buf.getvalue())

    def write_config(self) -> None:
        from ftc.build_info import git_revision

        doc = {"controller": dataclasses.asdict(self.cfg),
               "ppo": dataclasses.asdict(self.ppo_config), "seed": self.cfg.seed,
               "git_revision": git_revision(), "argv": sys.argv}
        if self.cfg.method == "ppo" and self.cfg.offline:
            from ftc.world_model import WorldModelConfig

            doc["world_model"] = dataclasses.asdict(WorldModelConfig(seed=self.cfg.seed))
        _atomic_write(self.out / "config.json", json.dumps(doc, indent=2, default=str) + "\n")

    # -- main loop ---------------------------------------------------------------
    def run(self, stop_after: int | None = None, plant: PlantLink | None = None
            ) -> list[dict[str, Any]]:
        """Run (or continue) the intervals; returns the metrics rows.

        stop_after: return after this many intervals of this call, as if the run
        had been stopped there (its checkpoint written; for tests of --resume).
        plant: drive this link instead of opening one from the config (tests).
        Raises a :class:`ControllerError` (PlantLostError, NonFiniteError,
        CheckpointError) with nothing written after the last finished interval.
        """
        cfg = self.cfg
        self.out.mkdir(parents=True, exist_ok=True)
        # one intra-op thread: the networks are tiny (threads cost more than they
        # give) and results are then bit-for-bit reproducible (measured: with the
        # default thread pool, losses differ in the 7th digit run to run)
        torch.set_num_threads(1)
        torch.manual_seed(cfg.seed)
        if cfg.resume:
            self.restore()
        else:
            self.write_config()
            self.prepare()
        start = time.perf_counter()
        if plant is None:
            try:
                plant = open_plant(cfg, self.interval * cfg.steps_per_interval)
            except PlantGoneError as e:
                raise PlantLostError(f"plant gone at interval {self.interval}, before the first "
                                     f"step: {e}") from None
            except PlantError as e:  # refused to start; its exit code 2 means bad input
                error = ControllerError(str(e))
                error.exit_code = 2 if e.exit_code == 2 else 1
                raise error from None
        pid_file = self.out / "plant.pid"
        process = getattr(plant, "process", None)
        if process is not None:  # for tools (and tests) that need the plant's process
            _atomic_write(pid_file, f"{process.pid}\n")
        try:
            while self.interval < cfg.intervals:
                k = self.interval
                t0 = time.perf_counter()
                swaps_before = self.swaps
                row = {"interval": k, **self.online(plant)}
                row["online_seconds"] = time.perf_counter() - t0
                row["eval_reward_per_step"] = self.evaluate(plant) if self.ppo else None
                self.rows.append(row)
                if self.ppo is not None and cfg.offline:
                    self.offline(k)
                row["policy_swaps"] = self.swaps - swaps_before
                row["wall_time"] = time.perf_counter() - start
                self.interval += 1
                self.checkpoint()
                self.write_metrics()
                self._progress(row)
                if stop_after is not None and self.interval >= stop_after:
                    return self.rows
            self._wait_pending()
            self.checkpoint()
            self.write_metrics()
        except PlantGoneError as e:
            raise PlantLostError(f"plant gone at {self.where}: {e}; results of the "
                                 f"{self.interval} finished intervals are in {self.out}, "
                                 "--resume continues from them") from None
        finally:
            plant.close()
            if process is not None:
                pid_file.unlink(missing_ok=True)
            if self.executor is not None:
                self.executor.shutdown(cancel_futures=True)
        _atomic_write(self.out / "done.json", json.dumps(
            {"intervals": self.interval, "wall_time": time.perf_counter() - start}) + "\n")
        return self.rows

    def _progress(self, row: dict[str, Any]) -> None:
        n = self.cfg.intervals
        bar = "#" * (row["interval"] + 1) + "." * (n - row["interval"] - 1)
        parts = [f"[{bar}] interval {row['interval'] + 1}/{n}",
                 f"reward/step {row['reward_per_step']:.3f}"]
        for key, label in (("eval_reward_per_step", "eval"), ("model_r2", "model R2"),
                           ("entropy", "entropy"), ("approx_kl", "kl"),
                           ("explained_variance", "ev")):
            if row.get(key) is not None and not _isnan(row.get(key)):
                parts.append(f"{label} {row[key]:.3g}")
        parts.append(f"{row['wall_time']:.1f}s")
        self._say("  ".join(parts))

    def _say(self, text: str) -> None:
        if not self.cfg.quiet and text:
            print(text, flush=True)


CHECKPOINT_FORMAT = 2
CHECKPOINT_KEYS = frozenset({"interval", "rows", "info", "np_rng", "torch_rng", "model",
                             "model_fits", "window", "ppo", "config"})


def _finite_observation(o: PlantObservation, where: str) -> PlantObservation:
    if not np.all(np.isfinite(o.level)):
        raise NonFiniteError(f"non-finite observation at {where}: levels {o.level.tolist()}")
    return o


def _check_finite_state(state: dict[str, Any], what: str) -> None:
    for name, value in state.items():
        if isinstance(value, dict):
            _check_finite_state(value, what)
        elif torch.is_tensor(value) and value.is_floating_point() \
                and not bool(torch.isfinite(value).all()):
            raise NonFiniteError(f"non-finite {what} ({name})")


def _check_update(ppo: PPO, stats: UpdateStats, what: str) -> None:
    """After an update: losses, then the last gradients, then the weights finite
    (a non-finite gradient of an earlier minibatch shows in the weights)."""
    for name in ("policy_loss", "value_loss", "entropy", "approx_kl"):
        if not math.isfinite(getattr(stats, name)):
            raise NonFiniteError(f"non-finite loss in {what}: {name} = {getattr(stats, name)}")
    for name, param in ppo.policy.named_parameters():
        if param.grad is not None and not bool(torch.isfinite(param.grad).all()):
            raise NonFiniteError(f"non-finite gradient in {what} ({name})")
    for name, param in ppo.policy.named_parameters():
        if not bool(torch.isfinite(param).all()):
            raise NonFiniteError(f"non-finite weights after {what} ({name}): a non-finite "
                                 "gradient reached them")


def _obs(o: PlantObservation) -> torch.Tensor:
    return torch.as_tensor(o.level, dtype=torch.float32).unsqueeze(0)


def _isnan(x: Any) -> bool:
    return isinstance(x, float) and math.isnan(x)


def _fmt(x: Any) -> Any:
    if x is None or _isnan(x):
        return ""
    return f"{x:.6g}" if isinstance(x, float) else x


def _transitions_state(t: Any) -> dict[str, torch.Tensor]:
    return {k: torch.as_tensor(getattr(t, k)) for k in ("level", "valves", "next_level", "episode")}


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


# --------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------

def _add_fields(parser: argparse.ArgumentParser, cls: type, prefix: str = "") -> None:
    add_dataclass_options(parser, cls, prefix, choices={"method": METHODS})


def parse_args(argv: Sequence[str] | None = None) -> tuple[ControllerConfig, PPOConfig]:
    parser = argparse.ArgumentParser(
        prog="python -m ftc.controller",
        description=__doc__.split("\n\n")[0] + " Prints one progress line per interval.",
    )
    _add_fields(parser, ControllerConfig)
    group = parser.add_argument_group("PPO hyperparameters")
    _add_fields(group, PPOConfig, "ppo-")
    ns = vars(parser.parse_args(argv))
    cfg = ControllerConfig(**{f.name: ns[f.name] for f in fields(ControllerConfig)})
    ppo = PPOConfig(**{f.name: ns["ppo_" + f.name] for f in fields(PPOConfig)})
    ppo.trunk_sizes, ppo.head_sizes = tuple(ppo.trunk_sizes), tuple(ppo.head_sizes)
    return cfg, ppo


def resume_config(out: str) -> tuple[ControllerConfig, PPOConfig]:
    """The configuration a stopped run was started with (from its config.json);
    raises CheckpointError when it is missing or malformed."""
    path = Path(out) / "config.json"
    try:
        doc = json.loads(path.read_text())
        cfg = ControllerConfig(**doc["controller"])
        ppo = PPOConfig(**doc["ppo"])
    except FileNotFoundError:
        raise CheckpointError(f"{path}: missing (is {out} a controller run directory?)") from None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise CheckpointError(f"{path}: malformed run configuration "
                              f"({type(e).__name__}: {e})") from None
    ppo.trunk_sizes, ppo.head_sizes = tuple(ppo.trunk_sizes), tuple(ppo.head_sizes)
    cfg.resume, cfg.out = out, out
    return cfg, ppo


def main(argv: Sequence[str] | None = None) -> int:
    torch.set_num_threads(1)
    cfg, ppo = parse_args(argv)
    try:
        cfg.validate()
    except ValueError as e:
        print(f"ftc.controller: error: {e}", file=sys.stderr, flush=True)
        return 2
    try:
        if cfg.resume:
            overrides = {k: getattr(cfg, k) for k in ("lcm_url", "prefix", "attach", "quiet",
                                                      "link_retry_timeout", "link_backoff",
                                                      "link_give_up_timeout")}
            cfg, ppo = resume_config(cfg.resume)
            for k, v in overrides.items():
                setattr(cfg, k, v)
        Controller(cfg, ppo).run()
    except ControllerError as e:
        print(f"ftc.controller: error: {e}", file=sys.stderr, flush=True)
        return e.exit_code
    return 0


if __name__ == "__main__":
    sys.exit(main())
