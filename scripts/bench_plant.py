#!/usr/bin/env python3
"""Plant benchmark (a script, not a timed test; the machine is shared and noisy,
so the LCM figures are measured side by side in alternating rounds and
compared as a ratio).

Prints:
  * the median wall time of one 1 s CVODE step in process, with valves held
    and with valves changing every step (build/bench_core);
  * lockstep steps per second from Python over LCM against the real plant, and
    against an echo responder that answers the same messages with no physics
    (build/lcm_echo), and their ratio (aim: >= 0.8).

Usage: .venv/bin/python scripts/bench_plant.py [--steps 3000] [--rounds 3]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import time

import numpy as np

from ftc import BUILD_DIR
from ftc.common.build_info import echo_binary
from ftc.plant import LcmPlant, launch, private_lcm_url, private_prefix


def lockstep_rate(link, steps: int, rng: np.random.Generator) -> float:
    link.reset()
    valves = rng.integers(0, 2, (steps, 6))
    start = time.perf_counter()
    for u in valves:
        o = link.step(u)
        if o.done:
            link.reset()
    return steps / (time.perf_counter() - start)


def start_echo() -> LcmPlant:
    url, prefix = private_lcm_url(), private_prefix()
    proc = subprocess.Popen([str(echo_binary()), "--lcm-url", url, "--prefix", prefix])
    return LcmPlant(url, prefix, process=proc)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=3000, help="lockstep steps per round")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds per target")
    parser.add_argument("--core-steps", type=int, default=20000, help="in-process steps")
    args = parser.parse_args()

    out = subprocess.run([str(BUILD_DIR / "bench_core"), str(args.core_steps)],
                         capture_output=True, text=True, check=True).stdout
    print("in-process CVODE step (1 s of plant time):")
    for line in out.strip().splitlines():
        print("  " + line)

    rng = np.random.default_rng(0)
    plant_rates, echo_rates = [], []
    with launch("scenarios/multiple.toml", 0) as plant, start_echo() as echo:
        lockstep_rate(plant, 200, rng), lockstep_rate(echo, 200, rng)  # warm up
        for _ in range(args.rounds):
            plant_rates.append(lockstep_rate(plant, args.steps, rng))
            echo_rates.append(lockstep_rate(echo, args.steps, rng))
    p, e = statistics.median(plant_rates), statistics.median(echo_rates)
    print(f"lockstep over LCM from Python ({args.rounds} alternating rounds of {args.steps}):")
    print(f"  plant  {p:9.0f} steps/s   (rounds: {', '.join(f'{r:.0f}' for r in plant_rates)})")
    print(f"  echo   {e:9.0f} steps/s   (rounds: {', '.join(f'{r:.0f}' for r in echo_rates)})")
    print(f"  ratio plant/echo = {p / e:.3f}  (aim >= 0.8)")


if __name__ == "__main__":
    main()
