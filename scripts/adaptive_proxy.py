"""The adaptive student's cheap proxy (docs/adaptive.md): how well does a
student configuration imitate the teacher, on held-out draws of the training
distribution, without a DAgger run or a benchmark evaluation?

    python scripts/adaptive_proxy.py collect --driver CHECKPOINT --out /tmp/proxy.npz
    python scripts/adaptive_proxy.py fit --data /tmp/proxy.npz head=valves,inputs=window \
        head=joint,inputs=rates ...

``collect`` runs plants drawn from the training distribution (draw seeds
disjoint from the default training run's) in the pool, driven by a trained
student (``--driver``) with a share ``--beta`` of them driven by the teacher,
and stores the teacher's labels and regrets for a fraction of the states: a
training part and a validation part from other plants. ``fit`` trains a fresh
student of each configuration (KEY=VALUE of TrainingConfig) on the training
part for ``--epochs`` epochs and prints, on the validation part, the fraction
of states where it picks the teacher's six valves and its mean regret (the
summed reward over the teacher's horizon that its choice loses against the
teacher's best plan). Fixed seeds; torch on one thread.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np
import torch

from ftc.control.planning.physics.teacher import PoolTeacher
from ftc.experiments.adaptive import dagger, distribution
from ftc.learning.history_policy import HistoryPolicy, TrainingConfig, rates_map


def collect(a: argparse.Namespace) -> None:
    dist = distribution.load(a.distribution)
    driver = HistoryPolicy.from_record(torch.load(a.driver, weights_only=True)["policy"])
    if driver.config.stuck_memory:
        raise ValueError(f"{a.driver}: a driver with the stuck memory: the proxy's data are "
                         "windows alone")
    parts = {}
    for part, iteration, envs in (("train", 100, a.envs), ("val", 200, a.val_envs)):
        config = TrainingConfig(envs=envs, label_fraction=a.label_fraction, head="joint",
                                window=driver.config.window, seed=0, stuck_memory=False,
                                teacher_stuck="all")
        t = time.monotonic()
        r = dagger.collect(driver, PoolTeacher(), dist, config, iteration, a.beta)
        print(f"proxy: {part}: {len(r['x'])} labels in {time.monotonic() - t:.0f} s, "
              f"driver reward/step {r['student_reward_per_step']:.3f}", flush=True)
        parts.update({f"{part}_x": r["x"], f"{part}_y": r["y"], f"{part}_g": r["regrets"]})
    np.savez_compressed(a.out, **parts)


def parse_config(text: str, epochs: int) -> TrainingConfig:
    types = {f.name: type(getattr(TrainingConfig(), f.name)) for f in
             dataclasses.fields(TrainingConfig)}
    values: dict = {"epochs": epochs, "stuck_memory": False, "teacher_stuck": "all"}
    for item in filter(None, text.split(",")):
        key, _, value = item.partition("=")
        if key not in types:
            raise ValueError(f"unknown TrainingConfig field {key!r} in {text!r}")
        if key == "stuck_memory":
            raise ValueError(f"{text!r}: the proxy's data are windows alone (no stuck memory)")
        if types[key] is tuple:
            values[key] = tuple(int(v) for v in value.split("x"))
        elif types[key] is bool:
            values[key] = value.lower() in ("1", "true", "yes")
        else:
            values[key] = types[key](value)
    return TrainingConfig(**values)


def write_rows(path: str, a: argparse.Namespace, n_train: int, n_val: int,
               rows: list[dict]) -> None:
    """The comparison as a result file (docs/results/): provenance, then the CSV."""
    from ftc.experiments.adaptive.summary import write_result

    write_result(path, f"student configurations fitted {a.epochs} epochs on {n_train} teacher "
                       f"labels of 24 plants drawn from the training distribution, scored on "
                       f"{n_val} labels of 12 other plants: share of states with the teacher's "
                       f"six valves, and mean regret (summed reward over the teacher's horizon "
                       f"lost against its best plan)", rows,
                 command="python scripts/adaptive_proxy.py")


def fit(a: argparse.Namespace) -> None:
    torch.set_num_threads(1)
    d = np.load(a.data)
    rows = []
    for text in a.configs:
        config = parse_config(text, a.epochs)
        w = config.window
        x, xv = d["train_x"][:, :12 * w], d["val_x"][:, :12 * w]
        torch.manual_seed(config.seed)
        policy = HistoryPolicy(config.student())
        if config.inputs == "rates":
            policy.set_input_map(*rates_map(w, x))
        optimizer = torch.optim.Adam(policy.parameters(), lr=config.lr)
        g = d["train_g"] if config.head == "joint" else np.zeros((len(x), 0), np.float32)
        t = time.monotonic()
        stats = dagger.fit(policy, optimizer, x, d["train_y"], config,
                           np.random.default_rng([config.seed, 2]), g)
        u = HistoryPolicy.from_record(policy.record()).act(xv)
        agree = float((u == d["val_y"]).all(axis=1).mean())
        regret = float(d["val_g"][np.arange(len(xv)), dagger.settings_of(u)].mean())
        print(f"proxy: {text}: train agreement {stats['action_agreement']:.4f}  val agreement "
              f"{agree:.4f}  val mean regret {regret:.5f}  ({time.monotonic() - t:.0f} s)",
              flush=True)
        rows.append({"student": text, "train_agreement": round(stats["action_agreement"], 3),
                     "validation_agreement": round(agree, 3),
                     "validation_mean_regret": round(regret, 3)})
    if a.out:
        write_rows(a.out, a, len(d["train_x"]), len(d["val_x"]), rows)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect")
    c.add_argument("--driver", required=True, help="a student checkpoint that drives the plants")
    c.add_argument("--out", required=True)
    c.add_argument("--distribution", default=str(distribution.DISTRIBUTION_FILE))
    c.add_argument("--envs", type=int, default=24)
    c.add_argument("--val-envs", type=int, default=12)
    c.add_argument("--beta", type=float, default=0.25)
    c.add_argument("--label-fraction", type=float, default=0.2)
    f = sub.add_parser("fit")
    f.add_argument("--data", required=True)
    f.add_argument("--epochs", type=int, default=8)
    f.add_argument("--out", default="", help="the comparison as a result file (CSV)")
    f.add_argument("configs", nargs="+", help="KEY=VALUE,... of TrainingConfig (hidden=256x256)")
    a = p.parse_args()
    try:
        collect(a) if a.command == "collect" else fit(a)
    except (ValueError, OSError, KeyError) as e:
        print(f"proxy: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
