"""Read a recorded LCM log of a plant run back into a trajectory.

    python -m ftc.replay runs/NAME/.../plant.lcmlog [--episode N] [--figure out.png] [--fit-model]

The log is what ``lcm-logger`` recorded of one plant's traffic (the
experiments record one per run). Only ``<prefix>STATE`` messages are used: they
carry the levels, the valves applied and the episode bookkeeping, so the
trajectory, the episodes and the rewards (recomputed with :mod:`ftc.reward`
from the published levels, as the controller computed them) follow from the
log alone. A plant re-sends its last state when a command is retried or a
HELLO arrives; such repeats are counted and dropped, keyed by (episode, step).
A message on that channel that is not a plant state (another process's
traffic) is counted and skipped, with a warning naming the first.

A truncated or corrupt log is an error naming the file and the byte offset
where reading stopped (exit code 2).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from ftc.common.cli import OneLineParser, at_least, checked, out_dir_problem
from ftc.common.errors import RunError
from ftc.experiments import figures
from ftc.learning.transitions import Transitions
from ftc.plant.log import LogError, Trajectory, control_episode, read_log, write_trajectory_csv


def summary(traj: Trajectory) -> str:
    """A human-readable summary: episodes, steps, per-interval mean rewards."""
    operating = traj.episodes(evaluation=False)
    evaluation = traj.episodes(evaluation=True)
    lines = [f"channel {traj.channel}: {traj.events} log events, {len(traj)} plant steps "
             f"({traj.repeats} repeated states dropped)",
             *([f"WARNING: {traj.missing} plant states are missing from the log (sequence "
                "gaps): rewards below cover only what was recorded"] if traj.missing else []),
             *([f"WARNING: {traj.undecodable} messages on {traj.channel} are not plant states "
                f"(skipped; the first: {traj.first_undecodable})"] if traj.undecodable else []),
             f"episodes: {len(operating)} operating, {len(evaluation)} evaluation; "
             f"terminal {int(traj.terminal.sum())}, truncated {int(traj.truncated.sum())}",
             f"mean reward per step over all operating steps: "
             f"{float(np.mean(traj.reward[~traj.evaluation])) if (~traj.evaluation).any() else float('nan'):.4f}",
             "interval  steps  reward/step  eval steps  eval reward/step"]
    exp, ev = traj.reward_per_interval(False), traj.reward_per_interval(True)
    counts = {k: int(((traj.interval() == k) & ~traj.evaluation).sum()) for k in exp}
    ecounts = {k: int(((traj.interval() == k) & traj.evaluation).sum()) for k in ev}
    for k in sorted(set(exp) | set(ev)):
        lines.append(f"{k:8d}  {counts.get(k, 0):5d}  {exp.get(k, float('nan')):11.4f}  "
                     f"{ecounts.get(k, 0):10d}  {ev.get(k, float('nan')):16.4f}")
    return "\n".join(lines)


def fit_model_from_log(traj: Trajectory, seed: int = 0) -> dict:
    """Fit the controller's default world model on the log's transitions.

    Transitions are consecutive states within an episode (the initial state
    included). Returns {"transitions": n, "r2": cross-validated R^2}.
    """
    xs, us, xn, eps = [], [], [], []
    for ep in traj.episodes():
        rows = traj.select(traj.episode == ep)
        prev, prev_step = traj.initial_level.get(ep), 0
        for i in range(len(rows)):
            if prev is not None and rows.step[i] == prev_step + 1:
                xs.append(prev)
                us.append(rows.valves[i])
                xn.append(rows.level[i])
                eps.append(ep)
            prev, prev_step = rows.level[i], rows.step[i]
    if len(set(eps)) < 3:
        raise LogError(f"only {len(xs)} transitions in {len(set(eps))} episodes in the log; "
                       "fitting needs at least 3 episodes (3-fold cross-validation)")
    from ftc.learning.world_model import WorldModelConfig, cross_validated_r2  # torch: on use

    data = Transitions(np.array(xs), np.array(us), np.array(xn), np.array(eps))
    r2 = cross_validated_r2(data, WorldModelConfig(seed=seed), folds=3)
    return {"transitions": len(xs), "episodes": len(set(eps)), "r2": float(r2)}


FIGURE_FORMATS = ("png", "svg")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="python -m ftc.replay", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("log", type=checked(Path, nonempty=True),
                        help="LCM log file written by lcm-logger")
    parser.add_argument("--channel", type=checked(str, nonempty=True), default=None,
                        help="STATE channel to read (default: the only *STATE channel)")
    parser.add_argument("--episode", type=checked(int, at_least(0, 2**63 - 1)), default=None,
                        help="episode to draw (default: the last complete one at the highest "
                             "degradation, preferring deterministic evaluation episodes)")
    parser.add_argument("--figure", type=checked(Path, nonempty=True), default=None,
                        help="draw the tank-control figure for the episode (PNG; SVG too if "
                             "the name ends in .svg)")
    parser.add_argument("--csv", type=checked(Path, nonempty=True), default=None,
                        help="write the whole trajectory as CSV")
    parser.add_argument("--fit-model", action="store_true",
                        help="fit the world model on the log's transitions and print its CV R^2")
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The options, checked before the log is read: the outputs must be writable
    files (not directories) and the figure's format one that is drawn."""
    parser = build_parser()
    args = parser.parse_args(argv)
    for name in ("figure", "csv"):
        path = getattr(args, name)
        if path is None:
            continue
        if path.is_dir():
            parser.error(f"--{name} {path}: is a directory (give the file to write)")
        problem = out_dir_problem(path.resolve().parent)
        if problem:
            parser.error(f"--{name} {path}: cannot write there ({problem})")
    if args.figure is not None and args.figure.suffix.lstrip(".") not in ("", *FIGURE_FORMATS):
        parser.error(f"--figure {args.figure}: the name must end in .png or .svg")
    return args


def main(argv: list[str] | None = None) -> int:
    """Exit codes: 2 a bad option (checked before the log is read, one line
    naming the flag) or a truncated/corrupt log; 5 an output could not be
    written (disk full): one line naming it."""
    args = parse_args(argv)
    try:
        traj = read_log(args.log, args.channel)
        print(summary(traj))
        if args.csv:
            write_trajectory_csv(traj, args.csv)
            print(f"wrote {args.csv}")
        if args.figure or args.episode is not None:
            episode = args.episode if args.episode is not None else control_episode(traj)
            rows = traj.episode_rows(episode)
            print(f"episode {episode}: {len(rows)} steps at age {rows.age[0]:g}"
                  f"{' (evaluation)' if rows.evaluation[0] else ''}, "
                  f"mean reward per step {float(np.mean(rows.reward)):.4f}")
            if args.figure:
                with tempfile.TemporaryDirectory() as tmp:
                    csv_path = Path(tmp) / "episode.csv"
                    write_trajectory_csv(rows, csv_path)
                    figures.tank_control([(f"{args.log.name}, episode {episode}", csv_path)],
                                         args.figure.with_suffix(""),
                                         formats=(args.figure.suffix.lstrip(".") or "png",))
                print(f"wrote {args.figure}")
        if args.fit_model:
            fit = fit_model_from_log(traj)
            print(f"world model fitted on {fit['transitions']} transitions: "
                  f"3-fold CV R^2 = {fit['r2']:.4f}")
    except LogError as e:
        print(f"ftc.replay: error: {e}", file=sys.stderr)
        return 2
    except RunError as e:  # StorageError: an output could not be written (exit 5)
        print(f"ftc.replay: error: {e}", file=sys.stderr)
        return e.exit_code
    return 0


if __name__ == "__main__":
    sys.exit(main())
