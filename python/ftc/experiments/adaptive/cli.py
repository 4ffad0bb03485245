"""The adaptive policy's commands (docs/adaptive.md):

    python -m ftc.experiments.adaptive train      # build the checkpoint (cached; a hit is instant)
    python -m ftc.experiments.adaptive evaluate --out docs/results/adaptive.csv \\
        --curve docs/results/adaptive_curve.csv --figure docs/figures/adaptive_curve.png

``train`` runs DAgger (:mod:`ftc.experiments.adaptive.dagger`) on the
distribution of ``scenarios/training/adaptive.toml`` and stores the student
under a key of its training config, that file's text and the code
(:func:`ftc.learning.history_policy.checkpoint_file`), which the registered
method ``adaptive-policy`` loads; ``evaluate`` scores a checkpoint per
scenario on the suite and on the check set, and every iteration's student on
the suite for the learning curve.

Exit codes: 0 done, 2 bad input (one line), 5 a file that could not be written.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from ftc.common.atomic import atomic_torch_save
from ftc.common.constants import NUM_TANKS
from ftc.common.errors import EXIT_STORAGE, EXIT_USAGE
from ftc.control.agents.balance import balance_valves
from ftc.control.agents.mpc_config import MPCConfig
from ftc.control.planning.physics.teacher import PoolTeacher
from ftc.experiments.adaptive import dagger, distribution, evaluate
from ftc.experiments.adaptive.summary import cmd_summarize, write_result
from ftc.learning.history_policy import HistoryPolicy, TrainingConfig, checkpoint_file

DEFAULT_CACHE = "~/.cache/ftc/adaptive"


OPTION_HELP = {  # TrainingConfig's fields, as its docstring describes them
    "iterations": "DAgger iterations",
    "envs": "plants drawn and run for their life per iteration",
    "life_intervals": "intervals of 512 steps each plant runs (<= the distribution's life)",
    "label_fraction": "share of the student-driven states the teacher labels",
    "dagger": "false: behaviour cloning (the teacher drives and labels every plant)",
    "epochs": "passes over the data set after each iteration",
    "batch": "minibatch size",
    "lr": "Adam's learning rate",
    "max_samples": "labelled windows kept (the newest)",
    "window": "steps of levels and valves the student reads",
    "hidden": "the student's hidden layer widths",
    "head": "joint: 64 logits, one per valve setting; valves: six, one per valve",
    "inputs": "window: the first layer reads the scaled window; rates: the newest levels and "
              "their changes, standardized while training (folded into the weights after)",
    "regret": "weight of the expected regret under the student's softmax (joint head)",
    "hold": "the teacher's plans hold a setting this many steps, then all closed",
    "horizon": "the teacher's planning horizon, steps",
    "extra_holds": "more hold lengths the teacher's plans try, each setting valued by the "
                   "best of its plans (the flag with no value: none, --hold alone)",
    "second_stage": "the teacher also values this many of its best settings by their "
                    "two-stage plans: held --hold steps, then any one setting held to the "
                    "horizon (0: none; nothing where --hold >= --horizon; 4 costs about twice "
                    "the teacher's CPU)",
    "recheck": "the teacher values this many of its best settings again over "
               "--recheck-horizon steps, each by its best plan held --hold or any "
               "--extra-holds steps, then continued as --recheck-rule says, and labels the "
               "best of them, so that a choice whose gain outlasts --horizon is settled by it "
               "(0: none)",
    "recheck_horizon": "the horizon of --recheck, longer than --horizon, cut at the "
                       "interval's end (nothing is rechecked where the cut leaves it no "
                       "longer than --horizon)",
    "recheck_rule": "what a rechecked plan does after its hold: closed (every valve), "
                    "balance (the balance rule in closed loop to --recheck-horizon, a "
                    "continuation that keeps balancing, run in C++; its labels cost about three "
                    "times a closing teacher's) or best (each plan valued by the better of the "
                    "two, all closed always rechecked too); closed where --recheck is 0 unless "
                    "given",
    "seed": "draws, pool plants, initial weights and minibatches",
    "members": "students trained with seeds seed, seed+1, ... and flown as one network "
               "whose logits are their mean",
    "privileged": "weight of the privileged head's loss: a second head, in training only, "
                  "learns from the student's last hidden layer which valves are stuck "
                  "(0: none)",
    "privileged_params": "weight of the parameter head's loss: another head, in training only, "
                         "regresses from the student's last hidden layer the true degraded "
                         "parameters in force (each pump's capacity, each tank's conductance, "
                         "each engine's demand, as fractions of the healthy ones) (0: none)",
    "stuck_memory": "the student also reads which valves it has seen stuck: applied by the "
                    "plant otherwise than it commanded them (what the state message "
                    "publishes), remembered for the plant's life",
    "teacher_stuck": "which stuck valves the teacher plans with: all (every one from its "
                     "event on) or seen (those in the student's stuck memory, the others as "
                     "healthy)",
    "explore": "in the plants the student drives, the chance per step that a perturbation "
               "begins: a random valve setting held in place of the student's for 1 to "
               "--explore-hold steps, the states labelled as any other (0: none)",
    "explore_hold": "the longest perturbation of --explore, steps",
}


def _config_options(p: argparse.ArgumentParser) -> None:
    d = TrainingConfig()
    for f in dataclasses.fields(TrainingConfig):
        value = getattr(d, f.name)
        flag = "--" + f.name.replace("_", "-")
        if isinstance(value, bool):
            p.add_argument(flag, type=lambda s: s.lower() in ("1", "true", "yes"), default=value,
                           metavar="BOOL", help=f"{OPTION_HELP[f.name]} (default {value})")
        elif isinstance(value, tuple):
            # extra holds may be none (the flag alone); a network has a hidden layer
            p.add_argument(flag, type=int, nargs="*" if f.name == "extra_holds" else "+",
                           default=list(value),
                           help=f"{OPTION_HELP[f.name]} (default "
                                f"{' '.join(map(str, value)) or 'none'})")
        else:
            p.add_argument(flag, type=type(value),  # no rule given: config_of chooses
                           default=None if f.name == "recheck_rule" else value,
                           metavar="K" if f.name in ("second_stage", "recheck") else None,
                           help=f"{OPTION_HELP[f.name]} (default {value})")


def config_of(a: argparse.Namespace) -> TrainingConfig:
    values = {f.name: getattr(a, f.name) for f in dataclasses.fields(TrainingConfig)}
    values["hidden"], values["extra_holds"] = tuple(values["hidden"]), tuple(values["extra_holds"])
    if values["recheck_rule"] is None:  # --recheck 0 alone: no rechecked plan to continue
        values["recheck_rule"] = TrainingConfig.recheck_rule if values["recheck"] else "closed"
    for name in ("iterations", "envs", "life_intervals", "epochs", "batch", "max_samples",
                 "window", "hold", "horizon", "recheck_horizon"):
        if values[name] < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {values[name]}")
    for name in ("second_stage", "recheck"):
        if not 0 <= values[name] <= 2 ** NUM_TANKS:
            raise ValueError(f"--{name.replace('_', '-')} must be in [0, {2 ** NUM_TANKS}] "
                             f"(settings), got {values[name]}")
    if values["recheck"] and values["recheck_horizon"] <= values["horizon"]:
        raise ValueError(f"--recheck-horizon ({values['recheck_horizon']}) must be longer than "
                         f"--horizon ({values['horizon']}) with --recheck {values['recheck']} "
                         "(--recheck 0 turns the recheck off)")
    if not values["recheck"] and values["recheck_rule"] != "closed":
        raise ValueError(f"--recheck-rule {values['recheck_rule']} continues rechecked plans: "
                         "not with --recheck 0")
    if any(h < 1 for h in values["extra_holds"]):
        raise ValueError(f"--extra-holds must be >= 1 each, got {list(values['extra_holds'])}")
    if not 0.0 <= values["label_fraction"] <= 1.0 or not values["lr"] > 0:
        raise ValueError("--label-fraction must be in [0, 1] and --lr > 0")
    return TrainingConfig(**values)


def oracle_config(config: TrainingConfig) -> TrainingConfig:
    """``config`` with the teacher's planner made oracle-mpc's: each setting held
    H steps then all closed, over L (MPCConfig's defaults), and nothing more."""
    return dataclasses.replace(config, hold=MPCConfig.hold, horizon=MPCConfig.horizon,
                               extra_holds=(), second_stage=0, recheck=0, recheck_rule="closed")


def cmd_train(a: argparse.Namespace) -> int:
    dist = distribution.load(a.distribution)
    config = config_of(a)
    path = checkpoint_file(a.cache, config, dist.text)
    if path.is_file() and not a.force:
        print(f"adaptive: cached {path}")
        return 0
    if a.jobs < 1:
        raise ValueError(f"--jobs must be >= 1, got {a.jobs}")
    start = time.monotonic()
    record = dagger.train(dist, config, log=lambda line: print(line, flush=True), jobs=a.jobs)
    record["train_seconds"] = time.monotonic() - start
    record["load_average"] = os.getloadavg()
    try:
        atomic_torch_save(path, record)
    except OSError as e:
        print(f"adaptive: error: cannot write {path}: {e}", file=sys.stderr)
        return EXIT_STORAGE
    print(f"adaptive: trained in {record['train_seconds']:.0f} s, {path}")
    return 0


def read_checkpoint(path: Path) -> dict[str, Any]:
    """A checkpoint's record (train's or merge_students'); ValueError naming a bad file."""
    import torch

    try:
        record = torch.load(path, weights_only=True)
    except Exception as e:  # torch.load raises many kinds on a corrupt file
        raise ValueError(f"cannot read {path}: {type(e).__name__}: {e}") from None
    if not isinstance(record, dict) or "policy" not in record:
        raise ValueError(f"{path} is not an adaptive-policy checkpoint (no 'policy' record)")
    return record


def load_record(a: argparse.Namespace) -> tuple[dict[str, Any], Path]:
    if a.checkpoint:
        path = Path(a.checkpoint)
    else:
        path = checkpoint_file(a.cache, config_of(a), distribution.load(a.distribution).text)
    if not path.is_file():
        raise ValueError(f"no checkpoint at {path}: build it with "
                         f"`python -m ftc.experiments.adaptive train`")
    return read_checkpoint(path), path


def cmd_evaluate(a: argparse.Namespace) -> int:
    import torch

    torch.set_num_threads(1)
    if "heldout" in a.sets and a.heldout_results and not Path(a.heldout_results).is_file():
        raise ValueError(f"--heldout-results {a.heldout_results}: no such file")
    for f in a.heldout_scenarios:
        if not Path(f).is_file():
            raise ValueError(f"--heldout-scenarios {f}: no such file")
    if a.heldout_name in ("suite", "check") or not a.heldout_name:
        raise ValueError(f"--heldout-name {a.heldout_name!r}: another set's name, or empty")
    if a.policy != "student" and a.curve:
        raise ValueError(f"--curve is the student's learning curve: not with --policy {a.policy}")
    record: dict[str, Any] = {}
    if a.policy == "oracle-mpc":  # its planner, whatever the teacher's options say
        policy: Any = PoolTeacher.from_config(oracle_config(config_of(a)))
        what = (f"oracle-mpc's planner (each setting held {policy.planner.hold} steps "
                f"over {policy.horizon}, told every stuck valve)")
    elif a.policy == "teacher":  # the planner alone: no checkpoint
        # the teacher these options distil (config_of refuses holds or rechecks out of range)
        policy = PoolTeacher.from_config(config_of(a))
        holds = " or ".join(str(p.hold) for p in policy.planners)
        staged = (f", its {a.second_stage} best settings also held {a.hold} steps, then any "
                  "setting" if a.second_stage else "")
        if policy.recheck:
            rule = policy.recheck_rule
            staged += (f", its {policy.recheck} best valued again over "
                       f"{policy.recheck_horizon}"
                       + ("" if rule == "closed" else f" (then the {rule} rule)"))
        what = (f"teacher (the planner holding {holds} over {a.horizon}{staged}, told "
                + ("the stuck valves its commands showed)" if a.teacher_stuck == "seen"
                   else "every stuck valve)"))
    elif a.policy == "balance":
        policy, what = balance_rule, "balance (the rule)"
    else:
        record, path = load_record(a)
        if a.curve and not record.get("curve"):
            raise ValueError(f"--curve: {path} holds no learning curve (a checkpoint of "
                             "scripts/merge_students.py was not trained)")
        policy, what = HistoryPolicy.from_record(record["policy"]), f"student ({path.name})"
    rows = []
    for which in a.sets:
        if which == "heldout" and not a.heldout_results:
            raise ValueError("--sets heldout needs --heldout-results (a benchmark's results.csv "
                             "with reference and closed on scenarios/heldout/)")
        scored = evaluate.evaluate(policy, which, seeds=a.seeds,
                                   heldout=Path(a.heldout_results) if a.heldout_results else None,
                                   heldout_files=[Path(f) for f in a.heldout_scenarios] or None,
                                   teacher_stuck=a.teacher_stuck if a.policy == "teacher"
                                   else "all", per_interval=a.per_interval)
        rows += [{**r, "set": a.heldout_name} if which == "heldout" else r for r in scored]
    for which in (a.heldout_name if w == "heldout" else w for w in a.sets):
        defined = [r for r in rows if r["set"] == which and np.isfinite(r["score"])]
        undefined = sum(r["set"] == which for r in rows) - len(defined)
        note = (f"; {undefined} undefined (the reference earns what closed earns)"
                if undefined else "")
        if not defined:
            print(f"adaptive: {a.policy}: {which}: no defined score{note}")
            continue
        worst = min(defined, key=lambda r: r["score"])
        print(f"adaptive: {a.policy}: {which}: mean score "
              f"{np.mean([r['score'] for r in defined]):.3f} over {len(defined)} runs, worst "
              f"{worst['score']:.3f} ({worst['scenario']}, seed {worst['seed']}){note}")
    try:
        if a.out:
            write_result(a.out, f"{what}, per-scenario normalized score "
                         "(intervals 1-9 against the shipped reference and closed rewards) "
                         "in the batched pool, 10 x 512 steps",
                         [{**{k: round(v, 4) if k.startswith("reward") else v
                              for k, v in r.items()},
                           "score": round(r["score"], 4) if np.isfinite(r["score"]) else "",
                           "reference_gain_per_step": round(r["reference_gain_per_step"], 4)}
                          for r in rows])
        if a.curve:
            curve = learning_curve(record)
            write_result(a.curve, "adaptive-policy's learning curve: each DAgger iteration's "
                         f"student on the suite (seed 0); training {record['train_seconds']:.0f} s "
                         f"wall, load average at its end {record['load_average'][0]:.1f}", curve)
            if a.figure:
                evaluate.draw_curve(curve, Path(a.figure), record)
    except OSError as e:
        print(f"adaptive: error: cannot write: {e}", file=sys.stderr)
        return EXIT_STORAGE
    return 0


def balance_rule(levels: np.ndarray) -> np.ndarray:
    """The balance rule's valves (N, 6) for levels (N, 6) (ftc.control.agents.balance)."""
    return np.stack([balance_valves(x) for x in levels])


def learning_curve(record: dict[str, Any]) -> list[dict[str, Any]]:
    """Per iteration: env steps, teacher labels, wall seconds, and the student's
    mean and worst per-scenario score on the suite (seed 0)."""
    out = []
    for row, snap in zip(record["curve"], record["snapshots"]):
        policy = HistoryPolicy.from_record(snap)
        s = np.array([r["score"] for r in evaluate.evaluate(policy, "suite")])
        out.append({"member": row.get("member", 0), "iteration": row["iteration"],
                    "env_steps": row["env_steps"],
                    "teacher_labels": row["teacher_labels"], "seconds": row["seconds"],
                    "loss": round(row["loss"], 5),
                    "action_agreement": round(row["action_agreement"], 4),
                    "suite_mean_score": round(float(s.mean()), 4),
                    "suite_worst_score": round(float(s.min()), 4)})
        print(f"adaptive: curve: member {row.get('member', 0)} iteration {row['iteration']}  "
              f"{row['env_steps']} steps  "
              f"{row['seconds']:.0f} s  suite mean {s.mean():.3f}  worst {s.min():.3f}")
    return out


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m ftc.experiments.adaptive",
                                description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    summ = sub.add_parser("summarize", help="summarize evaluate's result files per set")
    summ.add_argument("results", nargs="+", help="[LABEL=]FILE: evaluate's --out files")
    summ.add_argument("--out", required=True, help="the summary (CSV)")
    summ.add_argument("--by-scenario", action="store_true",
                      help="a row per set and scenario instead: each policy's mean score "
                           "there (a column per label) and the reference's gain over closed "
                           "per step, which tells the scenarios where the score is ill-posed")
    summ.add_argument("--pool", action="append", default=[], metavar="NAME=SET,SET",
                      help="also a row per policy over these sets' scenarios together, "
                           "named NAME (e.g. unseen=sealed,sealed2): one mean and interval "
                           "over all their scenarios, tighter than any one set's; repeatable")
    summ.add_argument("--versus", default="", metavar="LABEL",
                      help="also each row's mean minus LABEL's on the same scenarios, with "
                           "its 95%% interval from the same bootstrap paired (both drawn on "
                           "the same scenarios): whether a difference outlasts the draw")
    for name, help_ in (("train", "build the checkpoint (a cached one is kept)"),
                        ("evaluate", "score a checkpoint per scenario; the learning curve")):
        s = sub.add_parser(name, help=help_)
        s.add_argument("--cache", default=DEFAULT_CACHE, help="checkpoint cache directory")
        s.add_argument("--distribution", default=str(distribution.DISTRIBUTION_FILE),
                       help="the training distribution's file")
        _config_options(s)
        if name == "train":
            s.add_argument("--force", action="store_true", help="train even if cached")
            s.add_argument("--jobs", type=int, default=_usable_cpus(),
                           help="members trained at once, each in a process of its own "
                                "with one torch thread; the weights are the same whatever "
                                "the number, and it is not part of the checkpoint's key "
                                "(default: the CPUs this process may use, %(default)s here)")
        else:
            s.add_argument("--checkpoint", default="", help="a checkpoint file (default: the "
                           "cached one of the training options)")
            s.add_argument("--sets", nargs="+", default=["suite", "check"],
                           choices=["suite", "check", "heldout"])
            s.add_argument("--heldout-results", default="", help=(
                "results.csv of a benchmark of reference and closed on the held-out "
                "scenarios (`python -m ftc.experiments benchmark --methods closed --scenarios "
                "...`: the reference runs beside it)"))
            s.add_argument("--heldout-scenarios", nargs="+", default=[], metavar="TOML",
                           help="the held-out set's scenario files (default: scenarios/heldout/"
                                "*.toml); faults of your own, never trained on")
            s.add_argument("--heldout-name", default="heldout",
                           help="the held-out set's name in the output (e.g. drawn)")
            s.add_argument("--seeds", type=int, nargs="+", default=[0])
            s.add_argument("--policy", default="student",
                           choices=["student", "teacher", "oracle-mpc", "balance"],
                           help="what to score: the checkpoint's student, the teacher (the "
                                "planner on the true physics with --hold, --horizon, "
                                "--extra-holds, --second-stage and --recheck, told the "
                                "stuck valves --teacher-stuck says: all, or seen, those its "
                                "own commands showed; no checkpoint needed), oracle-mpc's "
                                "planner (the same planner with oracle-mpc's hold and "
                                "horizon and nothing more, told every stuck valve, whatever "
                                "those options say) or the balance rule")
            s.add_argument("--out", default="", help="per-scenario scores (CSV)")
            s.add_argument("--per-interval", action="store_true",
                           help="--out also holds each scored interval's reward per step "
                                "(reward_1 to reward_9), to see where a policy loses")
            s.add_argument("--curve", default="", help="the learning curve (CSV)")
            s.add_argument("--figure", default="", help="the learning curve's figure (PNG)")
    return p


def _usable_cpus() -> int:
    """The CPUs this process may run on (all of them where affinity is unknown)."""
    affinity = getattr(os, "sched_getaffinity", None)
    return len(affinity(0)) if affinity is not None else os.cpu_count() or 1


def main(argv: list[str] | None = None) -> int:
    p = parser()
    a = p.parse_args(argv)
    try:
        commands = {"train": cmd_train, "evaluate": cmd_evaluate, "summarize": cmd_summarize}
        return commands[a.command](a)
    except ValueError as e:
        print(f"adaptive: error: {e}", file=sys.stderr)
        return EXIT_USAGE

