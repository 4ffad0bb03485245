#!/usr/bin/env python3
"""The batched plant pool's speed (scripts/bench.py's "vector" group, and a
scaling table of its own).

    .venv/bin/python scripts/bench_vector.py [--rounds 3] [--sizes 1 4 16 64 256 1024 4096]
        [--results docs/results/vector.csv] [--figure docs/figures/vector_scaling.png]

Measured side by side in alternating rounds of one run (the machine is shared;
ratios are the figures to trust, absolute rates move with the load):

  pool steps/s     FuelTransferVectorEnv.step (Python call, action check and the
                   C++ step of N envs, closed form), random valves, single fault,
                   N envs and 1 or 2 C++ threads; and per CPU-second (process
                   time, 1024 envs, 1 thread): the rate of one unshared core
  core env         gym.make("ftc/FuelTransferCore-v0") stepped with random valves
                   (and per CPU-second)
  sb3 rollouts     SB3 PPO's collect_rollouts (policy forward passes included)
                   through PoolVecEnv, and through SubprocVecEnv over N Core envs;
                   and PPO.learn through PoolVecEnv, updates included
  closed form      the largest level and reward difference between the pool's
                   closed-form and CVODE envs over the suite's scenarios

With --results the scaling table (threads, num_envs, steps_per_s) is written as
a result file, with --figure its plot; docs/benchmarks.md renders both.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "python"))
sys.path.insert(0, str(REPO / "scripts"))

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

import ftc  # noqa: E402,F401  (registers the ids)
from ftc.plant.vector import FuelTransferVectorEnv  # noqa: E402

SIZES = (1, 4, 16, 64, 256, 1024, 4096)
SECONDS = 0.25  # per measurement
# the last scaling()'s steps per CPU-second: the pool (1024 envs, 1 thread), the Core env
CPU_RATE: list[float] = []
CORE_CPU_RATE: list[float] = []


def _actions(n: int, batches: int = 16) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    return [rng.integers(0, 2, (n, 6), dtype=np.int8) for _ in range(batches)]


def pool_rate(n: int, threads: int, seconds: float = SECONDS,
              clock: Callable[[], float] = time.perf_counter) -> Callable[[], float]:
    """Steps/s of the pool; with clock=time.process_time, steps per CPU-second of
    this process (every thread): what a core gives when it is not shared."""
    env = FuelTransferVectorEnv(n, "single", threads=threads, copy=False)
    env.reset(seed=0)
    actions = _actions(n)

    def run() -> float:
        steps, start, used = 0, time.perf_counter(), clock()
        while time.perf_counter() - start < seconds:
            for a in actions:
                env.step(a)
            steps += len(actions)
        return steps * n / (clock() - used)
    return run


def core_env_rate(seconds: float = SECONDS,
                  clock: Callable[[], float] = time.perf_counter) -> Callable[[], float]:
    env = gym.make("ftc/FuelTransferCore-v0")
    env.reset(seed=0)
    actions = _actions(1, 256)

    def run() -> float:
        steps, start, used = 0, time.perf_counter(), clock()
        while time.perf_counter() - start < seconds:
            for a in actions:
                _, _, term, trunc, _ = env.step(a[0])
                if term or trunc:
                    env.reset()
            steps += len(actions)
        return steps / (clock() - used)
    return run


def sb3_rates(n: int, rounds: int, n_steps: int = 128) -> dict[str, float]:
    """env steps/s of PPO's collect_rollouts through the pool and through
    SubprocVecEnv over n Core envs (alternating rounds), and of PPO.learn
    (rollouts and updates) through the pool."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import CallbackList
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    from ftc.plant.sb3_vec import PoolVecEnv

    torch.set_num_threads(1)
    pool = PPO("MlpPolicy", PoolVecEnv(num_envs=n, scenario="single"), n_steps=n_steps,
               seed=0, device="cpu")
    subproc_env = make_vec_env("ftc/FuelTransferCore-v0", n_envs=n, vec_env_cls=SubprocVecEnv)
    subproc = PPO("MlpPolicy", subproc_env, n_steps=n_steps, seed=0, device="cpu")

    def collect(model: PPO) -> Callable[[], float]:
        total, callback = model._setup_learn(10**9, CallbackList([]))
        callback.on_training_start(locals(), globals())

        def run() -> float:
            start = time.perf_counter()
            model.collect_rollouts(model.env, callback, model.rollout_buffer, n_steps)
            return n_steps * n / (time.perf_counter() - start)
        return run

    def learn() -> float:
        start = time.perf_counter()
        pool.learn(2 * n_steps * n, reset_num_timesteps=False)
        return 2 * n_steps * n / (time.perf_counter() - start)

    try:
        a, b, c = _rounds(rounds, collect(pool), collect(subproc), learn)
    finally:
        subproc_env.close()
    med = statistics.median
    return {"pool": med(a), "subproc": med(b), "learn": med(c)}


