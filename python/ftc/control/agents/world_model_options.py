"""The options of a method that fits the world model (the paper's PPO and
model-mpc): one definition each, as dataclass fields of their configs."""

from __future__ import annotations

from dataclasses import field
from typing import Any

from ftc.common.cli import at_least
from ftc.control.run.config import MAX_INTERVALS


def model_window() -> Any:
    return field(default=1, metadata={"check": at_least(1, MAX_INTERVALS), "help": (
        "intervals of real data each refit trains on: 1 = only the interval just run "
        "(Algorithm 1: the cache is cleared after each refit); k > 1 keeps the last k")})


def model_engine() -> Any:
    return field(default="numpy", metadata={"choices": ("numpy", "torch"), "help": (
        "how the world model is trained: numpy (several times faster at this size) or "
        "torch (autograd); the same algorithm, minibatches and stopping rule, float32 "
        "rounding differs (docs/benchmarks.md)")})


def model_episodes() -> Any:
    return field(default=50, metadata={"check": at_least(1, 100_000), "help": (
        "nominal random-valve episodes for world-model pretraining (paper: 50)")})
