"""Nominal pretraining of the policy in simulation, stopped while it still
explores (a policy trained until exploration collapses barely adapts), with a cache of pretrained policies.

Stop rule (explicit and measured): after an update, the mean valve-open
probability over the rollout is <= ``open_fraction`` (also requiring the
deterministic policy to keep every valve closed comes only at ~1.7% open, too
little exploration left to adapt: docs/controller.md).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from ftc.common.atomic import atomic_torch_save
from ftc.common.constants import NUM_TANKS, pretrain_seed
from ftc.learning.ppo import PPO, UpdateStats
from ftc.learning.rollout import train_on_env
from ftc.learning.sim_env import VecCorePlant

CACHE_VERSION = 3  # bump when the cached record's layout changes


@dataclass(frozen=True)
class PretrainSettings:
    """What pretraining depends on (the controller's --pretrain-* options)."""

    seed: int
    steps_per_interval: int
    envs: int = 16
    rollout: int = 64
    minibatch: int = 256
    max_steps: int = 200_000
    open_fraction: float = 0.05
    ent_coef: float = 0.0
    lr: float | None = None
    # PPO updates while pretraining: torch. The stop rule is a threshold on a noisy
    # statistic, so rounding differences move the stopping update (seed 0: update
    # 79 with torch, 71 with numpy) and give another policy, which adapted worse
    # on seeds 0 and 1 (docs/benchmarks.md); pretraining is cached, so its speed
    # matters least, and torch keeps every cached and measured pretrained policy.
    engine: str = "torch"


def pretrain_policy(ppo: PPO, settings: PretrainSettings) -> dict[str, float]:
    """Pretrain ``ppo`` in place on nominal C++ plants in process (pretraining
    on the pretrained world model instead measured worse: docs/controller.md);
    returns what was measured at the stop."""
    s = settings
    env = VecCorePlant(s.envs, pretrain_seed(s.seed))
    probe: dict[str, float] = {}

    def stop(stats: UpdateStats, obs: torch.Tensor) -> bool:
        with torch.no_grad():
            logits, _ = ppo.policy(obs.reshape(-1, NUM_TANKS))
        det_open = float((logits > 0).float().mean())
        probe.update(open_fraction=stats.open_fraction, entropy=stats.entropy,
                     deterministic_open_fraction=det_open)
        return stats.open_fraction <= s.open_fraction

    start = time.perf_counter()
    online_config = ppo.config
    ppo.config = dataclasses.replace(online_config, ent_coef=s.ent_coef, minibatch_size=s.minibatch,
                                     engine=s.engine)
    if s.lr is not None:
        for group in ppo.optimizer.param_groups:
            group["lr"] = s.lr
    try:
        stats, rew, steps = train_on_env(ppo, env, s.max_steps, s.rollout, stop)
    finally:
        ppo.config = online_config
        for group in ppo.optimizer.param_groups:
            group["lr"] = online_config.learning_rate
    return {"pretrain_steps": steps, "pretrain_plant_errors": env.errors,
            "pretrain_updates": len(stats), "pretrain_reward_per_step": rew,
            "pretrain_open_fraction": probe["open_fraction"],
            "pretrain_entropy": probe["entropy"],
            "pretrain_deterministic_open_fraction": probe["deterministic_open_fraction"],
            "pretrain_seconds": time.perf_counter() - start}


PACKAGE_DIR = Path(__file__).resolve().parents[1]
# the sources pretraining executes (policy, update, collector, simulated plants,
# the reward, constants)
FINGERPRINT_FILES = ("common/constants.py", "plant/link.py", "plant/reward.py",
                     "learning/buffer.py", "learning/ppo_policy.py", "learning/ppo.py",
                     "learning/rollout.py", "learning/sim_env.py", "learning/transitions.py",
                     "learning/pretrain.py", "learning/offline.py")


def code_fingerprint(package_dir: Path = PACKAGE_DIR, core: Path | None = None) -> str:
    """A hash of the code pretraining runs: the Python sources it executes and
    the compiled physics core. A cached policy made by other code is not reused."""
    if core is None:
        from ftc import _core  # native: the physics the nominal plants run

        core = Path(_core.__file__)
    h = hashlib.sha256()
    for name, path in [*((n, package_dir / n) for n in FINGERPRINT_FILES), (core.name, core)]:
        h.update(name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def cache_file(cache_dir: str, key_fields: dict[str, Any]) -> Path:
    """The cache entry of ``key_fields`` (plus this code's fingerprint and the
    cache layout version, which every key includes) under ``cache_dir``."""
    fields_ = {**key_fields, "code": code_fingerprint(), "version": CACHE_VERSION}
    key = hashlib.sha256(json.dumps(fields_, sort_keys=True).encode()).hexdigest()[:16]
    return Path(os.path.expanduser(cache_dir)) / f"{key}.pt"


def load_cached(path: Path) -> dict[str, Any] | None:
    """The record at ``path``, or None when there is none or it does not load
    (corrupt, other layout: the caller rebuilds and replaces it)."""
    if not path.exists():
        return None
    try:
        return torch.load(path, weights_only=True)
    except Exception:  # noqa: BLE001 - any unreadable entry is rebuilt
        return None


def store_cached(path: Path, record: dict[str, Any]) -> None:
    """Write ``record`` atomically; a cache that cannot be written costs time, not results."""
    try:
        atomic_torch_save(path, record)
    except OSError:
        pass


def cache_path(cache_dir: str, settings: PretrainSettings, ppo_config: Any) -> tuple[Path, dict]:
    """Where the policy pretrained with these settings and this code is cached."""
    ppo_fields = dataclasses.asdict(ppo_config)
    ppo_fields.pop("engine", None)  # pretraining runs settings.engine's updates
    key_fields = {"settings": dataclasses.asdict(settings), "ppo": ppo_fields}
    return cache_file(cache_dir, key_fields), {**key_fields, "code": code_fingerprint(),
                                               "version": CACHE_VERSION}


def pretrain_cached(ppo: PPO, settings: PretrainSettings, cache_dir: str) -> dict[str, Any]:
    """Pretrain ``ppo``, or load the identical result from ``cache_dir`` ('' : no cache).

    A cache entry that does not load (corrupt, other layout) is ignored and
    replaced; the returned info says which happened (``pretrain_cached``)."""
    if not cache_dir:
        return {**pretrain_policy(ppo, settings), "pretrain_cached": 0}
    path, key_fields = cache_path(cache_dir, settings, ppo.config)
    cached = load_cached(path)
    if cached is not None:
        try:
            ppo.load_state_dict(cached["ppo"])
            return {**cached["info"], "pretrain_cached": 1}
        except Exception:  # noqa: BLE001 - a record of another layout is rebuilt
            pass
    info = pretrain_policy(ppo, settings)
    store_cached(path, {"ppo": ppo.state_dict(), "info": info, "key": key_fields})
    return {**info, "pretrain_cached": 0}
