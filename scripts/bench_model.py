"""Benchmark of the learned-model side: ModelEnv steps per second (N = 64,
128, 256 envs, random valves) and seconds per world-model fit (nominal
pretraining and a warm-start refit on one 512-step interval of degraded data),
on the in-process C++ core. Prints a small table for the benchmark docs.

    .venv/bin/python scripts/bench_model.py [--steps 2000] [--threads 1]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from ftc.learning.model_env import ModelEnv, estimate_demand
from ftc.learning.transitions import collect_nominal_dataset, collect_random_episodes
from ftc.learning.world_model import WorldModel, WorldModelConfig
from ftc.plant import CorePlant

SINGLE_FAULT_TOML = 'name = "bench-single"\nengine_factor = [20.0, inf]\n'


def bench_env(model: WorldModel, num_envs: int, steps: int, threads: int) -> float:
    """Model steps (env transitions) per second with random valves."""
    env = ModelEnv(model, num_envs, demand_per_step=0.1, num_threads=threads)
    env.reset()
    gen = torch.Generator().manual_seed(0)
    actions = torch.randint(0, 2, (steps, num_envs, 6), generator=gen)
    for k in range(50):  # warm-up
        env.step(actions[k])
    start = time.perf_counter()
    for k in range(steps):
        env.step(actions[k])
    return steps * num_envs / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000, help="batched steps per measurement")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    args = parser.parse_args()

    start = time.perf_counter()
    nominal = collect_nominal_dataset(episodes=50, seed=0)
    collect_s = time.perf_counter() - start
    cfg = WorldModelConfig(num_threads=args.threads)
    model = WorldModel(cfg)
    pre = model.fit(nominal, cfg, warm_start=False)
    print(f"nominal data: {len(nominal)} rows in {collect_s:.2f} s")
    print(f"pretraining:  {pre.seconds:.2f} s, {pre.epochs} epochs, held-out R^2 "
          f"{pre.r2:.4f} (change {pre.r2_change:.3f})")

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "single.toml"
        path.write_text(SINGLE_FAULT_TOML)
        plant = CorePlant(str(path), 1, start_step=5 * 512)
        interval = collect_random_episodes(plant, 12, 1).tail(512)
    refits = []
    for _ in range(3):
        report = model.fit(interval, cfg, warm_start=True)
        refits.append(report)
    mean_s = sum(r.seconds for r in refits) / len(refits)
    print(f"warm refit on {len(interval)} rows: {mean_s:.2f} s per refit "
          f"(epochs {[r.epochs for r in refits]}), demand estimate "
          f"{estimate_demand(interval):.4f} m^3/step")

    print(f"ModelEnv, {args.threads} torch thread(s):")
    for n in (64, 128, 256):
        print(f"  N = {n:3d}: {bench_env(model, n, args.steps, args.threads):12,.0f} steps/s")


if __name__ == "__main__":
    main()
