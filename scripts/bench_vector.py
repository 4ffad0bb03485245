#!/usr/bin/env python3
"""The batched plant pool's speed (scripts/bench.py's "vector" group, and a
scaling table of its own).

    .venv/bin/python scripts/bench_vector.py [--rounds 3] [--sizes 1 4 16 64 256 1024 4096]
        [--results docs/results/vector.csv] [--figure docs/figures/vector_scaling.png]

Measured side by side in alternating rounds of one run (the machine is shared;
ratios are the figures to trust, absolute rates move with the load):

  pool steps/s     FuelTransferVectorEnv.step (Python call, action check and the
                   C++ step of N envs, closed form), random valves, single fault,
                   N envs and 1 or 2 C++ threads, in blocks of 128 steps from fresh
                   plants (Rate); and per CPU-second of the process: the rate of
                   unshared cores, and the CPU share the process got
  core env         gym.make("ftc/FuelTransferCore-v0") stepped the same way
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
import os
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
SECONDS = 0.25  # per measurement (whole blocks: at least one)
BLOCK = 128     # steps of a block, from fresh plants (age 0)
SB3_SIZES = (8, 16, 64)  # envs of the SB3 comparison (bench.py)


class Rate:
    """One measure: blocks of BLOCK steps with seeded random valves, each from fresh
    plants (age 0, seed 0; the fresh start untimed), repeated until SECONDS of
    stepping are timed. Every measure steps the same part of the plant's life, so
    its work per step does not depend on how fast it ran: a rate measured for a
    fixed time instead ages a fast env further than a slow one, and the faster the
    machine the older (a Core env ages ~10 intervals in 0.25 s), which moved the
    ratios with the load. A call returns env steps per wall second; the same
    blocks' steps per CPU-second of this process (every thread) go to .cpu_rates,
    and the CPU seconds the process got per wall second (2.0: both cores) to
    .cpu_shares."""

    def __init__(self, start: Callable[[], None], step: Callable[[int], None], envs: int,
                 seconds: float = SECONDS) -> None:
        self.start, self.step, self.envs, self.seconds = start, step, envs, seconds
        self.cpu_rates: list[float] = []
        self.cpu_shares: list[float] = []

    def __call__(self) -> float:
        wall = cpu = 0.0
        blocks = 0
        while blocks == 0 or wall < self.seconds:
            self.start()
            t, c = time.perf_counter(), time.process_time()
            for k in range(BLOCK):
                self.step(k)
            wall += time.perf_counter() - t
            cpu += time.process_time() - c
            blocks += 1
        steps = blocks * BLOCK * self.envs
        self.cpu_rates.append(steps / max(cpu, 1e-9))
        self.cpu_shares.append(cpu / wall)
        return steps / wall


def _actions(n: int, batches: int = BLOCK) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    return [rng.integers(0, 2, (n, 6), dtype=np.int8) for _ in range(batches)]


def pool_rate(n: int, threads: int, seconds: float = SECONDS) -> Rate:
    """The pool of n envs (single fault, closed form) on `threads` C++ threads."""
    env = FuelTransferVectorEnv(n, "single", threads=threads, copy=False)
    actions = _actions(n)
    return Rate(lambda: env.reset(seed=0), lambda k: env.step(actions[k]), n, seconds)


def core_env_rate(seconds: float = SECONDS) -> Rate:
    """gym.make("ftc/FuelTransferCore-v0"), single fault, the same blocks (a
    finished episode is reset within the block, as the pool's env is)."""
    env = gym.make("ftc/FuelTransferCore-v0")
    actions = [a[0] for a in _actions(1)]

    def step(k: int) -> None:
        _, _, term, trunc, _ = env.step(actions[k])
        if term or trunc:
            env.reset()
    return Rate(lambda: env.reset(seed=0), step, 1, seconds)


def sb3_rates(n: int, rounds: int, n_steps: int = 128) -> dict[str, float]:
    """env steps/s of PPO's collect_rollouts through the pool and through
    SubprocVecEnv over n Core envs (alternating rounds), and of PPO.learn
    (rollouts and updates) through the pool; and the two rollouts' env steps per
    CPU-second of every process they use (this one, and SubprocVecEnv's
    workers): under load n worker processes get n shares of the machine where
    the pool's one process gets one, so the wall ratio falls with the load and
    the CPU ratio does not."""
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

    workers = [p.pid for p in subproc_env.processes]
    cpu_rates: dict[str, list[float]] = {"pool": [], "subproc": []}

    def collect(model: PPO, name: str, pids: list[int]) -> Callable[[], float]:
        total, callback = model._setup_learn(10**9, CallbackList([]))
        callback.on_training_start(locals(), globals())

        def run() -> float:
            start, cpu = time.perf_counter(), time.process_time() + _cpu_seconds(pids)
            model.collect_rollouts(model.env, callback, model.rollout_buffer, n_steps)
            used = time.process_time() + _cpu_seconds(pids) - cpu
            cpu_rates[name].append(n_steps * n / max(used, 1e-9))
            return n_steps * n / (time.perf_counter() - start)
        return run

    def learn() -> float:
        start = time.perf_counter()
        pool.learn(2 * n_steps * n, reset_num_timesteps=False)
        return 2 * n_steps * n / (time.perf_counter() - start)

    try:
        a, b, c = _rounds(rounds, collect(pool, "pool", []), collect(subproc, "subproc", workers),
                          learn)
    finally:
        subproc_env.close()
    med = statistics.median
    return {"pool": med(a), "subproc": med(b), "learn": med(c),
            "pool_cpu": med(cpu_rates["pool"]), "subproc_cpu": med(cpu_rates["subproc"])}


def _cpu_seconds(pids: list[int]) -> float:
    """User + system CPU seconds of these processes so far (/proc/PID/stat)."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0
    for pid in pids:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        total += int(fields[11]) + int(fields[12])  # utime, stime (fields 14, 15)
    return total / tick


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


def scaling(rounds: int, sizes: tuple[int, ...] = SIZES) -> tuple[list[dict], list[float], Rate]:
    """Rows (threads, num_envs, steps_per_s, over_core_env, steps_per_cpu_s,
    cpu_share), the Core env's rates (steps per wall second) and its Rate (per
    CPU-second: .cpu_rates), every measure of a round taken side by side."""
    keys = [(t, n) for t in (1, 2) for n in sizes]
    pools = {key: pool_rate(key[1], key[0]) for key in keys}
    core = core_env_rate()
    measures = [pools[key] for key in keys] + [core]
    for m in measures:
        m()  # warm up (the prepared modes of age 0); not kept
        m.cpu_rates.clear(), m.cpu_shares.clear()
    *walls, core_walls = _rounds(rounds, *measures)
    med = statistics.median
    rows = [{"threads": t, "num_envs": n, "steps_per_s": f"{med(r):.0f}",
             "over_core_env": f"{med(r) / med(core_walls):.1f}",
             "steps_per_cpu_s": f"{med(pools[(t, n)].cpu_rates):.0f}",
             "cpu_share": f"{med(pools[(t, n)].cpu_shares):.2f}"}
            for (t, n), r in zip(keys, walls)]
    return rows, core_walls, core


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
    rows, core, core_rate = scaling(args.rounds, tuple(args.sizes))
    core_text = (f"the Core env {statistics.median(core):.0f} steps/s, "
                 f"{statistics.median(core_rate.cpu_rates):.0f} per CPU-second")
    print(core_text)
    for r in rows:
        print(r)
    if args.results:
        from suite_results import write_result_file

        from ftc.common.build_info import git_revision

        provenance = (f"# what: FuelTransferVectorEnv.step rate (env steps per wall second), "
                      f"random valves, single fault, closed form, blocks of {BLOCK} steps from "
                      f"fresh plants (age 0), median of {args.rounds} alternating rounds; "
                      f"over_core_env: over gym.make('ftc/FuelTransferCore-v0') stepped the "
                      f"same way in the same rounds ({core_text}); steps_per_cpu_s: per "
                      f"CPU-second of the process (every thread); cpu_share: CPU seconds the "
                      f"process got per wall second (2 = both cores)\n"
                      f"# command: scripts/bench_vector.py --rounds {args.rounds} --sizes "
                      f"{' '.join(map(str, args.sizes))}\n"
                      f"# commit: {git_revision()}\n# date: {time.strftime('%Y-%m-%d')}\n")
        write_result_file(args.results, provenance, rows)
        if args.figure:
            write_figure(read_rows(args.results), args.figure)
    return 0


if __name__ == "__main__":
    sys.exit(main())
