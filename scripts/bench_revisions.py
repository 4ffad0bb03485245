#!/usr/bin/env python3
"""bench.py's figures for two checkouts of the project, side by side: is a
change (a refactor, say) no slower than the code before it?

    .venv/bin/python scripts/bench_revisions.py --before DIR --after DIR \\
        [--only GROUP...] [--rounds 3] [--results docs/results/bench_revisions.csv]

DIR is a checkout with its own ``.venv`` and ``build/`` (``bash
scripts/setup.sh`` there; ``git worktree add DIR REV`` makes one of any
revision). Each round runs ``scripts/bench.py --rounds 1 --json --only G`` of
each checkout for one group after the other, the order of the two checkouts
swapped every round, so both meet the same load: on a shared machine the load
drifts over minutes, and two whole bench runs one after the other measure the
drift as much as the code. Each figure is the median of its rounds per
checkout; ``after/before`` is their ratio. A figure with an aim (bench.py's
``aim``) is ``worse`` when the after checkout's median is more than
``--tolerance`` (default 10%) on the wrong side of the before one's; the
others are information. Prints the table; --results writes it as a result
file (provenance lines first).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _checkout(path: str) -> Path:
    root = Path(path).resolve()
    for need in (".venv/bin/python", "scripts/bench.py", "build"):
        if not (root / need).exists():
            raise SystemExit(f"bench_revisions: error: {root} has no {need} "
                             "(a checkout set up with `bash scripts/setup.sh`)")
    return root


def _revision(root: Path) -> str:
    done = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True,
                          text=True)
    dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    return (done.stdout.strip() or "unknown") + ("-dirty" if dirty else "")


def _bench(root: Path, group: str) -> list[dict]:
    done = subprocess.run([str(root / ".venv/bin/python"), "scripts/bench.py", "--rounds", "1",
                           "--json", "--only", group], cwd=root, capture_output=True, text=True)
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise SystemExit(f"bench_revisions: error: bench.py --only {group} failed in {root}: "
                         f"{tail}")
    return json.loads(done.stdout)


def _worse(aim: str, before: float, after: float, tolerance: float) -> bool:
    if aim == "-" or not before:
        return False
    op = aim.split()[0]
    return after > before * (1 + tolerance) if op == "<=" else after < before * (1 - tolerance)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    p.add_argument("--before", required=True, metavar="DIR", help="the checkout before the change")
    p.add_argument("--after", required=True, metavar="DIR", help="the checkout after the change")
    p.add_argument("--only", nargs="+", default=["lockstep", "learning", "robust", "startup",
                                                 "runs"], metavar="GROUP",
                   help="bench.py groups to compare (default: lockstep learning robust startup "
                        "runs, the Python side's)")
    p.add_argument("--rounds", type=int, default=3, help="rounds per checkout (default 3)")
    p.add_argument("--tolerance", type=float, default=0.10,
                   help="how much worse than before a figure with an aim may be (default 0.10)")
    p.add_argument("--results", type=Path, metavar="CSV", help="also write the table here")
    args = p.parse_args()
    if args.rounds < 1:
        p.error("--rounds must be >= 1")
    sides = {"before": _checkout(args.before), "after": _checkout(args.after)}
    values: dict[str, dict[str, list[float]]] = {"before": {}, "after": {}}
    meta: dict[str, tuple[str, str]] = {}  # figure -> (unit, aim), in bench.py's order
    start = time.monotonic()
    for k in range(args.rounds):
        order = ("before", "after") if k % 2 == 0 else ("after", "before")
        for group in args.only:
            for side in order:
                for f in _bench(sides[side], group):
                    meta.setdefault(f["name"], (f["unit"], f["aim"]))
                    values[side].setdefault(f["name"], []).append(f["value"])
            print(f"round {k + 1}/{args.rounds}: {group} done "
                  f"({time.monotonic() - start:.0f} s)", file=sys.stderr, flush=True)
    rows = []
    for name, (unit, aim) in meta.items():
        if name not in values["before"] or name not in values["after"]:
            continue  # a figure only one checkout's bench.py has
        b, a = (statistics.median(values[s][name]) for s in ("before", "after"))
        status = ("worse" if _worse(aim, b, a, args.tolerance) else "ok") if aim != "-" else "info"
        rows.append({"figure": f"`{name}`", "unit": unit, "aim": aim, "before": f"{b:.4g}",
                     "after": f"{a:.4g}", "after/before": f"{a / b:.3f}" if b else "-",
                     "status": status})
    for r in rows:
        print(f"{r['figure'][1:-1]:34s} {r['before']:>10s} {r['after']:>10s} "
              f"{r['after/before']:>7s} {r['unit']:8s} {r['aim']:>10s} {r['status']}")
    if args.results:
        sys.path.insert(0, str(HERE))
        from suite_results import write_result_file  # the one writer of result files

        provenance = (
            f"# what: scripts/bench.py's figures for two checkouts, the median of {args.rounds} "
            "rounds each, the two alternating group by group (scripts/bench_revisions.py)\n"
            f"# command: scripts/bench_revisions.py --before BEFORE --after AFTER --rounds "
            f"{args.rounds} --only {' '.join(args.only)}\n"
            f"# commit: before {_revision(sides['before'])}, after {_revision(sides['after'])}\n"
            f"# date: {time.strftime('%Y-%m-%d')}, wall time {time.monotonic() - start:.0f} s, "
            f"load average {os.getloadavg()[0]:.1f} at the end\n")
        write_result_file(args.results, provenance, rows)
    return 1 if any(r["status"] == "worse" for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
