#!/usr/bin/env python3
"""Parameter error of the online identification (ftc.learning.identify) against
the sensor noise on the published levels: the figures of docs/controller.md's
"Identification under sensor noise".

    .venv/bin/python scripts/noise_identification.py [--noise 0 0.005 0.01 0.02] [--seeds 0 1 2]

For each noise level and seed: the plant of scenarios/check/noise-10.toml (tank 4
D_T = 12, engine E1 D_E = 18) with that noise, at age 3, driven for one interval
(512 steps) by sparse random valve openings held 1-10 steps, each step fed to
OnlineIdentification as identified-mpc feeds it (re-identified every 64 steps,
the change trigger on), after one such interval at age 2 (where the noise is
first estimated, as in a run); then the interval's final estimate against the
true parameters of that age. Prints, per noise level, the mean over seeds of the
mean relative error of the pumps, the valve conductances of the valves opened
and the engine demands, and the changes the trigger reported in the interval (the
plant degraded at its start: one is a true detection, more are false alarms).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "python"))

from ftc import _core  # noqa: E402
from ftc.learning.identify import Identifier, OnlineIdentification, PlantParameters  # noqa: E402
from ftc.plant.link import CorePlant  # noqa: E402

AGE = 3


def one(noise: float, seed: int, directory: Path) -> dict[str, float]:
    text = (REPO / "scenarios" / "check" / "noise-10.toml").read_text()
    path = directory / f"noise-{noise}.toml"
    path.write_text(text.replace("std = 0.01", f"std = {noise}"))
    rng = np.random.default_rng(seed)
    online = OnlineIdentification(Identifier(seed=seed), trigger=1e-4, every=64)
    for age in (AGE - 1, AGE):  # an interval before, as a run has (the noise estimated there)
        changes, est, opened = _interval(online, path, seed, age, rng)
    true = _core.degraded_params(_core.load_scenario(str(path)), float(AGE))
    cond = np.abs(1 / est.resistance - 1 / true["resistance"]) * true["resistance"]
    return {"pump": float(np.mean(np.abs(est.pump - true["pump"]) / true["pump"])),
            "conductance": float(np.mean(cond[opened])),
            "demand": float(np.mean(np.abs(est.demand - true["demand"]) / true["demand"])),
            "changes": float(changes),
            "noise_estimate": float(getattr(online, "noise", float("nan")))}  # nan: no estimate


def _interval(online: OnlineIdentification, path: Path, seed: int, age: int,
              rng: np.random.Generator) -> tuple[int, PlantParameters, np.ndarray]:
    """One interval at ``age`` fed to ``online``: (changes detected, the final
    estimate, which valves were open with the conduit active)."""
    plant = CorePlant(str(path), seed, start_step=age * 512)
    online.begin()
    obs, hold, p_open, opened = plant.reset(), 0, rng.uniform(0, 0.3), np.zeros(6, bool)
    for _ in range(512):
        if hold == 0:
            valves = (rng.random(6) < p_open).astype(np.int8)
            hold = int(rng.integers(1, 11))
        hold -= 1
        nxt = plant.step(valves)
        online.add(obs.level, nxt.valves, nxt.level, nxt.deficit)
        opened |= nxt.valves.astype(bool) & (valves.sum() >= 2)
        obs = nxt
        if nxt.done:
            obs, p_open = plant.reset(), rng.uniform(0, 0.3)
    plant.close()
    changes = online.changes
    return changes, online.end()[0], opened


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.005, 0.01, 0.02])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = p.parse_args()
    print("noise_m,pump_rel_error,conductance_rel_error,demand_rel_error,changes,"
          "noise_estimate_m")
    with tempfile.TemporaryDirectory() as d:
        for noise in args.noise:
            rows = [one(noise, s, Path(d)) for s in args.seeds]
            mean = {k: np.mean([r[k] for r in rows]) for k in rows[0]}
            print(f"{noise},{mean['pump']:.4f},{mean['conductance']:.4f},{mean['demand']:.4f},"
                  f"{mean['changes']:.1f},{mean['noise_estimate']:.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
