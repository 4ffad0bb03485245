"""The metrics.csv schema of interval runs (one row per interval) and the
progress line printed after each interval."""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

# every run's columns; an agent's own (Agent.extra_columns) go between the head and the tail
METRIC_COLUMNS = ["interval", "reward_per_step", "eval_reward_per_step", "episodes"]
TAIL_COLUMNS = ["online_seconds", "wall_time", "eval_steps"]
# what a refitted world model reports (the PPO agent's offline phase, the model MPC)
MODEL_COLUMNS = ("model_r2", "model_prior_r2", "model_one_step_rmse", "model_ten_step_rmse",
                 "demand_estimate")
# what a PPO agent reports per interval
PPO_COLUMNS = (*MODEL_COLUMNS, "offline_reward_per_step", "entropy", "open_fraction",
               "approx_kl", "clipfrac", "explained_variance", "value_loss", "policy_swaps",
               "offline_seconds")
# the PPO agents' entries of the progress line (Agent.progress_keys)
PPO_PROGRESS_KEYS = (("entropy", "entropy"), ("approx_kl", "kl"), ("explained_variance", "ev"))


def metric_columns(extra: Sequence[str]) -> list[str]:
    """metrics.csv's header for an agent whose own columns are ``extra``."""
    own = [c for c in dict.fromkeys(extra) if c not in METRIC_COLUMNS + TAIL_COLUMNS]
    return [*METRIC_COLUMNS, *own, *TAIL_COLUMNS]


# columns that measure time, not results (they differ run to run)
TIMING_COLUMNS = ("online_seconds", "offline_seconds", "wall_time", "refit_seconds",
                  "decisions_per_second")


def _isnan(x: Any) -> bool:
    return isinstance(x, float) and math.isnan(x)


def mean(values: Sequence[float]) -> float:
    return float(np.mean(values)) if len(values) else float("nan")


def format_cell(x: Any) -> Any:
    """A metrics.csv cell: 6 significant digits, '' for missing or nan."""
    if x is None or _isnan(x):
        return ""
    return f"{x:.6g}" if isinstance(x, float) else x


def progress_line(row: dict[str, Any], intervals: int,
                  extra: Sequence[tuple[str, str]] = ()) -> str:
    """``[###.......] interval 3/10  reward/step 2.345  eval ...  12.3s``"""
    k = row["interval"]
    parts = [f"[{'#' * (k + 1)}{'.' * (intervals - k - 1)}] interval {k + 1}/{intervals}",
             f"reward/step {row['reward_per_step']:.3f}"]
    for key, label in (("eval_reward_per_step", "eval"), ("model_r2", "model R2"), *extra):
        if row.get(key) is not None and not _isnan(row.get(key)):
            parts.append(f"{label} {row[key]:.3g}")
    parts.append(f"{row['wall_time']:.1f}s")
    return "  ".join(parts)
