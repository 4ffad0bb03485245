"""Benchmark directories written by hand, for the tools that read them
(scripts/headroom.py, ftc.experiments compare): benchmark.json, the scenario
files and results.csv, as ``ftc.experiments benchmark`` lays them out."""

from __future__ import annotations

import csv
import json
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def write_benchmark(path: Path, rewards: dict[str, dict[tuple[str, int], list[float]]],
                    steps_per_interval: int = 512, reference: str = "reference",
                    scenario_text: dict[str, str] | None = None) -> Path:
    """A finished benchmark directory: rewards[method][(scenario, seed)] is the
    reward per step of each interval; scenario files are scenarios/single.toml's
    text unless ``scenario_text`` gives a scenario's own."""
    cells = [(m, s, seed, k, v) for m, runs in rewards.items()
             for (s, seed), values in runs.items() for k, v in enumerate(values)]
    scenarios = sorted({s for _, s, _, _, _ in cells})
    (path / "scenarios").mkdir(parents=True)
    for s in scenarios:
        text = (scenario_text or {}).get(s, (REPO / "scenarios" / "single.toml").read_text())
        (path / "scenarios" / f"{s}.toml").write_text(text)
    (path / "benchmark.json").write_text(json.dumps({
        "config": {"scenarios": scenarios, "methods": list(rewards),
                   "seeds": sorted({seed for _, _, seed, _, _ in cells}),
                   "intervals": max(k for _, _, _, k, _ in cells) + 1,
                   "steps_per_interval": steps_per_interval, "reference": reference},
        "git_revision": "0" * 40, "created": "2026-12-04T00:00:00"}))
    with open(path / "results.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["scenario", "method", "seed", "interval", "reward_per_step"])
        w.writerows([s, m, seed, k, v] for m, s, seed, k, v in cells)
    return path
