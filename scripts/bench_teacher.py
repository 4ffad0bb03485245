"""The adaptive student's teachers' labelling cost, side by side (docs/adaptive.md):
each teacher labels the same states (levels drawn at random, late in blind-00's
life: worn tanks, two valves stuck closed, an engine burning more) in turn,
for a few rounds, and the script prints CPU milliseconds per label and each
teacher's cost over the one without a recheck (the earlier default's). CPU time of this process, one torch/BLAS
thread, so that other work on the machine moves the ratios little.

    python scripts/bench_teacher.py [--labels 300] [--rounds 3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ftc import _core
from ftc.control.planning.physics.teacher import PoolTeacher
from ftc.experiments.adaptive import distribution

TEACHERS = {  # name -> PoolTeacher options (hold 2 over 6, holds 1, 3 and 6 too)
    "no recheck (earlier default)": {},
    "recheck 4 over 10 (closed)": {"recheck": 4, "recheck_horizon": 10},
    "recheck 4 over 30 (balance, balancing default)": {"recheck": 4, "recheck_horizon": 30,
                                                       "recheck_rule": "balance"},
    "recheck 4 over 30 (best, default)": {"recheck": 4, "recheck_horizon": 30,
                                          "recheck_rule": "best"},
}
BASE = "no recheck (earlier default)"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--labels", type=int, default=300, help="states labelled per round")
    p.add_argument("--rounds", type=int, default=3, help="rounds, teachers interleaved")
    a = p.parse_args()
    if a.labels < 1 or a.rounds < 1:
        p.error("--labels and --rounds must be >= 1")
    scenario = _core.load_scenario(str(distribution.SCENARIO_DIR / "heldout" / "blind" /
                                       "blind-00.toml"))
    levels = np.random.default_rng(0).uniform(0.1, 1.0, (a.labels, 6))
    steps = 4000 + np.arange(a.labels) % 100  # 12 to 111 steps left in interval 7
    seconds = {name: 0.0 for name in TEACHERS}
    for _ in range(a.rounds):
        for name, options in TEACHERS.items():
            teacher = PoolTeacher(2, 6, extra_holds=(1, 3, 6), **options)
            start = time.process_time()
            teacher.label_with_regrets(list(range(a.labels)), [scenario] * a.labels, steps,
                                       levels)
            seconds[name] += time.process_time() - start
    labels = a.labels * a.rounds
    base = seconds[BASE] / labels
    print(f"{'teacher':38s} {'ms per label':>12s} {'over no recheck':>15s}")
    for name, s in seconds.items():
        print(f"{name:38s} {1e3 * s / labels:12.2f} {s / labels / base:15.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
