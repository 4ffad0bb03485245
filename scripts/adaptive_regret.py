"""Where a policy loses against the adaptive student's teacher (docs/adaptive.md,
"Variants"): the policy flies one scenario from full tanks in the batched
pool for 10 intervals (``--intervals``), and at every ``--every``-th step the
teacher (the planner on the plant's true physics, told the stuck valves the
policy's own commands have shown, or every stuck valve, as the student was
trained) values all 64 settings; the policy's regret there is what its
setting loses against the teacher's best plan over the horizon (0 where it
chose as the teacher would).

Prints, and with ``--out`` writes as CSV, the policy's reward per step and
its summed regret per interval, and its summed regret by steps since the
tanks were last filled (when they run dry, and at each interval's start), in
bins of ``--bin`` steps: where in the life and where in each tank cycle the
policy departs from its teacher. The teacher is the one the checkpoint was
trained with (its config; a merged checkpoint's inputs must agree), unless
the teacher's flags say otherwise.

    python scripts/adaptive_regret.py SCENARIO.toml --checkpoint C.pt --seed 11
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import sys
from pathlib import Path

import numpy as np

from ftc.common.atomic import atomic_write_text
from ftc.common.errors import StorageError
from ftc.learning.history_policy import RECHECK_RULES, TrainingConfig

INTERVALS = 10
TEACHER = ("hold", "horizon", "extra_holds", "second_stage", "recheck", "recheck_horizon",
           "recheck_rule", "teacher_stuck")


def regrets(policy, teacher, scenario, seed: int, every: int, bin_steps: int,
            intervals: int = INTERVALS, seen_only: bool = True
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(reward per step (intervals,), summed regret per interval, summed regret
    per bin of steps since the tanks were last filled) of ``policy``: a
    HistoryPolicy, the teacher itself, a function of the levels (1, 6) ->
    valves (1, 6), or None for all valves closed. seen_only: the teacher is
    told the stuck valves the policy's commands have shown (else every one)."""
    from ftc.experiments.adaptive.dagger import settings_of
    from ftc.learning.history_policy import HistoryPolicy, HistoryWindow
    from ftc.learning.stuck import StuckMemory
    from ftc.plant.vector import FuelTransferVectorEnv

    env = FuelTransferVectorEnv(1, [scenario], plant_seed=[seed], autoreset="same_step",
                                threads=1, copy=False)
    levels, _ = env.reset()
    window = None
    if isinstance(policy, HistoryPolicy):
        window = HistoryWindow(1, policy.config.window, policy.config.stuck_memory)
        window.start(levels)
    seen = StuckMemory(1)
    steps = scenario.steps_per_interval
    reward, regret = np.zeros(intervals), np.zeros(intervals)
    phases = np.zeros(0)
    since = 0
    for t in range(intervals * steps):
        labelled = t % every == 0
        if labelled or policy is teacher:
            label, r = teacher.label_with_regrets([0], [scenario], np.array(
                [env.pool.operating_steps(0)]), levels, seen.stuck if seen_only else None)
        if window is not None:
            u = policy.act(window.features())
        elif policy is teacher:
            u = label
        elif policy is not None:
            u = np.asarray(policy(levels), np.int8)
        else:
            u = np.zeros((1, 6), np.int8)
        if labelled:
            lost = float(r[0, settings_of(u)[0]])
            regret[t // steps] += lost
            if since // bin_steps >= len(phases):
                phases = np.pad(phases, (0, since // bin_steps + 1 - len(phases)))
            phases[since // bin_steps] += lost
        levels, rew, terminated, truncated, info = env.step(u)
        reward[t // steps] += rew[0]
        done = terminated | truncated
        since = 0 if done[0] else since + 1
        if window is not None:
            window.push(levels, u, done, info["valves"])
        seen.see(u, info["valves"])
    env.close()
    return reward / steps, regret, phases


def _load_student(path: Path) -> tuple[dict, dict | None]:
    """(the checkpoint's policy record, the teacher's options it was trained
    with, None where it names none)."""
    from ftc.experiments.adaptive.cli import read_checkpoint

    try:
        record = read_checkpoint(path)
    except ValueError as e:
        raise SystemExit(f"adaptive_regret: error: {e}") from None
    configs = ([m.get("config") for m in record["merged_from"]] if "merged_from" in record
               else [record.get("config")])
    teachers = [{k: (list(c[k]) if isinstance(c[k], (list, tuple)) else c[k]) for k in TEACHER}
                for c in configs if isinstance(c, dict) and all(k in c for k in TEACHER)]
    if len(teachers) < len(configs):
        return record["policy"], None
    if any(t != teachers[0] for t in teachers):
        raise SystemExit(f"adaptive_regret: error: {path}: its students were trained with "
                         "different teachers; name the teacher with its flags")
    return record["policy"], teachers[0]


def main(argv: list[str] | None = None) -> int:
    defaults = dataclasses.asdict(TrainingConfig())
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scenario", type=Path, help="a scenario file (TOML)")
    p.add_argument("--checkpoint", type=Path,
                   help="the student's checkpoint (train's cache file or merge_students'); "
                        "needed with --policy student, and names the teacher otherwise")
    p.add_argument("--policy", choices=("student", "teacher", "closed"), default="student",
                   help="what flies: the student, the teacher itself (its regret is 0) or "
                        "all valves closed (default student)")
    p.add_argument("--seed", type=int, default=0, help="the plant's seed (default 0)")
    p.add_argument("--intervals", type=int, default=INTERVALS,
                   help=f"the scenario's intervals flown (default {INTERVALS})")
    p.add_argument("--every", type=int, default=2,
                   help="the teacher values every this many steps (default 2)")
    p.add_argument("--bin", type=int, default=10,
                   help="steps since the tanks were last filled, per bin (default 10)")
    teacher = p.add_argument_group(
        "the teacher", "default: the checkpoint's training config, else train's defaults")
    teacher.add_argument("--hold", type=int, help="steps its plans hold a setting")
    teacher.add_argument("--horizon", type=int, help="its planning horizon, steps")
    teacher.add_argument("--extra-holds", type=int, nargs="*", help="more hold lengths")
    teacher.add_argument("--second-stage", type=int, help="settings valued by two-stage plans")
    teacher.add_argument("--recheck", type=int, help="settings valued again over "
                         "--recheck-horizon")
    teacher.add_argument("--recheck-horizon", type=int, help="the recheck's horizon")
    teacher.add_argument("--recheck-rule", choices=RECHECK_RULES,
                         help="what a rechecked plan does after its hold")
    teacher.add_argument("--teacher-stuck", choices=("seen", "all"),
                         help="the stuck valves it is told: those the policy's commands "
                              "showed, or all")
    p.add_argument("--out", type=Path, help="write the figures as CSV here")
    a = p.parse_args(argv)
    if min(a.every, a.bin, a.intervals) < 1:
        p.error(f"--every, --bin and --intervals must be >= 1, got {a.every}, {a.bin} "
                f"and {a.intervals}")
    if a.seed < 0:
        p.error(f"--seed must be >= 0, got {a.seed}")
    if a.policy == "student" and a.checkpoint is None:
        p.error("--policy student needs --checkpoint")
    if not a.scenario.is_file():
        p.error(f"{a.scenario}: no such file")
    if a.out is not None and not a.out.parent.is_dir():
        p.error(f"--out {a.out}: no directory {a.out.parent}")

    import torch

    from ftc import _core
    from ftc.control.planning.physics.teacher import PoolTeacher
    from ftc.learning.history_policy import HistoryPolicy

    torch.set_num_threads(1)
    try:
        scenario = _core.load_scenario(str(a.scenario))
    except Exception as e:  # the parser names the file, line and key
        raise SystemExit(f"adaptive_regret: error: {e}") from None
    record, trained = _load_student(a.checkpoint) if a.checkpoint else (None, None)
    options = {k: (trained or defaults)[k] for k in TEACHER}
    options.update({k: getattr(a, k) for k in TEACHER if getattr(a, k) is not None})
    if not options["recheck"] and a.recheck_rule is None:  # as train's --recheck 0 alone
        options["recheck_rule"] = "closed"
    if min(options["hold"], options["horizon"], options["recheck_horizon"]) < 1:
        p.error("--hold, --horizon and --recheck-horizon must be >= 1")
    try:
        planner = PoolTeacher(options["hold"], options["horizon"],
                              extra_holds=tuple(options["extra_holds"]),
                              second_stage=options["second_stage"], recheck=options["recheck"],
                              recheck_horizon=options["recheck_horizon"],
                              recheck_rule=options["recheck_rule"])
    except ValueError as e:
        raise SystemExit(f"adaptive_regret: error: the teacher: {e}") from None
    policy = {"closed": None, "teacher": planner}.get(a.policy)
    if a.policy == "student":
        try:
            policy = HistoryPolicy.from_record(record)
        except (KeyError, ValueError, RuntimeError) as e:
            raise SystemExit(f"adaptive_regret: error: {a.checkpoint}: not a student: "
                             f"{type(e).__name__}: {e}") from None
    reward, regret, phases = regrets(policy, planner, scenario, a.seed, a.every, a.bin,
                                     a.intervals, options["teacher_stuck"] == "seen")
    print(f"adaptive_regret: {a.policy} on {a.scenario.stem}, plant seed {a.seed}, valued "
          f"every {a.every} steps by the teacher {options}")
    print("interval  reward/step  regret")
    for k in range(a.intervals):
        print(f"{k:8d}  {reward[k]:11.3f}  {regret[k]:6.2f}")
    print("steps since filled  regret")
    for k, v in enumerate(phases):
        print(f"{k * a.bin:6d}-{(k + 1) * a.bin - 1:<11d}  {v:6.2f}")
    if a.out:
        text = io.StringIO()
        text.write("# command: python scripts/adaptive_regret.py "
                   f"{' '.join(sys.argv[1:] if argv is None else argv)}\n")
        w = csv.writer(text, lineterminator="\n")
        w.writerow(["kind", "index", "reward_per_step", "regret"])
        w.writerows(["interval", k, round(reward[k], 4), round(regret[k], 4)]
                    for k in range(a.intervals))
        w.writerows(["since_filled", k * a.bin, "", round(v, 4)] for k, v in enumerate(phases))
        try:
            atomic_write_text(a.out, text.getvalue())
        except (OSError, StorageError) as e:
            raise SystemExit(f"adaptive_regret: error: cannot write {a.out}: {e}") from None
    return 0


if __name__ == "__main__":
    sys.exit(main())
