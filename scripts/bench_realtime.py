#!/usr/bin/env python3
"""How fast a plant the embedded controller keeps up with: build/policy_node
flying a policy on the plant in real-time mode at rising rates.

    .venv/bin/python scripts/bench_realtime.py [--steps 5000] [--rates 100 200 500 1000 2000]
        [--results docs/results/realtime.csv] [--figure docs/figures/realtime_latency.png]

For each rate: a plant (single fault, --watchdog 1) in real-time mode on a
private loopback port and the node with a policy (a fresh ActorCritic, seed
0, exported as the node reads it) for --steps steps; the node's own line gives
the deadline misses (a plant step taken before the command answering the
state before it) and the latency percentiles (state received to command
sent). The highest rate with fewer than 0.1% misses is reported. With
--results the table is written as a result file (docs/results/), with
--figure a histogram of the latencies at the lowest rate.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "python"))
sys.path.insert(0, str(REPO / "scripts"))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from ftc.common.build_info import git_revision, plant_binary, policy_node_binary  # noqa: E402
from ftc.learning.ppo import ActorCritic  # noqa: E402
from ftc.plant import private_lcm_url, private_prefix  # noqa: E402
from ftc.tools import policy_weights  # noqa: E402

SUMMARY = re.compile(r"steps (\d+) deadline_misses (\d+) latency_p50_us (\d+) "
                     r"latency_p99_us (\d+) latency_max_us (\d+)")
MISS_LIMIT = 0.001  # the aim: fewer than 0.1% of the steps missed


def run_rate(weights: Path, rate: float, steps: int, log: Path) -> dict:
    url, prefix = private_lcm_url(), private_prefix()
    plant = subprocess.Popen([str(plant_binary()), "--scenario", str(REPO / "scenarios" /
                              "single.toml"), "--mode", "realtime", "--rate", str(rate),
                              "--watchdog", "1", "--lcm-url", url, "--prefix", prefix],
                             stderr=subprocess.DEVNULL)
    try:
        out = subprocess.run([str(policy_node_binary()), "--policy", str(weights), "--lcm-url",
                              url, "--prefix", prefix, "--steps", str(steps),
                              "--latency-log", str(log)], capture_output=True, text=True,
                             timeout=steps / rate + 60)
    finally:
        plant.kill()
        plant.wait()
    m = SUMMARY.search(out.stdout)
    if out.returncode or not m:
        raise SystemExit(f"bench_realtime: the node failed at {rate} Hz: {out.stderr.strip()}")
    n, misses, p50, p99, worst = map(int, m.groups())
    return {"rate_hz": f"{rate:g}", "steps": str(n), "deadline_misses": str(misses),
            "miss_fraction": f"{misses / n:.4f}", "latency_p50_us": str(p50),
            "latency_p99_us": str(p99), "latency_max_us": str(worst),
            "keeps_up": "yes" if misses / n < MISS_LIMIT else "no"}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=int, default=5000, help="steps per rate (default 5000)")
    p.add_argument("--rates", type=float, nargs="+", default=[100, 200, 500, 1000, 2000],
                   help="plant rates to try, Hz")
    p.add_argument("--results", type=Path, help="write the table as a result file")
    p.add_argument("--figure", type=Path, help="draw the latency histogram at the lowest rate")
    args = p.parse_args(argv)
    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as tmp:
        weights = Path(tmp) / "policy.txt"
        policy_weights.write_weights(weights, *policy_weights.actor_layers(ActorCritic()))
        rows, first_log = [], None
        for rate in sorted(args.rates):
            log = Path(tmp) / f"latency-{rate:g}.txt"
            rows.append(run_rate(weights, rate, args.steps, log))
            if first_log is None:
                first_log = np.loadtxt(log)
            print(" ".join(f"{k} {v}" for k, v in rows[-1].items()), flush=True)
    kept = [float(r["rate_hz"]) for r in rows if r["keeps_up"] == "yes"]
    print(f"bench_realtime: highest rate with < 0.1% misses: "
          f"{max(kept):g} Hz" if kept else "bench_realtime: no rate kept up")
    if args.results:
        from suite_results import write_result_file

        write_result_file(args.results, (
            f"# what: build/policy_node on the plant in real-time mode, {args.steps} steps per "
            f"rate, single fault, a fresh 6-64-64-16-16-6 policy; latency: state received to "
            f"command sent\n# command: scripts/bench_realtime.py --steps {args.steps} --rates "
            f"{' '.join(f'{r:g}' for r in args.rates)}\n# commit: {git_revision()}\n"), rows)
    if args.figure and first_log is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 3.2))
        ax.hist(first_log, bins=60, color="#4477aa")
        ax.set_yscale("log")
        ax.set_xlabel("latency, state received to command sent (microseconds)")
        ax.set_ylabel("steps")
        ax.set_title(f"policy_node at {rows[0]['rate_hz']} Hz, {rows[0]['steps']} steps: "
                     f"p50 {rows[0]['latency_p50_us']} us, p99 {rows[0]['latency_p99_us']} us",
                     fontsize=9)
        fig.tight_layout()
        args.figure.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(args.figure, dpi=100)
        print(f"bench_realtime: figure -> {args.figure}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
