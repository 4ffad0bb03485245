#!/usr/bin/env python3
"""Where the time of one controller run goes: cProfile over ``python -m
ftc.controller ARGS...``, summed into the phases of Algorithm 1.

Prints a table of seconds per phase (cProfile's own overhead inflates every
figure, by about 1.5x here, so compare phases and runs, not wall times):

  start-up            imports, argument parsing, building the agent
  prepare             pretraining (world model, policy) or loading them from the cache
  online: acting + plant   the policy choosing valves, plant steps, the reward
  online: PPO updates the clipped-surrogate updates every t_update steps
  evaluation          the deterministic evaluation episode of each interval
  refit               world-model refits on the interval's data
  offline PPO         PPO on the world model (model rollouts and updates)

Usage: .venv/bin/python scripts/profile_run.py [--top 0] -- --pretrain --link core
(the arguments after -- go to ftc.controller; --quiet and a temporary --out are added)
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import runpy
import sys
import tempfile

# function (file suffix, name) whose cumulative time makes up a phase
PHASES = {
    "run": ("control/run/runner.py", "run"),
    "prepare": ("control/agents/ppo.py", "prepare"),
    "online": ("control/run/runner.py", "online"),
    "online_updates": ("learning/rollout.py", "update"),
    "evaluation": ("control/run/runner.py", "evaluate"),
    "refit": ("learning/offline.py", "refit"),
    "offline_ppo": ("learning/rollout.py", "train_on_env"),
}


def cumulative(stats: pstats.Stats, suffix: str, name: str) -> float:
    total = 0.0
    for (path, _line, func), (_cc, _nc, _tt, ct, _callers) in stats.stats.items():  # type: ignore[attr-defined]
        if func == name and path.endswith(suffix):
            total += ct
    return total


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    parser.add_argument("--top", type=int, default=0,
                        help="also print the N functions with the most cumulative time")
    parser.add_argument("controller_args", nargs="*", help="arguments for ftc.controller")
    args = parser.parse_args()
    out = tempfile.mkdtemp(prefix="ftc-profile-")
    sys.argv = ["ftc.controller", *args.controller_args, "--quiet", "--out", out]
    profiler = cProfile.Profile()
    profiler.enable()
    try:
        runpy.run_module("ftc.controller", run_name="__main__")
    except SystemExit as stop:
        if stop.code not in (0, None):
            print(f"profile_run: the controller exited with {stop.code}", file=sys.stderr)
            return 1
    finally:
        profiler.disable()
    stats = pstats.Stats(profiler)
    total = stats.total_tt  # type: ignore[attr-defined]
    t = {k: cumulative(stats, *v) for k, v in PHASES.items()}
    # the online loop's updates run inside it; the offline phase's PPO inside the
    # offline phase (rollout.update is also called there: subtract it from online only)
    online_updates_in_offline = 0.0
    for (path, _l, func), (_cc, _nc, _tt, _ct, callers) in stats.stats.items():  # type: ignore[attr-defined]
        if func == "update" and path.endswith("learning/rollout.py"):
            for (cpath, _cl, cfunc), caller in callers.items():
                if cfunc == "train_on_env":
                    online_updates_in_offline += caller[3]
    updates_online = t["online_updates"] - online_updates_in_offline
    rows = [("start-up", total - t["run"]), ("prepare", t["prepare"]),
            ("online: acting + plant", t["online"] - updates_online),
            ("online: PPO updates", updates_online), ("evaluation", t["evaluation"]),
            ("refit", t["refit"]), ("offline PPO", t["offline_ppo"])]
    rest = total - sum(v for _, v in rows)  # checkpoints, metrics, the run's own loop
    print(f"{'phase':26s} {'seconds':>8s} {'share':>6s}")
    for name, sec in [*rows, ("other", rest)]:
        print(f"{name:26s} {sec:8.2f} {sec / total:6.0%}")
    print(f"{'total (profiled)':26s} {total:8.2f}")
    if args.top:
        stats.sort_stats("cumulative").print_stats(args.top)
    return 0


if __name__ == "__main__":
    sys.exit(main())
