"""The paper's world-model search: every point of a grid of architectures and
learning rates scored by k-fold cross-validated R^2 (folds split by episode)
on the nominal random-valve data set; written ranked to model_search.csv and
model_search.json."""

from __future__ import annotations

import dataclasses
import multiprocessing
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np
import torch

from ftc.common.atomic import atomic_write_csv, atomic_write_json
from ftc.experiments.progress import format_duration
from ftc.learning.transitions import Transitions, collect_nominal_dataset
from ftc.learning.world_model import WorldModelConfig, cross_validated_r2


@dataclass(frozen=True)
class ModelSearchConfig:
    """The paper's grid of world models, scored by k-fold cross-validated R^2.

    widths: hidden units per layer; layers: hidden layers; activations; lrs: Adam rates
    episodes: nominal episodes of random persistent valve settings in the data set
    folds: cross-validation folds; seed: data and initialisation seed
    """

    widths: tuple[int, ...] = (32, 64, 128, 256, 512)
    layers: tuple[int, ...] = (2, 3)
    activations: tuple[str, ...] = ("relu", "tanh")
    lrs: tuple[float, ...] = (1e-2, 5e-3, 1e-3)
    episodes: int = 50
    folds: int = 3
    seed: int = 0

    def grid(self) -> list[dict]:
        return [dict(width=w, layers=n, activation=a, lr=lr) for w in self.widths
                for n in self.layers for a in self.activations for lr in self.lrs]


QUICK_MODEL_SEARCH = ModelSearchConfig(widths=(32,), layers=(2,), activations=("relu", "tanh"),
                                       lrs=(1e-2,), episodes=6, folds=3)


def _model_search_point(data: Transitions, point: dict, folds: int, seed: int) -> dict:
    """Score one grid point (run in a worker process, so it sets its own threads and seed)."""
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    start = time.time()
    cfg = WorldModelConfig(hidden=(point["width"],) * point["layers"],
                           activation=point["activation"], lr=point["lr"], seed=seed)
    scores = np.atleast_1d(np.asarray(cross_validated_r2(data, cfg, folds=folds),
                                      dtype=np.float64))
    return {**point, "r2_mean": float(scores.mean()), "fit_seconds": time.time() - start}


def model_search(out: Path, config: ModelSearchConfig, jobs: int,
                 stream: TextIO = sys.stderr) -> list[dict]:
    """Score every grid point in parallel processes; write model_search.csv/json ranked."""
    out = Path(out)
    start = time.time()
    data = collect_nominal_dataset(episodes=config.episodes, seed=config.seed)
    grid = config.grid()
    print(f"model-search: {len(grid)} models, {config.folds}-fold CV on "
          f"{config.episodes} nominal episodes, jobs {jobs}", file=stream)
    results = []

    def report_point(i: int) -> None:
        r, el = results[-1], time.time() - start
        print(f"  [{i + 1}/{len(grid)}] {r['layers']}x{r['width']} {r['activation']} "
              f"lr {r['lr']:g}: R^2 {r['r2_mean']:.4f}  (elapsed {format_duration(el)}, ETA "
              f"{format_duration(el / (i + 1) * (len(grid) - i - 1))})", file=stream)

    if jobs <= 1:
        for i, p in enumerate(grid):
            results.append(_model_search_point(data, p, config.folds, config.seed))
            report_point(i)
    else:
        with ProcessPoolExecutor(max_workers=jobs,
                                 mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = [pool.submit(_model_search_point, data, p, config.folds, config.seed)
                       for p in grid]
            for i, f in enumerate(futures):
                results.append(f.result())
                report_point(i)
    results.sort(key=lambda r: -r["r2_mean"])
    for rank, r in enumerate(results, 1):
        r["rank"] = rank
    header = ["rank", "width", "layers", "activation", "lr", "r2_mean", "fit_seconds"]
    atomic_write_csv(out / "model_search.csv", header, [[r[h] for h in header] for r in results])
    atomic_write_json(out / "model_search.json", {"config": dataclasses.asdict(config),
                                                  "wall_time_s": time.time() - start,
                                                  "results": results})
    return results
