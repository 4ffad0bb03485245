"""adaptive-policy with and without its online fine-tune (docs/adaptive.md,
"Online adaptation"), flown by the real runner: each (scenario, seed, variant)
one ``python -m ftc.controller --method adaptive-policy --link core`` run of
10 x 512 steps, scored per scenario as ``ftc.experiments.adaptive evaluate``
scores (intervals 1-9 against the shipped reference and closed rewards; the
held-out set's from a benchmark's results.csv).

    python scripts/adaptive_online.py --checkpoint /tmp/p38/joint5.pt \\
        --heldout-results /tmp/p38/heldout-results.csv --seeds 0 1 2 \\
        --out docs/results/adaptive_online.csv

Runs go to --work (kept: a finished run's metrics.csv is reused, so an
interrupted measurement resumes). The variants: "off" (the default method)
and "on" (``--fine-tune``, its defaults, or the --fine-tune-args given).
Exit codes: 0 done, 2 bad input (one line), 1 a run failed.
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ftc.experiments.adaptive import evaluate
from ftc.experiments.adaptive.summary import write_result

SUITE = ["single", "multiple", "random-05", "random-10", "random-17"]
CHECK = ["abrupt", "deadpump", "unseen-continuous", "unseen-noise"]


def rewards_of(metrics: Path) -> tuple[np.ndarray, float | None]:
    """(reward per step of each interval, the share of the states the fine-tune
    rated that it corrected, None without it), from a run's metrics.csv."""
    with open(metrics, newline="") as f:
        rows = sorted(csv.DictReader(f), key=lambda r: int(r["interval"]))
    rated = sum(int(r.get("fine_tune_states") or 0) for r in rows)
    corrected = sum(int(r.get("fine_tune_corrected") or 0) for r in rows)
    return (np.array([float(r["reward_per_step"]) for r in rows]),
            corrected / rated if rated else None)


def summary(rows: list[dict]) -> list[dict]:
    """Per (variant, set): runs, mean score, worst scenario (its mean over seeds),
    scenarios below 0.60, the share of rated states corrected."""
    out = []
    for variant in dict.fromkeys(r["fine_tune"] for r in rows):
        for which in dict.fromkeys(r["set"] for r in rows):
            cells = [r for r in rows if r["fine_tune"] == variant and r["set"] == which]
            if not cells:
                continue
            per: dict[str, list[float]] = {}
            for r in cells:
                per.setdefault(r["scenario"], []).append(r["score"])
            means = {k: float(np.mean(v)) for k, v in per.items()}
            worst = min(means, key=means.get)
            shares = [r["corrected"] for r in cells if r["corrected"] != ""]
            out.append({"fine_tune": variant, "set": which, "runs": len(cells),
                        "mean score": round(float(np.mean([r["score"] for r in cells])), 3),
                        "worst scenario": f"{worst} ({means[worst]:.3f})",
                        "scenarios below 0.60": sum(v < 0.6 for v in means.values()),
                        "states corrected": f"{np.mean(shares):.3f}" if shares else ""})
    return out


def run(cell: Path, scenario: Path, seed: int, checkpoint: str, extra: list[str]) -> Path:
    metrics = cell / "metrics.csv"
    if (cell / "done").is_file():
        return metrics
    cmd = [sys.executable, "-m", "ftc.controller", "--method", "adaptive-policy",
           "--checkpoint", checkpoint, "--link", "core", "--scenario", str(scenario),
           "--seed", str(seed), "--intervals", "10", "--steps-per-interval", "512",
           "--out", str(cell), "--overwrite", "--quiet", *extra]
    t0 = time.monotonic()
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or [""])[-1]  # the run's one-line error
        raise RuntimeError(f"{scenario.stem} seed {seed}: exit {done.returncode}: {last} "
                           f"(the run: {cell})")
    (cell / "done").write_text(f"{time.monotonic() - t0:.1f}\n")
    return metrics


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--heldout-results", default="", help="benchmark results.csv with reference "
                   "and closed on scenarios/heldout/ (without it the held-out set is skipped)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--suite-seeds", type=int, nargs="+", default=None,
                   help="the suite's seeds (default: --seeds)")
    p.add_argument("--heldout-seeds", type=int, nargs="+", default=[0])
    p.add_argument("--sets", nargs="+", default=["heldout", "check", "suite"],
                   choices=["heldout", "check", "suite"])
    p.add_argument("--fine-tune-args", default="", help="options of the 'on' variant beside "
                   "--fine-tune (one string)")
    p.add_argument("--work", default="runs/adaptive-online")
    p.add_argument("--out", required=True, help="per-run scores (CSV)")
    p.add_argument("--summary", default="", help="per variant and set (CSV)")
    a = p.parse_args()
    for given in (a.checkpoint, a.heldout_results):
        if given and not Path(given).is_file():
            print(f"adaptive_online: error: {given}: no such file", file=sys.stderr)
            return 2
    variants = {"off": [], "on": ["--fine-tune", *a.fine_tune_args.split()]}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for which in a.sets:
            if which == "heldout" and not a.heldout_results:
                continue
            files = evaluate.scenario_files(which, Path(tmp))
            names = {"suite": SUITE, "check": CHECK}.get(which, list(files))
            seeds = {"heldout": a.heldout_seeds, "suite": a.suite_seeds or a.seeds}.get(
                which, a.seeds)
            for seed in seeds:
                ref = evaluate.reference_rewards(which, names, seed, Path(a.heldout_results)
                                                 if which == "heldout" else None)
                for variant, extra in variants.items():
                    r, shares = [], []
                    for name in names:
                        cell = Path(a.work) / variant / which / name / f"s{seed}"
                        got = rewards_of(run(cell, files[name], seed, a.checkpoint, extra))
                        r.append(got[0])
                        shares.append(got[1])
                        print(f"adaptive_online: {variant} {which} {name} s{seed}: "
                              f"{(cell / 'done').read_text().strip()} s", flush=True)
                    sc = evaluate.scores(np.array(r), ref["reference"], ref["closed"])
                    for i, name in enumerate(names):
                        rows.append({"fine_tune": variant, "set": which, "scenario": name,
                                     "seed": seed, "score": round(float(sc[i]), 4),
                                     "reward_per_step": round(float(r[i][1:].mean()), 4),
                                     "corrected": "" if shares[i] is None else
                                     round(shares[i], 4)})
    write_result(a.out, "adaptive-policy without (off) and with (on) its online fine-tune, flown "
                 f"by the real runner (--link core, 10 x 512 steps) with {a.checkpoint}; per-"
                 "scenario normalized score (intervals 1-9 against the reference and closed)",
                 rows, command="python scripts/adaptive_online.py")
    summed = summary(rows)
    if a.summary:
        write_result(a.summary, "adaptive-policy without (off) and with (on) its online "
                     f"fine-tune, per set, from {a.out}: runs, mean and worst per-scenario "
                     "score, scenarios below 0.60, share of the states rated after each "
                     "interval that the learned model corrected", summed,
                     command="python scripts/adaptive_online.py")
    for s in summed:
        print(f"adaptive_online: {s['fine_tune']}: {s['set']}: mean {s['mean score']:.3f} over "
              f"{s['runs']} runs, worst {s['worst scenario']}, corrected {s['states corrected']}")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    try:
        sys.exit(main())
    except RuntimeError as e:
        print(f"adaptive_online: error: {e}", file=sys.stderr)
        sys.exit(1)
