#!/usr/bin/env python3
"""How fast a plant each controller keeps up with: the plant in real-time
mode at rising rates, driven by

    node   build/policy_node flying a policy (a fresh ActorCritic, seed 0,
           exported as the node reads it) for --steps steps;
    node-signed  the same with a bus key (plant and node --key-file): every
           message signed and checked (HMAC-SHA256), for the signing's cost
           side by side with node at the same rates;
    ppo    python -m ftc.controller --method ppo-offline --realtime RATE, learning
           on: 2 intervals of 256 steps, a PPO update every 128 steps and the
           offline phase (2048 model steps) after each interval, plus the
           evaluation episodes;
    mpc    python -m ftc.mpc --method oracle-mpc --realtime RATE, the same run;
    robust python -m ftc.controller --method ppo-robust --pretrain --offline-steps 0
           --realtime RATE, the same run: PPO updates and the guided fit (DAgger
           with the planner) after each interval, off the control loop.

    .venv/bin/python scripts/bench_realtime.py [--controllers node ppo mpc] [--steps 5000]
        [--rates 100 200 500 1000 2000] [--python-rates 20 50 100 200]
        [--results docs/results/realtime.csv] [--figure docs/figures/realtime_latency.png]

Every plant is on a private loopback port (single fault, --watchdog 1). A
deadline miss is a plant step taken before the command answering the state
before it; the latency runs from the state's arrival to the command's send.
The node prints both; a Python run's metrics.csv has them per interval
(deadline_misses summed, p50 the median of the intervals', p99 and max the
worst interval's). The highest rate with fewer than 0.1% misses is reported
per controller. With --results the table is written as a result file
(docs/results/), with --figure a histogram of the node's latencies at its
lowest rate.
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "python"))
sys.path.insert(0, str(REPO / "scripts"))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from ftc.common.build_info import git_revision, plant_binary, policy_node_binary  # noqa: E402
from ftc.plant.signing import new_key  # noqa: E402
from ftc.learning.ppo import ActorCritic  # noqa: E402
from ftc.plant import private_lcm_url, private_prefix  # noqa: E402
from ftc.tools import policy_weights  # noqa: E402

SUMMARY = re.compile(r"steps (\d+) deadline_misses (\d+) latency_p50_us (\d+) "
                     r"latency_p99_us (\d+) latency_max_us (\d+)")
MISS_LIMIT = 0.001  # the aim: fewer than 0.1% of the steps missed


def run_rate(weights: Path, rate: float, steps: int, log: Path,
             key_file: Path | None = None) -> dict:
    url, prefix = private_lcm_url(), private_prefix()
    keyed = ["--key-file", str(key_file)] if key_file else []
    plant = subprocess.Popen([str(plant_binary()), "--scenario", str(REPO / "scenarios" /
                              "single.toml"), "--mode", "realtime", "--rate", str(rate),
                              "--watchdog", "1", "--lcm-url", url, "--prefix", prefix, *keyed],
                             stderr=subprocess.DEVNULL)
    try:
        out = subprocess.run([str(policy_node_binary()), "--policy", str(weights), "--lcm-url",
                              url, "--prefix", prefix, "--steps", str(steps),
                              "--latency-log", str(log), *keyed], capture_output=True, text=True,
                             timeout=steps / rate + 60)
    finally:
        plant.kill()
        plant.wait()
    m = SUMMARY.search(out.stdout)
    if out.returncode or not m:
        raise SystemExit(f"bench_realtime: the node failed at {rate} Hz: {out.stderr.strip()}")
    n, misses, p50, p99, worst = map(int, m.groups())
    return _row("node-signed" if key_file else "node", rate, n, misses, p50, p99, worst)


def _row(controller: str, rate: float, n: int, misses: int, p50: float, p99: float,
         worst: float) -> dict:
    return {"controller": controller, "rate_hz": f"{rate:g}", "steps": str(n),
            "deadline_misses": str(misses), "miss_fraction": f"{misses / n:.4f}",
            "latency_p50_us": f"{p50:.0f}", "latency_p99_us": f"{p99:.0f}",
            "latency_max_us": f"{worst:.0f}",
            "keeps_up": "yes" if misses / n < MISS_LIMIT else "no"}


PYTHON_RUNS = {  # controller -> the run (2 intervals of 256 steps, the plant's rate added)
    "ppo": ["ftc.controller", "--method", "ppo-offline", "--update-every", "128"],
    "mpc": ["ftc.mpc", "--method", "oracle-mpc"],
    "robust": ["ftc.controller", "--method", "ppo-robust", "--pretrain", "--offline-steps", "0",
               "--update-every", "128"],
}


def run_python(controller: str, rate: float, out: Path) -> dict:
    """One real-time run of a Python controller; its deadlines from metrics.csv."""
    cmd = [sys.executable, "-m", *PYTHON_RUNS[controller], "--realtime", f"{rate:g}",
           "--intervals", "2", "--steps-per-interval", "256", "--quiet", "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": str(REPO / "python"), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO,
                          timeout=4 * 512 / rate + 300)
    if done.returncode:
        raise SystemExit(f"bench_realtime: {controller} failed at {rate:g} Hz: "
                         f"{done.stderr.strip()[-2000:]}")
    with open(out / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    n = sum(256 + int(r["eval_steps"]) for r in rows)
    p50 = float(np.median([float(r["latency_p50_ms"]) for r in rows]))
    p99 = max(float(r["latency_p99_ms"]) for r in rows)
    worst = max(float(r["latency_max_ms"]) for r in rows)
    return _row(controller, rate, n, sum(int(r["deadline_misses"]) for r in rows),
                1000 * p50, 1000 * p99, 1000 * worst)


def measure(controllers: list[str], steps: int, rates: list[float],
            python_rates: list[float], echo: bool = False) -> tuple[list[dict], Any]:
    """Every controller at every rate: the table's rows, and the node's latencies
    at its lowest rate with that row (or None)."""
    torch.manual_seed(0)
    rows, first_log = [], None
    with tempfile.TemporaryDirectory() as tmp:
        weights = Path(tmp) / "policy.txt"
        policy_weights.write_weights(weights, *policy_weights.actor_layers(ActorCritic()))
        key_file = Path(tmp) / "bus.key"
        key_file.write_text(new_key().hex())
        key_file.chmod(0o600)
        for controller in controllers:
            node = controller.startswith("node")
            for rate in sorted(rates if node else python_rates):
                if node:
                    log = Path(tmp) / f"latency-{controller}-{rate:g}.txt"
                    rows.append(run_rate(weights, rate, steps, log,
                                         key_file if controller == "node-signed" else None))
                    if first_log is None:
                        first_log = (np.loadtxt(log), rows[-1])
                else:
                    rows.append(run_python(controller, rate, Path(tmp) / f"{controller}-{rate:g}"))
                if echo:
                    print(" ".join(f"{k} {v}" for k, v in rows[-1].items()), flush=True)
    return rows, first_log


def highest_rate(rows: list[dict], controller: str) -> float | None:
    """The highest rate at which ``controller`` missed fewer than 0.1% of its deadlines."""
    kept = [float(r["rate_hz"]) for r in rows
            if r["controller"] == controller and r["keeps_up"] == "yes"]
    return max(kept) if kept else None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--controllers", nargs="+", choices=["node", "node-signed", *PYTHON_RUNS],
                   default=["node", *PYTHON_RUNS], help="which controllers (default all)")
    p.add_argument("--steps", type=int, default=5000,
                   help="the node's steps per rate (default 5000)")
    p.add_argument("--rates", type=float, nargs="+", default=[100, 200, 500, 1000, 2000],
                   help="plant rates to try with the node, Hz")
    p.add_argument("--python-rates", type=float, nargs="+", default=[20, 50, 100, 200],
                   help="plant rates to try with the Python controllers, Hz")
    p.add_argument("--results", type=Path, help="write the table as a result file")
    p.add_argument("--figure", type=Path, help="draw the latency histogram at the lowest rate")
    args = p.parse_args(argv)
    rows, first_log = measure(args.controllers, args.steps, args.rates, args.python_rates,
                              echo=True)
    for controller in args.controllers:
        best = highest_rate(rows, controller)
        print(f"bench_realtime: {controller}: highest rate with < 0.1% misses: "
              + (f"{best:g} Hz" if best else "none tried"))
    if args.results:
        from suite_results import write_result_file

        write_result_file(args.results, (
            f"# what: controllers on the plant in real-time mode, single fault: node = "
            f"build/policy_node, {args.steps} steps per rate, a fresh 6-64-64-16-16-6 policy; "
            f"ppo = ftc.controller ppo-offline learning on, mpc = ftc.mpc oracle-mpc, robust = "
            f"ftc.controller ppo-robust (guided fits), 2 x 256 steps and the evaluations; "
            f"latency: state received to command sent\n"
            f"# command: scripts/bench_realtime.py --controllers {' '.join(args.controllers)} "
            f"--steps {args.steps} --rates {' '.join(f'{r:g}' for r in args.rates)} "
            f"--python-rates {' '.join(f'{r:g}' for r in args.python_rates)}\n"
            f"# commit: {git_revision()}\n"), rows)
    if args.figure and first_log is not None:
        first_log, first = first_log
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 3.2))
        ax.hist(first_log, bins=60, color="#4477aa")  # the node's latencies, microseconds
        ax.set_yscale("log")
        ax.set_xlabel("latency, state received to command sent (microseconds)")
        ax.set_ylabel("steps")
        ax.set_title(f"policy_node at {first['rate_hz']} Hz, {first['steps']} steps: "
                     f"p50 {first['latency_p50_us']} us, p99 {first['latency_p99_us']} us",
                     fontsize=9)
        fig.tight_layout()
        args.figure.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(args.figure, dpi=100)
        print(f"bench_realtime: figure -> {args.figure}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
