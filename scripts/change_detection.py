#!/usr/bin/env python3
"""Detection delay and false alarms of the online identification's change test
(ftc.learning.identify.OnlineIdentification, as identified-mpc runs it: the
one-error trigger on exact levels, the CUSUM on noisy ones): the figures of
docs/controller.md's "Faults that change the plant's form".

    .venv/bin/python scripts/change_detection.py [--seeds 0 1 2] [--intervals 10] \
        [--scenarios NAME[@STD] ...]

Each scenario's plant is driven for ``--intervals`` intervals of 512 steps by
sparse random valve openings (an open probability in [0, 0.3] per episode,
each setting held 1-10 steps), every step fed to the identification
(re-identified every 64 steps). An abrupt event's delay is the operating steps
from it to the first alarm at or after it. The plant also degrades at every
interval boundary (stepwise): the first alarm in an interval's first 64 steps
is that change, found; any other alarm not within 64 steps of an event is a
false alarm. Prints per scenario: the mean delay per event over seeds (a
demand jump; stuck valves are found by the stuck-valve detector instead, from
the applied valves, and the identification predicts with the applied valves,
so they are not changes to it) and false alarms per interval.
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
from ftc.learning.identify import Identifier, OnlineIdentification  # noqa: E402
from ftc.plant.link import CorePlant  # noqa: E402

SCENARIOS = ["single", "multiple", "check/noise-10", "check/noise-20", "abrupt",
             "check/compound-01", "check/compound-02", "check/compound-01@0.01",
             "check/compound-01@0.02"]
WINDOW = 64


def scenario_file(name: str, directory: Path) -> Path:
    """scenarios/NAME.toml, or for NAME@STD a copy of it with that sensor noise (m)."""
    name, _, std = name.partition("@")
    path = REPO / "scenarios" / f"{name}.toml"
    if not std:
        return path
    out = directory / f"{path.stem}-noise-{std}.toml"
    out.write_text(path.read_text().replace("[[event]]", f"[noise]\nstd = {std}\n\n[[event]]", 1))
    return out


def run(path: Path, seed: int, intervals: int) -> tuple[list[int], list[int], list[int]]:
    """(event steps of parameter jumps, alarm operating steps, interval starts)."""
    scenario = _core.load_scenario(str(path))
    events = sorted({e["at_step"] for e in scenario.events if "factor" in e})
    plant = CorePlant(str(path), seed)
    rng = np.random.default_rng(seed)
    online = OnlineIdentification(Identifier(seed=seed), trigger=1e-4, every=64)
    alarms, starts = [], []
    obs, hold, p_open = plant.reset(), 0, rng.uniform(0, 0.3)
    for k in range(intervals):
        online.begin()
        start = obs.operating_steps
        starts.append(start)
        steps = []
        for _ in range(512):
            if hold == 0:
                valves = (rng.random(6) < p_open).astype(np.int8)
                hold = int(rng.integers(1, 11))
            hold -= 1
            nxt = plant.step(valves)
            steps.append(obs.operating_steps)
            online.add(obs.level, nxt.valves, nxt.level, nxt.deficit)
            obs = nxt
            if nxt.done:
                obs, p_open = plant.reset(), rng.uniform(0, 0.3)
        alarms += [steps[r] for r in online.alarms]
        online.end()
    plant.close()
    return events, alarms, starts


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--intervals", type=int, default=10)
    p.add_argument("--scenarios", nargs="+", default=SCENARIOS)
    args = p.parse_args()
    print("scenario,noise_m,events,mean_delay_steps,boundaries_found,false_alarms_per_interval")
    directory = Path(tempfile.mkdtemp())
    for name in args.scenarios:
        delays, found, false = [], 0, 0
        path = scenario_file(name, directory)
        noise = _core.load_scenario(str(path)).noise_std
        for seed in args.seeds:
            events, alarms, starts = run(path, seed, args.intervals)
            for e in events:
                after = [a - e for a in alarms if a >= e]
                delays.append(min(after) if after else float("inf"))
            boundary = set()
            for s in starts[1:]:
                first = [a for a in alarms if s <= a < s + WINDOW]
                if first:
                    boundary.add(first[0])
                    found += 1
            false += sum(1 for a in alarms if a not in boundary
                         and not any(0 <= a - e < WINDOW for e in events))
        n_int = len(args.seeds) * args.intervals
        delay = f"{np.mean(delays):.1f}" if delays else ""
        print(f"{name},{noise},{len(delays) // len(args.seeds)},{delay},"
              f"{found}/{len(args.seeds) * (args.intervals - 1)},{false / n_int:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
