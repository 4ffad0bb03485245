#!/usr/bin/env python3
"""The controller's quality bar: every method x seed on one scenario,
the per-interval mean reward per step experienced on the plant, and the checks.

    .venv/bin/python scripts/quality_controller.py --seeds 5 --jobs 2

Each run is ``python -m ftc.controller`` in its own process (and its own plant
process over LCM unless --link core), two at a time on the two cores. Results
are read back from each run's metrics.csv (plots and tables never recompute).

Checks (single fault, averaged over seeds, experienced metric; the bars and
the measurements behind them are in docs/controller.md, "Quality bar"):
  (a) PPO online+offline with --pretrain earns >= 95% of all-closed in interval 0
      (the exploration pretraining leaves costs about 2.5%);
  (b) ... earns >= 98% of all-closed in interval 1 (the first faulty interval,
      where it is level with all-closed) and beats all-closed in every later one;
  (c) ... and beats PPO online-only (--pretrain) averaged over intervals 1-9;
  (d) from scratch (the paper's setting) it beats random valves by interval 3.
Each check prints its measured value and its bar; the exit status is 1 when
a check or a run failed, 0 otherwise (checks whose methods are not run are
listed as not run). --judge applies (a) and (b) to another method: a broken
controller (--judge random) fails them.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import csv
import io
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

METHODS: dict[str, list[str]] = {
    "closed": ["--method", "closed"],
    "open": ["--method", "open"],
    "random": ["--method", "random"],
    "ppo-scratch": ["--method", "ppo", "--offline"],
    "ppo-online": ["--method", "ppo", "--no-offline", "--pretrain"],
    "ppo-offline": ["--method", "ppo", "--offline", "--pretrain"],
}

# The bars of checks (a) and (b), as fractions of all-closed's reward per step
# (docs/controller.md, "Quality bar", has the measurements behind them).
BAR_INTERVAL_0 = 0.95  # (a): the pretrained policy's exploration costs about 2.5%
BAR_INTERVAL_1 = 0.98  # (b): in the first faulty interval it is level with all-closed


def run_one(method: str, seed: int, args: argparse.Namespace) -> tuple[str, int, list[dict], float]:
    out = Path(args.out) / method / f"seed{seed}"
    cmd = [sys.executable, "-m", "ftc.controller", *METHODS[method], "--seed", str(seed),
           "--out", str(out), "--intervals", str(args.intervals), "--scenario", args.scenario,
           "--link", args.link, "--quiet",
           *(args.extra if "ppo" in method else ())]  # PPO options: only PPO runs take them
    start = time.perf_counter()
    done = out / "done.json"
    if not (args.reuse and done.exists()):
        proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
        if proc.returncode != 0:  # reported, and left out of the means
            print(f"FAILED {method} seed {seed}: {' '.join(cmd)}\n{proc.stderr[-1500:]}",
                  file=sys.stderr, flush=True)
            return method, seed, [], time.perf_counter() - start
    with open(out / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    return method, seed, rows, time.perf_counter() - start


LABELS = {"closed": "all closed", "open": "all open", "random": "random valves",
          "ppo-scratch": "PPO from scratch (paper)", "ppo-online": "PPO online, pretrained",
          "ppo-offline": "PPO online + offline, pretrained"}


def _machine() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            model = next(line.split(":", 1)[1].strip() for line in f
                         if line.startswith("model name"))
    except (OSError, StopIteration):
        model = "unknown CPU"
    return f"{model}, {os.cpu_count()} cores"


def _run_revisions(args: argparse.Namespace) -> str:
    """The commits the runs were made at (their config.json), for --reuse."""
    revisions = set()
    for config in Path(args.out).glob("*/seed*/config.json"):
        try:
            revisions.add(json.loads(config.read_text()).get("git_revision") or "unknown")
        except (OSError, ValueError):
            revisions.add("unreadable")
    return " ".join(sorted(r[:12] + ("-dirty" if r.endswith("-dirty") else "")
                           for r in revisions)) or "none"


def write_results(path: Path, exp: dict[str, np.ndarray], ev: dict[str, np.ndarray],
                  args: argparse.Namespace) -> None:
    """The table as a small CSV with its provenance in '#' lines (what, the
    measuring command, the commit it was written at and those its runs were
    made at, machine, date): what the docs' tables are rendered from."""
    sys.path.insert(0, str(REPO / "python"))
    from ftc.common.atomic import atomic_write_text
    from ftc.common.build_info import git_revision

    n = args.intervals
    command = (f"scripts/quality_controller.py --seeds {args.seeds} --jobs {args.jobs} "
               f"--link {args.link} --intervals {n} --scenario {args.scenario}"
               + (" -- " + " ".join(args.extra) if args.extra else ""))
    buf = io.StringIO()
    for line in (f"what: mean reward per step experienced, over {args.seeds} seeds",
                 f"command: {command}", f"commit: {git_revision()}",
                 f"runs made at: {_run_revisions(args)}", f"machine: {_machine()}",
                 f"date: {time.strftime('%Y-%m-%d')}"):
        buf.write(f"# {line}\n")
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["method", "label", "seeds", *(f"mean_{k}" for k in range(n)), "mean_1_9",
                     *(f"std_{k}" for k in range(n)), *(f"eval_{k}" for k in range(n))])
    for m in args.methods:
        mean, std = exp[m].mean(0), exp[m].std(0)
        evals = [f"{v:.3f}" for v in ev[m].mean(0)] if m.startswith("ppo") else [""] * n
        writer.writerow([m, LABELS.get(m, m), len(exp[m]), *(f"{v:.3f}" for v in mean),
                         f"{mean[1:].mean():.3f}", *(f"{v:.3f}" for v in std), *evals])
    atomic_write_text(path, buf.getvalue())
    print(f"\ntable written to {path}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=5, help="seeds 0..N-1 per method")
    p.add_argument("--intervals", type=int, default=10)
    p.add_argument("--jobs", type=int, default=2, help="runs in parallel")
    p.add_argument("--scenario", default="scenarios/single.toml")
    p.add_argument("--link", default="lcm", choices=["lcm", "core"],
                   help="lcm: the real plant process per run; core: in-process physics")
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    p.add_argument("--out", default="runs/quality", help="run directories go here")
    p.add_argument("--reuse", action="store_true", help="read finished runs instead of rerunning")
    p.add_argument("--judge", default="ppo-offline", choices=list(METHODS),
                   help="the method checks (a) and (b) judge (random: what failing looks like)")
    p.add_argument("--results", default=None, metavar="CSV",
                   help="also write the table (mean and std over seeds per interval) with its "
                        "provenance to this file (docs/results/quality_single.csv is the one "
                        "the docs render: scripts/render_results.py)")
    p.add_argument("extra", nargs="*",
                   help="extra options for the PPO methods' controllers (after --)")
    args = p.parse_args(argv)

    results: dict[str, dict[int, list[dict]]] = {m: {} for m in args.methods}
    seconds: dict[str, list[float]] = {m: [] for m in args.methods}
    failed: list[str] = []
    jobs = [(m, s) for s in range(args.seeds) for m in args.methods]
    with concurrent.futures.ThreadPoolExecutor(args.jobs) as pool:
        futures = [pool.submit(run_one, m, s, args) for m, s in jobs]
        for fut in concurrent.futures.as_completed(futures):
            m, s, rows, sec = fut.result()
            if not rows:
                failed.append(f"{m}/seed{s}")
                continue
            results[m][s] = rows
            seconds[m].append(sec)
            print(f"  done {m} seed {s} in {sec:.1f}s", file=sys.stderr, flush=True)

    def table(key: str) -> dict[str, np.ndarray]:
        out = {}
        for m, by_seed in results.items():
            vals = [[float(r[key]) if r[key] != "" else np.nan for r in rows]
                    for rows in by_seed.values()]
            # (seeds, intervals); a method without a finished run shows as nan (and fails)
            out[m] = np.array(vals) if vals else np.full((1, args.intervals), np.nan)
        return out

    exp, ev = table("reward_per_step"), table("eval_reward_per_step")
    n = args.intervals
    head = f"{'method':14s}" + "".join(f"{k:>7d}" for k in range(n)) + "   mean1-9  s/run"
    print(f"\nmean reward per step experienced, {args.seeds} seeds ({args.scenario})")
    print(head)
    for m in args.methods:
        mean = exp[m].mean(0)
        print(f"{m:14s}" + "".join(f"{v:7.3f}" for v in mean)
              + f"   {mean[1:].mean():7.3f}  {np.mean(seconds[m]) if seconds[m] else np.nan:5.1f}")
    print("\nstd over seeds")
    for m in args.methods:
        print(f"{m:14s}" + "".join(f"{v:7.3f}" for v in exp[m].std(0)))
    print("\ndeterministic evaluation (open iff p > 0.5)")
    for m in args.methods:
        if m.startswith("ppo"):
            print(f"{m:14s}" + "".join(f"{v:7.3f}" for v in ev[m].mean(0)))

    if failed:
        print(f"\nFAILED runs (left out of the means): {', '.join(failed)}")
    if args.results:
        write_results(Path(args.results), exp, ev, args)
    verdict = {True: "PASS", False: "FAIL"}
    checked: dict[str, bool] = {}  # check -> passed (a check fails if any of its lines fails)

    def record(name: str, passed: bool) -> None:
        checked[name] = checked.get(name, True) and passed

    print()
    j = args.judge
    if {"closed", j} <= set(args.methods):
        c, o = exp["closed"].mean(0), exp[j].mean(0)
        a = bool(o[0] >= BAR_INTERVAL_0 * c[0])
        print(f"(a) {j} interval 0: {o[0]:.3f} >= {BAR_INTERVAL_0:.2f} x all-closed {c[0]:.3f}"
              f" = {BAR_INTERVAL_0 * c[0]:.3f}: {verdict[a]} ({o[0] / c[0]:.3f} of all-closed)")
        record("a", a)
        if n > 1:
            b1 = bool(o[1] >= BAR_INTERVAL_1 * c[1])
            print(f"(b) {j} interval 1: {o[1]:.3f} >= {BAR_INTERVAL_1:.2f} x all-closed {c[1]:.3f}"
                  f" = {BAR_INTERVAL_1 * c[1]:.3f}: {verdict[b1]} (margin {o[1] - c[1]:+.3f})")
            record("b", b1)
        if n > 2:
            margin = o[2:] - c[2:]
            b2 = bool(np.all(margin > 0))
            worst = int(np.argmin(margin)) + 2
            print(f"(b) {j} beats all-closed in every interval 2-{n - 1} (margin > 0):"
                  f" smallest margin {margin.min():+.3f} in interval {worst}"
                  f" ({o[worst]:.3f} against {c[worst]:.3f}): {verdict[b2]}")
            record("b", b2)
    if {"ppo-online", "ppo-offline"} <= set(args.methods) and n > 1:
        on, off = exp["ppo-online"].mean(0)[1:].mean(), exp["ppo-offline"].mean(0)[1:].mean()
        cc = bool(off > on)
        print(f"(c) offline {off:.3f} > online-only {on:.3f} over intervals 1-{n - 1}: "
              f"{verdict[cc]}")
        record("c", cc)
    if {"random", "ppo-scratch"} <= set(args.methods) and n > 3:
        r, s = exp["random"].mean(0), exp["ppo-scratch"].mean(0)
        d = bool(s[3] > r[3])
        print(f"(d) from scratch {s[3]:.3f} > random {r[3]:.3f} in interval 3: {verdict[d]}")
        record("d", d)
    bad = [k for k, v in checked.items() if not v]
    skipped = [k for k in "abcd" if k not in checked]
    print(f"\nchecks {', '.join(checked) or 'none'}: "
          + (f"FAIL ({', '.join(bad)})" if bad else "all PASS")
          + (f"; not run (methods or intervals missing): {', '.join(skipped)}" if skipped else "")
          + ("; runs FAILED" if failed else ""))
    return 1 if bad or failed else 0


if __name__ == "__main__":
    sys.exit(main())
