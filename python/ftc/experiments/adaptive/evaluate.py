"""The adaptive student scored on the benchmark's protocol, in the batched pool:
each scenario a plant of its own, 10 intervals of 512 operating steps from
full tanks, the reward per step of each interval, scored per scenario
against the shipped reference and closed rewards (``scenarios/reference/``):
the sum over intervals 1-9 of (r - closed), divided by the same sum for the
reference.

The pool runs the plant's physics (closed-form steps where they apply, CVODE
for the rest); all valves closed, run here, reproduces the shipped closed
rewards (tests/python/test_adaptive.py), so the scores are the benchmark's.
The learning curve evaluates every iteration's student this way (the suite
is never used to choose anything).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ftc.common.atomic import atomic_write_bytes
from ftc.common.paths import SCENARIO_DIR
from ftc.control.planning.physics.teacher import PoolTeacher
from ftc.experiments.suite import write_suite
from ftc.learning.history_policy import HistoryPolicy, HistoryWindow
from ftc.learning.stuck import StuckMemory
from ftc.plant.vector import FuelTransferVectorEnv

REFERENCE_FILES = {"suite": SCENARIO_DIR / "reference" / "suite.json",
                   "check": SCENARIO_DIR / "reference" / "check.json"}
FIRST_SCORED = 1  # interval 0 (a healthy plant) is not scored


HELDOUT_DIR = SCENARIO_DIR / "heldout"  # faults made to check it, in no training or suite


def scenario_files(which: str, directory: Path,
                   heldout_files: Sequence[Path] | None = None) -> dict[str, Path]:
    """name -> scenario file of the suite (written into ``directory``), the check
    set or the held-out set (``heldout_files``, default ``scenarios/heldout/``)."""
    if which == "suite":
        return {p.stem: p for p in write_suite(directory)}
    if which == "heldout":
        files = heldout_files or sorted(HELDOUT_DIR.glob("*.toml"))
        return {Path(p).stem: Path(p) for p in files}
    names = json.loads(REFERENCE_FILES["check"].read_text())["scenarios"]
    return {n: (SCENARIO_DIR / f"{n}.toml" if (SCENARIO_DIR / f"{n}.toml").is_file()
                else SCENARIO_DIR / "check" / f"{n}.toml") for n in names}


def rewards(policy: HistoryPolicy | PoolTeacher | Callable[[np.ndarray], np.ndarray] | None,
            scenarios: Sequence[Any], seeds: Sequence[int], intervals: int = 10,
            steps_per_interval: int = 512, teacher_stuck: str = "all") -> np.ndarray:
    """Reward per step (len(scenarios), intervals) of ``policy`` on plant i with
    scenario i seeded seeds[i], from full tanks: the student, the teacher
    (the planner on each plant's true physics; with ``teacher_stuck`` "seen"
    told only the stuck valves its own commands have shown, as the student's
    teacher in training), a function of the levels (N, 6) -> valves (N, 6),
    or None (all valves closed)."""
    n = len(scenarios)
    env = FuelTransferVectorEnv(n, list(scenarios), plant_seed=list(seeds),
                                autoreset="same_step", threads=1, copy=False)
    obs, _ = env.reset()
    window = None
    if isinstance(policy, HistoryPolicy):
        window = HistoryWindow(n, policy.config.window, policy.config.stuck_memory)
        window.start(obs)
    seen = StuckMemory(n) if teacher_stuck == "seen" else None
    out = np.zeros((n, intervals))
    u = np.zeros((n, 6), np.int8)
    for k in range(intervals):
        for _ in range(steps_per_interval):
            if window is not None:
                u = policy.act(window.features())
            elif isinstance(policy, PoolTeacher):
                u = policy.label_with_regrets(range(n), scenarios, np.array(
                    [env.pool.operating_steps(i) for i in range(n)]), obs,
                    None if seen is None else seen.stuck)[0]
            elif policy is not None:
                u = np.asarray(policy(obs), np.int8)
            obs, r, terminated, truncated, info = env.step(u)
            out[:, k] += r
            if window is not None:
                window.push(obs, u, terminated | truncated, info["valves"])
            if seen is not None:
                seen.see(u, info["valves"])
    env.close()
    return out / steps_per_interval


def benchmark_rewards(results_csv: Path) -> dict[str, Any]:
    """A benchmark's results.csv (or its cells trimmed to scenario, method,
    seed, interval and reward_per_step, '#' lines first, as
    scenarios/reference/{heldout,drawn,final}.csv) as reference_scores' layout:
    scenario -> {"rewards": method -> seed (str) -> reward per step of each
    interval}."""
    import csv

    out: dict[str, Any] = {}
    with open(results_csv, newline="") as f:
        for r in csv.DictReader(line for line in f if not line.startswith("#")):
            cells = out.setdefault(r["scenario"], {"rewards": {}})["rewards"]
            seq = cells.setdefault(r["method"], {}).setdefault(r["seed"], {})
            seq[int(r["interval"])] = float(r["reward_per_step"])
    for sc in out.values():
        for per_seed in sc["rewards"].values():
            for seed, seq in per_seed.items():
                per_seed[seed] = [seq[k] for k in sorted(seq)]
    return out


def reference_rewards(which: str, names: Sequence[str], seed: int,
                      heldout: Path | None = None) -> dict[str, np.ndarray]:
    """method ('reference', 'closed') -> (len(names), intervals) rewards: the
    shipped ones, or for the held-out set a benchmark's results.csv."""
    data = (benchmark_rewards(heldout) if which == "heldout" else
            json.loads(REFERENCE_FILES[which].read_text())["scenarios"])
    missing = [f"{n} ({m}, seed {seed})" for n in names for m in ("reference", "closed")
               if str(seed) not in data.get(n, {}).get("rewards", {}).get(m, {})]
    if missing:
        raise ValueError(f"{heldout if which == 'heldout' else REFERENCE_FILES[which]}: "
                         f"no rewards of {', '.join(missing[:3])}"
                         f"{f' and {len(missing) - 3} more' if len(missing) > 3 else ''}")
    return {m: np.array([data[n]["rewards"][m][str(seed)] for n in names])
            for m in ("reference", "closed")}


