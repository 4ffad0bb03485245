"""A full disk mid-run (Reliability item 3): the write that fails gives one
line naming the path and exit 5, leaves no temporary file and no partial
result (metrics.csv and checkpoint.pt stay those of the last finished
interval), and --resume completes the run once space is back, with the same
results as a run that never failed. The disk is a small tmpfs (needs root, as
CI runs; skipped with the reason otherwise)."""

from __future__ import annotations

import csv
import os
import subprocess
from pathlib import Path

import pytest
import torch

from ftc.tools import controller as controller_cli
from ftc.tools.controller import Controller, resume_config
from ftc.control.agents.ppo import ControllerConfig
from ftc.learning.ppo import PPOConfig

REPO = Path(__file__).resolve().parents[2]
TIME_COLUMNS = {"online_seconds", "offline_seconds", "wall_time", "refit_seconds"}


@pytest.fixture
def small_disk(tmp_path):
    mount = tmp_path / "disk"
    mount.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(mount)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({proc.stderr.strip() or proc.returncode})")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def _fill(disk: Path) -> Path:
    """Fill ``disk`` up to the last byte; returns the filler file."""
    filler = disk / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT)
    try:
        for size in (65536, 1):  # large blocks, then the last bytes one by one
            try:
                while True:
                    os.write(fd, b"\0" * size)
            except OSError:
                pass
    finally:
        os.close(fd)
    return filler


def _config(out: Path, scenarios: Path) -> ControllerConfig:
    return ControllerConfig(out=str(out), scenario=str(scenarios / "single.toml"), intervals=3,
                            steps_per_interval=64, update_every=32, offline_steps=128,
                            offline_envs=4, offline_rollout=16, model_episodes=4, link="core",
                            quiet=True, seed=2)


def _rows(out: Path) -> list[dict[str, str]]:
    with open(out / "metrics.csv") as f:
        return [{k: v for k, v in r.items() if k not in TIME_COLUMNS} for r in csv.DictReader(f)]


def test_full_disk_mid_run_loses_nothing_and_resume_completes(small_disk, tmp_path, scenarios,
                                                              capsys):
    reference = tmp_path / "reference"
    Controller(_config(reference, scenarios), PPOConfig()).run()

    out = small_disk / "run"
    Controller(_config(out, scenarios), PPOConfig()).run(stop_after=1)
    before = (out / "metrics.csv").read_bytes(), (out / "checkpoint.pt").read_bytes()
    filler = _fill(small_disk)

    code = controller_cli.main(["--resume", str(out), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 5
    assert len(err) == 1 and err[0].startswith("ftc.controller: error: cannot write "), err
    assert str(out) in err[0]
    assert not [p.name for p in out.iterdir() if p.name.endswith(".tmp")]
    assert ((out / "metrics.csv").read_bytes(), (out / "checkpoint.pt").read_bytes()) == before
    assert torch.load(out / "checkpoint.pt", weights_only=True)["interval"] == 1

    os.unlink(filler)  # space is back
    cfg, ppo = resume_config(str(out))
    Controller(cfg, ppo).run()
    diffs = [(k, c, a[c], b[c]) for k, (a, b) in enumerate(zip(_rows(out), _rows(reference)))
             for c in a if a[c] != b[c]]
    assert not diffs
    assert (out / "done.json").exists()