def closed_form_error(steps: int = 500, seeds: int = 2) -> tuple[float, float, int]:
    """(largest true-level difference m, largest reward difference, steps whose
    episode end differs) between closed-form and CVODE plants (_core.Plant, as the
    pool's envs), the same random valves, over the suite's 22 scenarios and
    scenarios/ (64-step intervals so that the plants age)."""
    from ftc import _core
    from ftc.experiments.suite import write_suite

    with tempfile.TemporaryDirectory() as tmp:
        files = write_suite(Path(tmp), steps_per_interval=64)
        for p in [*sorted((REPO / "scenarios").glob("*.toml")),
                  *sorted((REPO / "scenarios" / "check").glob("*.toml"))]:
            out = Path(tmp) / f"x-{p.name}"
            out.write_text(p.read_text().replace("= 512", "= 64"))
            files.append(out)
        scenarios = [_core.load_scenario(str(f)) for f in files]
    rng = np.random.default_rng(0)
    level = reward = 0.0
    ends = 0
    for seed in range(seeds):
        for s in scenarios:
            a, b = (_core.Plant(s, seed, method=m) for m in ("cvode", "closed_form"))
            a.reset(), b.reset()
            for _ in range(steps):
                u = rng.integers(0, 2, 6)
                x, y = a.step(u), b.step(u)
                level = max(level, float(np.abs(x["level"] - y["level"]).max()))
                reward = max(reward, abs(_core.reward(x["observed"], u)["reward"]
                                         - _core.reward(y["observed"], u)["reward"]))
                ends += (x["terminal"], x["truncated"]) != (y["terminal"], y["truncated"])
                if x["terminal"] or x["truncated"]:
                    a.reset(), b.reset()
    return level, reward, ends


def _rounds(rounds: int, *measures: Callable[[], float]) -> list[list[float]]:
    out: list[list[float]] = [[] for _ in measures]
    for k in range(rounds):
        for i in range(len(measures)):
            j = (i + k) % len(measures)
            out[j].append(measures[j]())
    return out


def scaling(rounds: int, sizes: tuple[int, ...] = SIZES) -> tuple[list[dict], list[float]]:
    """Rows (threads, num_envs, steps_per_s) and the Core env's rates, every
    measure of a round taken side by side."""
    keys = [(t, n) for t in (1, 2) for n in sizes]
    measures = [pool_rate(n, t) for t, n in keys] + [core_env_rate()]
    for m in measures:
        m()  # warm up
    *pool, core = _rounds(rounds, *measures)
    global CPU_RATE, CORE_CPU_RATE  # noqa: PLW0603  (read by bench.py beside the rows)
    CPU_RATE, CORE_CPU_RATE = _rounds(rounds, pool_rate(1024, 1, clock=time.process_time),
                                      core_env_rate(clock=time.process_time))
    rows = [{"threads": t, "num_envs": n, "steps_per_s": f"{statistics.median(r):.0f}",
             "over_core_env": f"{statistics.median(r) / statistics.median(core):.1f}"}
            for (t, n), r in zip(keys, pool)]
    return rows, core


def write_figure(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6))
    for t in sorted({int(r["threads"]) for r in rows}):
        mine = [r for r in rows if int(r["threads"]) == t]
        ax.loglog([int(r["num_envs"]) for r in mine], [float(r["steps_per_s"]) for r in mine],
                  "o-", label=f"{t} thread{'s' if t > 1 else ''}")
    ax.axhline(1e6, color="grey", ls="--", lw=1, label="1,000,000 steps/s")
    ax.set_xlabel("envs in the pool (N)")
    ax.set_ylabel("env steps/s (random valves)")
    ax.set_title("FuelTransferVectorEnv.step, closed form, single fault")
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def write_curve_figure(rows: list[dict], path: Path) -> None:
    """examples/train_vector.py's curve (its --results file): reward per step per
    rollout against env steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot([int(r["steps"]) / 1e6 for r in rows], [float(r["reward_per_step"]) for r in rows],
            "-", lw=1)
    ax.set_xlabel("env steps (millions)")
    ax.set_ylabel("reward per step (rollout mean)")
    ax.set_title("examples/train_vector.py: PPO on the pool, fault distribution")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def read_rows(path: Path) -> list[dict]:
    from render_results import read_results

    return read_results(path)[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    parser.add_argument("--results", type=Path, help="write the scaling table here (CSV)")
    parser.add_argument("--figure", type=Path, help="plot the result file's table here")
    parser.add_argument("--figure-only", action="store_true",
                        help="only draw --figure from --results (no measurement)")
    parser.add_argument("--curve", type=Path, nargs=2, metavar=("CSV", "PNG"),
                        help="only plot examples/train_vector.py's --results CSV into PNG")
    args = parser.parse_args()
    if args.curve:
        write_curve_figure(read_rows(args.curve[0]), args.curve[1])
        return 0
    if args.figure_only:
        if not (args.results and args.figure):
            parser.error("--figure-only needs --results and --figure")
        write_figure(read_rows(args.results), args.figure)
        return 0
    rows, core = scaling(args.rounds, tuple(args.sizes))
    print(f"core env: {statistics.median(core):.0f} steps/s; per CPU-second: pool (1024 envs, "
          f"1 thread) {statistics.median(CPU_RATE):.0f}, core env "
          f"{statistics.median(CORE_CPU_RATE):.0f}")
    for r in rows:
        print(r)
    if args.results:
        from suite_results import write_result_file

        from ftc.common.build_info import git_revision

        provenance = (f"# what: FuelTransferVectorEnv.step rate (env steps/s), random valves, "
                      f"single fault, closed form, median of {args.rounds} alternating rounds; "
                      f"over_core_env: over gym.make('ftc/FuelTransferCore-v0') measured in the "
                      f"same rounds ({statistics.median(core):.0f} steps/s); per CPU-second "
                      f"(process time, 1 thread): the pool at 1024 envs "
                      f"{statistics.median(CPU_RATE):.0f}, the Core env "
                      f"{statistics.median(CORE_CPU_RATE):.0f}\n"
                      f"# command: scripts/bench_vector.py --rounds {args.rounds} --sizes "
                      f"{' '.join(map(str, args.sizes))}\n"
                      f"# commit: {git_revision()}\n# date: {time.strftime('%Y-%m-%d')}\n")
        write_result_file(args.results, provenance, rows)
        if args.figure:
            write_figure(read_rows(args.results), args.figure)
    return 0


if __name__ == "__main__":
    sys.exit(main())
