"""Where a policy loses against the adaptive student's teacher (docs/adaptive.md,
"Variants"): the policy flies one scenario from full tanks in the batched
pool for 10 intervals of 512 steps (``--intervals``), and at every ``--every``-th step the
teacher (the planner on the plant's true physics, told the stuck valves the
policy's own commands have shown, as in training) values all 64 settings;
the policy's regret there is what its setting loses against the teacher's
best plan over the horizon (0 where it chose as the teacher would).

Prints, and with ``--out`` writes as CSV, the policy's reward per step and
its summed regret per interval, and its summed regret by steps since the
last refill (the plant refills its tanks when they run dry), in bins of
``--bin`` steps: where in the life and where in each tank cycle the policy
departs from its teacher.

    python scripts/adaptive_regret.py SCENARIO.toml --checkpoint C.pt --seed 11 \\
        --recheck 4 --recheck-horizon 30 --recheck-rule balance
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

from ftc.learning.history_policy import TrainingConfig

INTERVALS, STEPS = 10, 512


def regrets(policy, teacher, scenario, seed: int, every: int, bin_steps: int,
            intervals: int = INTERVALS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(reward per step (intervals,), summed regret per interval, summed regret
    per bin of steps since the last refill) of ``policy`` (a HistoryPolicy,
    the PoolTeacher itself, or None for all valves closed)."""
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
    reward, regret = np.zeros(intervals), np.zeros(intervals)
    by_phase: dict[int, float] = {}
    since = 0
    bits = 1 << np.arange(6)
    for t in range(intervals * STEPS):
        labelled = t % every == 0
        if labelled or policy is teacher:
            label, r = teacher.label_with_regrets([0], [scenario], np.array(
                [env.pool.operating_steps(0)]), levels, seen.stuck)
        if window is not None:
            u = policy.act(window.features())
        elif policy is teacher:
            u = label
        else:
            u = np.zeros((1, 6), np.int8)
        if labelled:
            lost = float(r[0, int(u[0] @ bits)])
            regret[t // STEPS] += lost
            by_phase[since // bin_steps] = by_phase.get(since // bin_steps, 0.0) + lost
        levels, rew, terminated, truncated, info = env.step(u)
        reward[t // STEPS] += rew[0]
        done = terminated | truncated
        since = 0 if done[0] else since + 1
        if window is not None:
            window.push(levels, u, done, info["valves"])
        seen.see(u, info["valves"])
    env.close()
    phases = np.zeros(max(by_phase) + 1 if by_phase else 0)
    for k, v in by_phase.items():
        phases[k] = v
    return reward / STEPS, regret, phases


def main(argv: list[str] | None = None) -> int:
    defaults = TrainingConfig()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scenario", type=Path, help="a scenario file (TOML)")
    p.add_argument("--checkpoint", type=Path,
                   help="the student's checkpoint (train's cache file or merge_students'); "
                        "needed with --policy student")
    p.add_argument("--policy", choices=("student", "teacher", "closed"), default="student",
                   help="what flies: the student, the teacher itself (its regret is 0) or "
                        "all valves closed (default student)")
    p.add_argument("--seed", type=int, default=0, help="the plant's seed (default 0)")
    p.add_argument("--every", type=int, default=2,
                   help="the teacher values every this many steps (default 2)")
    p.add_argument("--intervals", type=int, default=INTERVALS,
                   help=f"intervals of {STEPS} steps flown (default {INTERVALS})")
    p.add_argument("--bin", type=int, default=10,
                   help="steps since the last refill per bin (default 10)")
    p.add_argument("--hold", type=int, default=defaults.hold)
    p.add_argument("--horizon", type=int, default=defaults.horizon)
    p.add_argument("--extra-holds", type=int, nargs="*", default=list(defaults.extra_holds))
    p.add_argument("--second-stage", type=int, default=defaults.second_stage)
    p.add_argument("--recheck", type=int, default=defaults.recheck)
    p.add_argument("--recheck-horizon", type=int, default=defaults.recheck_horizon)
    p.add_argument("--recheck-rule", default=defaults.recheck_rule)
    p.add_argument("--out", type=Path, help="write the figures as CSV here")
    a = p.parse_args(argv)
    if min(a.every, a.bin, a.intervals) < 1:
        p.error(f"--every, --bin and --intervals must be >= 1, got {a.every}, {a.bin} "
                f"and {a.intervals}")
    if a.policy == "student" and a.checkpoint is None:
        p.error("--policy student needs --checkpoint")
    if not a.scenario.is_file():
        p.error(f"{a.scenario}: no such file")

    import torch

    from ftc import _core
    from ftc.control.planning.physics.teacher import PoolTeacher
    from ftc.learning.history_policy import HistoryPolicy

    torch.set_num_threads(1)
    try:
        scenario = _core.load_scenario(str(a.scenario))
    except Exception as e:  # the parser names the file, line and key
        raise SystemExit(f"adaptive_regret: error: {e}") from None
    try:
        teacher = PoolTeacher(a.hold, a.horizon, extra_holds=tuple(a.extra_holds),
                              second_stage=a.second_stage, recheck=a.recheck, recheck_horizon=a.recheck_horizon,
                              recheck_rule=a.recheck_rule)
    except ValueError as e:
        raise SystemExit(f"adaptive_regret: error: the teacher: {e}") from None
    policy = None if a.policy == "closed" else teacher
    if a.policy == "student":
        try:
            policy = HistoryPolicy.from_record(
                torch.load(a.checkpoint, weights_only=True)["policy"])
        except Exception as e:  # torch.load raises many kinds on a corrupt file
            raise SystemExit(f"adaptive_regret: error: cannot read {a.checkpoint}: "
                             f"{type(e).__name__}: {e}") from None
    reward, regret, phases = regrets(policy, teacher, scenario, a.seed, a.every, a.bin,
                                     a.intervals)
    print(f"adaptive_regret: {a.policy} on {a.scenario.stem}, plant seed {a.seed}, "
          f"teacher every {a.every} steps")
    print("interval  reward/step  regret")
    for k in range(a.intervals):
        print(f"{k:8d}  {reward[k]:11.3f}  {regret[k]:6.2f}")
    print("steps since refill  regret")
    for k, v in enumerate(phases):
        print(f"{k * a.bin:6d}-{(k + 1) * a.bin - 1:<11d}  {v:6.2f}")
    if a.out:
        rows = ([{"kind": "interval", "index": k, "reward_per_step": round(reward[k], 4),
                  "regret": round(regret[k], 4)} for k in range(a.intervals)]
                + [{"kind": "since_refill", "index": k * a.bin, "reward_per_step": "",
                    "regret": round(v, 4)} for k, v in enumerate(phases)])
        tmp = a.out.with_name(a.out.name + ".tmp")
        try:
            with open(tmp, "w", newline="") as f:
                f.write(f"# command: python scripts/adaptive_regret.py "
                        f"{' '.join(sys.argv[1:] if argv is None else argv)}\n")
                w = csv.DictWriter(f, ["kind", "index", "reward_per_step", "regret"])
                w.writeheader()
                w.writerows(rows)
            tmp.replace(a.out)
        except OSError as e:
            tmp.unlink(missing_ok=True)
            raise SystemExit(f"adaptive_regret: error: cannot write {a.out}: {e}") from None
    return 0


if __name__ == "__main__":
    sys.exit(main())