def gains(r: np.ndarray, closed: np.ndarray) -> np.ndarray:
    """Reward per step of rewards (S, intervals) over closed's, summed over the
    scored intervals (S,)."""
    return (r[:, FIRST_SCORED:] - closed[:, FIRST_SCORED:]).sum(1)


def scores(r: np.ndarray, reference: np.ndarray, closed: np.ndarray) -> np.ndarray:
    """Per-scenario normalized score of rewards (S, intervals); NaN (undefined)
    where the reference earns exactly what closed earns over the scored
    intervals, as the benchmark's normalized_score leaves such a cell empty."""
    gain = gains(reference, closed)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(gain != 0, gains(r, closed) / gain, np.nan)


def evaluate(policy: Any, which: str, seeds: Sequence[int] = (0,),
             heldout: Path | None = None, heldout_files: Sequence[Path] | None = None,
             teacher_stuck: str = "all", per_interval: bool = False) -> list[dict[str, Any]]:
    """Rows (set, scenario, seed, score (NaN where undefined), reward per step
    of intervals 1-9, and the reference's over closed's per step there; with
    ``per_interval``, each scored interval's reward per step too, reward_1 to
    reward_9, to read beside the reference's and closed's own) of
    ``policy`` on the suite, the check set or the held-out set (``heldout_files``,
    default ``scenarios/heldout/``; its reference and closed rewards from the
    benchmark results.csv ``heldout``), each seed."""
    from ftc import _core  # the plant's scenario parser

    with tempfile.TemporaryDirectory() as tmp:
        files = scenario_files(which, Path(tmp), heldout_files)
        names = list(files)
        loaded = [_core.load_scenario(str(files[n])) for n in names]
    rows = []
    for seed in seeds:
        r = rewards(policy, loaded, [seed] * len(loaded), teacher_stuck=teacher_stuck)
        ref = reference_rewards(which, names, seed, heldout)
        sc = scores(r, ref["reference"], ref["closed"])
        gain = gains(ref["reference"], ref["closed"]) / (r.shape[1] - FIRST_SCORED)
        for i, name in enumerate(names):
            rows.append({"set": which, "scenario": name, "seed": seed, "score": float(sc[i]),
                         "reward_per_step": float(r[i, FIRST_SCORED:].mean()),
                         "reference_gain_per_step": float(gain[i]),
                         **({f"reward_{k}": float(r[i, k])
                             for k in range(FIRST_SCORED, r.shape[1])} if per_interval else {})})
    return rows


def curve_title(config: dict[str, Any]) -> str:
    """The learning curve figure's title: the teacher, the perturbations and the
    members of a checkpoint's training ``config``."""
    *first, last = [str(h) for h in [config["hold"], *config.get("extra_holds", [])]]
    holds = f"{', '.join(first)} or {last}" if first else last
    title = (f"adaptive-policy: DAgger from the planner holding {holds} steps over "
             f"{config['horizon']}")
    if config.get("recheck"):
        rule = config.get("recheck_rule", "closed")
        after = "the better of balance and closed" if rule == "best" else rule
        title += (f", its {config['recheck']} best rechecked over {config['recheck_horizon']} "
                  f"({after} after the hold)")
    if config.get("explore"):
        title += (f", perturbed (a random setting held 1 to {config['explore_hold']} steps, "
                  f"begun with chance {config['explore']:g} a step)")
    members = int(config.get("members", 1))
    return title + (f", {members} members one after another" if members > 1 else "")


def draw_curve(curve: list[dict[str, Any]], path: Path, record: dict[str, Any]) -> None:
    """The learning curve's figure (PNG): the suite's mean and worst scenario
    against the plant steps and the members' training seconds, written whole
    or not at all."""
    import io
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), sharey=True)
    for ax, x, label in ((axes[0], "env_steps", "environment steps"),
                         (axes[1], "seconds", "training time, s (the members' own, added up)")):
        xs = [r[x] for r in curve]
        ax.plot(xs, [r["suite_mean_score"] for r in curve], "o-", label="mean over scenarios")
        ax.plot(xs, [r["suite_worst_score"] for r in curve], "s--", label="worst scenario")
        ax.axhline(0.9, color="gray", lw=0.8, ls=":")
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("normalized score (suite, per scenario)")
    axes[0].legend(loc="lower right")
    fig.suptitle(textwrap.fill(curve_title(record["config"]), 100), fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())  # its directory made too
