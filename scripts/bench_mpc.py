"""Benchmark of the MPC controllers: decisions per second of the
oracle (C++ batch rollouts, H=3, L=10: 64 candidates x 10 steps) and of the
learned-model MPC (torch, same planner), on states visited by a closed-loop
run of the single-fault plant at several ages; then, unless --no-runs, the
wall time of one single-fault experiment (10 intervals over LCM) per method
with its per-interval reward per step.

    .venv/bin/python scripts/bench_mpc.py [--seconds 2] [--intervals 10] [--no-runs]

One process at a time (the machine's cores are shared); the load average is
printed so numbers from a busy machine are read as such.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "python"))

from ftc import _core  # noqa: E402
from ftc.control.planning.physics.evaluators import OracleEvaluator  # noqa: E402
from ftc.control.planning.planners import HoldPlanner, ModelEvaluator  # noqa: E402
from ftc.plant import CorePlant  # noqa: E402

SCENARIO = REPO / "scenarios" / "single.toml"
NOTES_ORACLE = [2.68, 2.63, 2.59, 2.56, 2.53, 2.53, 2.50, 2.50, 2.48, 2.47]


def visited_states(ages: list[int], per_age: int = 40) -> list[tuple[int, np.ndarray]]:
    """(age, levels) along closed-valve episodes of the single-fault plant."""
    states = []
    for age in ages:
        plant = CorePlant(str(SCENARIO), 0, start_step=age * 512)
        o = plant.reset()
        for t in range(2 * per_age):  # every other step: spread over an episode
            if t % 2 == 0:
                states.append((age, o.level))
            o = plant.step(np.zeros(6, int))
            if o.done:
                o = plant.reset()
    return states


def rate(decide, states, seconds: float) -> float:
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        decide(*states[n % len(states)])
        n += 1
    return n / (time.perf_counter() - start)


def bench_decisions(seconds: float) -> None:
    states = visited_states([0, 3, 6, 9])
    planner = HoldPlanner(3, 10)
    scenario = _core.load_scenario(str(SCENARIO))

    for label, kwargs in (("oracle (rtol 1e-6, closed-form idle steps, shared prefixes)", {}),
                          ("oracle at the plant's tolerances (rtol 1e-8)",
                           {"rtol": 1e-8, "atol": 1e-10})):
        oracle = OracleEvaluator(scenario, **kwargs)

        def decide(age, x):
            oracle.set_age(float(age))
            planner.plan(oracle, x)

        print(f"{label}: {rate(decide, states, seconds):.0f} decisions/s")

    plain = _core.BatchRollout(exact_idle_conduit=False, share_prefixes=False)
    seqs = planner.candidates(10)
    params = {a: _core.degraded_params(scenario, float(a)) for a in (0, 3, 6, 9)}
    r = rate(lambda age, x: plain.run(x, seqs, params[age]), states, seconds)
    print(f"oracle without caches (CVODE every step, rtol 1e-8): {r:.0f} decisions/s")

    from ftc.learning.model_env import estimate_demand
    from ftc.learning.transitions import collect_nominal_dataset
    from ftc.learning.world_model import WorldModel, WorldModelConfig

    torch.set_num_threads(1)
    data = collect_nominal_dataset(50, seed=0)
    model = WorldModel(WorldModelConfig(seed=0))
    model.fit(data, warm_start=False)
    evaluator = ModelEvaluator(model, estimate_demand(data))
    r = rate(lambda age, x: planner.plan(evaluator, x), states, seconds)
    print(f"learned-model MPC (torch, 1 thread): {r:.0f} decisions/s")


def run_experiment(method: str, intervals: int) -> None:
    with tempfile.TemporaryDirectory(prefix=f"bench-mpc-{method}-") as out:
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "ftc.mpc", "--method", method, "--scenario",
                        str(SCENARIO), "--seed", "0", "--out", out, "--intervals",
                        str(intervals), "--quiet"], check=True,
                       env={**os.environ, "PYTHONPATH": str(REPO / "python")})
        wall = time.perf_counter() - start
        import csv

        with open(Path(out) / "metrics.csv") as f:
            rows = list(csv.DictReader(f))
    print(f"{method}: single-fault experiment, {intervals} intervals over LCM: {wall:.1f} s wall")
    print("  interval  reward/step  eval    notes(oracle)")
    for r in rows:
        k = int(r["interval"])
        note = f"{NOTES_ORACLE[k]:.2f}" if k < len(NOTES_ORACLE) else ""
        print(f"  {k:8d}  {float(r['reward_per_step']):11.3f}  "
              f"{float(r['eval_reward_per_step']):.3f}   {note}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=2.0, help="per decision benchmark")
    parser.add_argument("--intervals", type=int, default=10)
    parser.add_argument("--no-runs", action="store_true", help="skip the experiment runs")
    args = parser.parse_args()
    print(f"load average: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    bench_decisions(args.seconds)
    if not args.no_runs:
        for method in ("oracle", "model"):
            run_experiment(method, args.intervals)
    return 0


if __name__ == "__main__":
    sys.exit(main())
