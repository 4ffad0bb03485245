"""The world model's side of Algorithm 1, shared by every agent that learns a
model: pretraining it on the nominal data set, the window of recent real
data, the refit after each interval (with its metrics), and the offline phase
(refit, then PPO on the model env)."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch

from ftc.common.constants import offline_seed
from ftc.learning.model_env import ModelEnv, estimate_demand
from ftc.learning.ppo import PPO, PPOConfig
from ftc.learning.pretrain import cache_file, load_cached, store_cached
from ftc.learning.rollout import train_on_env
from ftc.learning.transitions import Transitions, collect_nominal_dataset
from ftc.learning.world_model import WorldModel, WorldModelConfig, evaluate_model


def pretrained_world_model(episodes: int, seed: int, cache_dir: str = "", engine: str = "numpy"
                           ) -> tuple[WorldModel, float, dict[str, float]]:
    """The model fitted on the paper's nominal data set (``episodes`` random-valve
    episodes), the demand per step estimated from it, and what was measured.

    With ``cache_dir`` the result is kept there, keyed on (episodes, seed, the
    model's config, the code's fingerprint), and loaded by later runs: the
    same weights, normalisers and fit count bit for bit, since pretraining is
    deterministic in those inputs; ``model_pretrain_cached`` says which happened.
    """
    config = WorldModelConfig(seed=seed, engine=engine)
    path = cache_file(cache_dir, {"world_model": dataclasses.asdict(config),
                                  "episodes": episodes, "seed": seed}) if cache_dir else None
    cached = load_cached(path) if path is not None else None
    if cached is not None:
        try:
            model = WorldModel(config)
            model.load_state_dict(cached["model"])
            model.fits = int(cached["fits"])
            return model, float(cached["demand"]), {**cached["info"], "model_pretrain_cached": 1}
        except Exception:  # noqa: BLE001 - a record of another layout is rebuilt
            pass
    start = time.perf_counter()
    data = collect_nominal_dataset(episodes, seed=seed)
    model = WorldModel(config)
    report = model.fit(data, warm_start=False)
    demand = estimate_demand(data)
    info = {"model_pretrain_r2": report.r2, "model_pretrain_seconds": time.perf_counter() - start}
    if path is not None:
        store_cached(path, {"model": model.state_dict(), "fits": model.fits, "demand": demand,
                            "info": info})
    return model, demand, {**info, "model_pretrain_cached": 0}


class ModelWindow:
    """The real transitions each refit trains on: the last ``intervals`` intervals'
    (1: only the interval just run, and the cache is cleared after each refit,
    as in Algorithm 1)."""

    def __init__(self, intervals: int) -> None:
        self.intervals = intervals
        self.parts: list[Transitions] = []

    def add(self, data: Transitions) -> None:
        self.parts.append(data)

    def take(self) -> Transitions:
        """The data of the next refit (and clear the cache when the window is 1)."""
        self.parts = self.parts[-self.intervals:]
        data = Transitions.concat(self.parts)
        if self.intervals <= 1:
            self.parts = []
        return data


def refit(model: WorldModel, data: Transitions) -> tuple[float, dict[str, Any]]:
    """Warm-start refit of ``model`` on ``data``; returns the new demand estimate
    and the metrics (the model's error on ``data`` before it trained on it, R^2
    after)."""
    prior = evaluate_model(model, data)
    report = model.fit(data, warm_start=True)
    demand = estimate_demand(data)
    return demand, {"model_r2": report.r2, "model_prior_r2": prior["r2"],
                    "model_one_step_rmse": prior["one_step_rmse"],
                    "model_ten_step_rmse": prior["ten_step_rmse"],
                    "model_fit_epochs": report.epochs, "demand_estimate": demand}


@dataclass(frozen=True)
class OfflineSettings:
    """The offline phase's options (the controller's --offline-* options)."""

    seed: int
    steps: int = 2048          # t_offline: model steps of PPO per interval
    envs: int = 16             # model rollouts side by side
    rollout: int = 64          # model steps per env between updates
    minibatch: int = 64
    max_episode_steps: int = 512
    model_engine: str = "numpy"  # WorldModelConfig.engine of the refits


class OfflineResult(NamedTuple):
    ppo_state: dict
    model_state: dict
    model_fits: int
    metrics: dict


def offline_phase(ppo_state: dict, ppo_config: PPOConfig, model_state: dict, model_fits: int,
                  data: Transitions, settings: OfflineSettings, interval: int) -> OfflineResult:
    """Refit the world model on ``data`` (warm start), then PPO on the model env.

    A pure function of its arguments (state dicts in, state dicts out) so it can
    run in this process or in a background worker with the same result.
    """
    s = settings
    torch.set_num_threads(1)
    start = time.perf_counter()
    model = WorldModel(WorldModelConfig(seed=s.seed, engine=s.model_engine))
    model.load_state_dict(model_state)
    model.fits = model_fits
    demand, metrics = refit(model, data)
    refit_seconds = time.perf_counter() - start

    ppo = PPO(ppo_config, seed=s.seed)
    ppo.load_state_dict(ppo_state)
    ppo.generator.manual_seed(offline_seed(s.seed, interval))  # reproducible in any process
    ppo.config = dataclasses.replace(ppo_config, minibatch_size=s.minibatch)
    env = ModelEnv(model, s.envs, demand, max_episode_steps=s.max_episode_steps,
                   seed=offline_seed(s.seed, interval),
                   engine="torch" if ppo_config.engine == "torch" else "numpy")
    stats, rew, _ = train_on_env(ppo, env, s.steps, s.rollout)
    ppo.config = ppo_config
    metrics.update(offline_reward_per_step=rew, offline_updates=len(stats),
                   refit_seconds=refit_seconds, offline_seconds=time.perf_counter() - start)
    return OfflineResult(ppo.state_dict(), model.state_dict(), model.fits, metrics)
