"""Adding a method takes one file and one registry entry (issue 36): a toy
controller with two options, written into a copy of the package as a new
module of control/agents/ plus one ``register(Method(...))`` line in
control/registry.py, runs through ``ftc.controller`` with its options (and
only those, in ``--help`` and on the command line) and through the benchmark."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
TOY = '''"""A toy controller: opens one valve while its tank is above a level."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ftc.common.cli import at_least, between
from ftc.control.run.agent import Agent, StepContext
from ftc.control.run.config import RunConfig
from ftc.plant.link import PlantObservation


@dataclass
class ToyConfig(RunConfig):
    method: str = field(default="toy", metadata={"help": "the method"})
    valve: int = field(default=0, metadata={"check": at_least(0, 5), "help": "the valve it opens"})
    level: float = field(default=0.5, metadata={"check": between(0.0, 2.0),
                                                "help": "the level above which it opens it, m"})


class ToyAgent(Agent):
    name = "toy"
    evaluates = False
    Config = ToyConfig

    def __init__(self, cfg: ToyConfig) -> None:
        self.cfg = cfg

    @classmethod
    def from_configs(cls, configs: dict[str, Any]) -> "ToyAgent":
        return cls(configs["controller"])

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        u = np.zeros(6, np.int8)
        u[self.cfg.valve] = obs.level[self.cfg.valve] > self.cfg.level
        return u
'''
ENTRY = ('\nregister(Method("toy", "ftc.control.agents.toy:ToyAgent", "toy: one valve above a '
         'level", color="tab:olive"))\n')


@pytest.fixture(scope="module")
def with_toy(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """A copy of the package with the toy method: its file and its registry entry."""
    root = tmp_path_factory.mktemp("toy")
    shutil.copytree(REPO / "python" / "ftc", root / "python" / "ftc",
                    ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(REPO / "pyproject.toml", root / "pyproject.toml")  # the checkout's version
    (root / "python" / "ftc" / "control" / "agents" / "toy.py").write_text(TOY)
    registry = root / "python" / "ftc" / "control" / "registry.py"
    registry.write_text(registry.read_text() + ENTRY)
    env = dict(os.environ, PYTHONPATH=str(root / "python"), FTC_BUILD_DIR=str(REPO / "build"),
               OMP_NUM_THREADS="1")
    return root, env


def _run(root: Path, env: dict[str, str], *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], cwd=root, env=env, capture_output=True,
                          text=True, timeout=600)


@pytest.mark.slow  # four processes that import torch: ~15 s
def test_a_new_method_runs_with_its_options_and_only_those(with_toy):
    root, env = with_toy
    shown = _run(root, env, "ftc.controller", "--method", "toy", "--help")
    assert shown.returncode == 0, shown.stderr
    assert "--valve" in shown.stdout and "--level" in shown.stdout
    assert "--update-every" not in shown.stdout and "--band" not in shown.stdout
    rewards = {}
    for level in ("0.3", "2.0"):  # 2.0: above full tanks, the valve never opens
        out = root / f"run-{level}"
        run = _run(root, env, "ftc.controller", "--method", "toy", "--valve", "2", "--level",
                   level, "--scenario", str(REPO / "scenarios" / "single.toml"), "--link",
                   "core", "--intervals", "1", "--steps-per-interval", "32", "--quiet",
                   "--out", str(out))
        assert run.returncode == 0, run.stderr[-3000:]
        config = json.loads((out / "config.json").read_text())["controller"]
        assert (config["method"], config["valve"], config["level"]) == ("toy", 2, float(level))
        rewards[level] = float(next(csv.DictReader(open(out / "metrics.csv")))["reward_per_step"])
    # its option acts: an open valve pays the activity term (1/6 a step) and moves fuel
    assert rewards["0.3"] != rewards["2.0"]
    foreign = _run(root, env, "ftc.controller", "--method", "toy", "--update-every", "2",
                   "--out", str(root / "no"))
    assert foreign.returncode == 2 and not (root / "no").exists()
    assert foreign.stderr.strip() == ("ftc.controller: error: --update-every is not an option "
                                      "of --method toy (python -m ftc.controller --method toy "
                                      "--help lists them)")


@pytest.mark.slow
def test_a_new_method_runs_in_the_benchmark(with_toy):
    root, env = with_toy
    out = root / "bench"
    bench = _run(root, env, "ftc.experiments", "benchmark", "--methods", "toy", "--reference",
                 "balance", "--scenarios", str(REPO / "scenarios" / "single.toml"), "--seeds",
                 "0", "--intervals", "1", "--steps-per-interval", "64", "--jobs", "2", "--out",
                 str(out), "--controller-args=--level=0.4")
    assert bench.returncode == 0, bench.stderr[-3000:]
    rows = [r for r in csv.DictReader(open(out / "results.csv")) if r["method"] == "toy"]
    assert rows, (out / "results.csv").read_text()[:2000]
    config = json.loads(next(out.rglob("toy/**/config.json")).read_text())["controller"]
    assert config["level"] == 0.4  # its own option reached its runs, and no other method's
