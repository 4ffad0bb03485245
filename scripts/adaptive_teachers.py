"""Which teacher for the adaptive student (docs/adaptive.md): the privileged
planner on the true physics, "hold H steps, then all closed" over L steps,
scored per scenario on the suite, the check set and the held-out faults, for
each (H, L) given; H1,H2,...xL values each setting by the best of its plans
holding H1 or H2 or ... steps (``PoolTeacher``'s extra_holds). The student
can only approach its teacher, so the teacher that scores best on the check
and held-out sets is the one to distil.

    python scripts/adaptive_teachers.py --heldout-results RESULTS.csv \
        --out docs/results/adaptive_teachers.csv 3x10 3x6 2x6 2,1,3,6x6 ...

RESULTS.csv: a benchmark's results.csv with reference and closed on
scenarios/heldout/ (as ``ftc.experiments.adaptive evaluate --heldout-results``).
Each row also gives the teacher's labelling cost: its decisions per second of
this process's CPU time over the set (the pool's steps included; CPU time, so
that other jobs on the machine do not change it).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from ftc.control.planning.physics.teacher import PoolTeacher
from ftc.experiments.adaptive import evaluate
from ftc.experiments.adaptive.summary import write_result


def plan_shape(text: str) -> tuple[tuple[int, ...], int]:
    try:
        holds_text, horizon_text = text.lower().split("x")
        holds, horizon = tuple(int(v) for v in holds_text.split(",")), int(horizon_text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected HOLDxHORIZON or "
                                         f"HOLD,HOLD,...xHORIZON, e.g. 2x6 or 2,1,3,6x6") from None
    if not all(1 <= h <= horizon for h in holds) or len(set(holds)) < len(holds):
        raise argparse.ArgumentTypeError(f"{text!r}: need 1 <= hold <= horizon, each hold once")
    return holds, horizon


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("plans", nargs="+", type=plan_shape,
                   help="HOLDxHORIZON or HOLD,HOLD,...xHORIZON, e.g. 3x10 2x6 2,1,3,6x6")
    p.add_argument("--sets", nargs="+", default=["suite", "check", "heldout"],
                   choices=["suite", "check", "heldout"])
    p.add_argument("--heldout-results", type=Path, default=None)
    p.add_argument("--out", required=True, help="the table (CSV)")
    a = p.parse_args(argv)
    if "heldout" in a.sets and (a.heldout_results is None or not a.heldout_results.is_file()):
        print(f"adaptive_teachers: error: --sets heldout needs --heldout-results FILE "
              f"(got {a.heldout_results})", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    rows = []
    for holds, horizon in a.plans:
        hold = ",".join(map(str, holds))
        for which in a.sets:
            teacher = PoolTeacher(holds[0], horizon, extra_holds=holds[1:])
            start = time.process_time()
            scored = evaluate.evaluate(teacher, which, heldout=a.heldout_results)
            seconds = time.process_time() - start
            s = {r["scenario"]: r["score"] for r in scored}
            worst = min(s, key=s.get)
            rows.append({"hold": hold, "horizon": horizon, "set": which, "runs": len(s),
                         "mean score": round(float(np.mean(list(s.values()))), 3),
                         "worst scenario": f"{worst} ({s[worst]:.3f})",
                         "decisions per cpu second": round(teacher.labels / seconds)})
            print(f"adaptive_teachers: hold {hold} horizon {horizon} {which}: mean "
                  f"{rows[-1]['mean score']:.3f}, worst {rows[-1]['worst scenario']}", flush=True)
    write_result(a.out, "the adaptive student's candidate teachers: the planner on each plant's "
                 "true physics, 'hold H steps, then all closed' over L steps (oracle-mpc: H 3, "
                 "L 10; H1,H2,...: each setting valued by the best of its plans holding H1, "
                 "H2, ... steps), per-scenario normalized score per set (intervals 1-9, against the "
                 "reference and closed) in the batched pool", rows,
                 command="python scripts/adaptive_teachers.py")
    return 0


if __name__ == "__main__":
    sys.exit(main())
