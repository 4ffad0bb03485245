"""The controller loop: end to end against the real plant process over LCM,
baselines, outputs, and resume equals an uninterrupted run."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest
import torch

from ftc.tools.controller import Controller, main, parse_args, resume_config
from ftc.control.agents.ppo import ControllerConfig
from ftc.learning.ppo import PPOConfig

TIME_COLUMNS = {"online_seconds", "offline_seconds", "wall_time", "refit_seconds",
                "pretrain_seconds", "model_pretrain_seconds"}


def _short(out: Path, **kw) -> ControllerConfig:
    """Two shortened intervals (128 steps, update every 64, 512 offline steps)."""
    base = dict(out=str(out), intervals=2, steps_per_interval=128, update_every=64,
                offline_steps=512, offline_envs=8, offline_rollout=32, model_episodes=6,
                quiet=True, seed=3)
    base.update(kw)
    return ControllerConfig(**base)


def _rows(out: Path) -> list[dict[str, str]]:
    with open(out / "metrics.csv") as f:
        return list(csv.DictReader(f))


def test_end_to_end_over_lcm_with_offline(tmp_path, scenarios):
    out = tmp_path / "run"
    cfg = _short(out, scenario=str(scenarios / "single.toml"), link="lcm")
    rows = Controller(cfg, PPOConfig()).run()
    assert [r["interval"] for r in rows] == [0, 1]
    table = _rows(out)
    assert len(table) == 2
    for col in ("interval", "reward_per_step", "eval_reward_per_step", "episodes", "model_r2",
                "entropy", "approx_kl", "clipfrac", "explained_variance",
                "model_one_step_rmse", "model_ten_step_rmse", "wall_time"):
        assert table[0][col] != "", col
    assert all(0.0 < float(r["reward_per_step"]) < 2.7 for r in table)
    assert int(table[0]["episodes"]) >= 2  # 128 steps hold at least two ~59-step episodes
    doc = json.loads((out / "config.json").read_text())
    assert doc["seed"] == 3 and doc["git_revision"]
    assert (out / "done.json").exists()
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    agent = state["agent"]
    assert state["interval"] == 2 and "policy" in agent["ppo"] and agent["model"] is not None


@pytest.mark.parametrize("method", ["closed", "open", "random"])
def test_baselines_through_the_same_loop(tmp_path, method, scenarios):
    cfg = _short(tmp_path, method=method, link="core", scenario=str(scenarios / "single.toml"))
    rows = Controller(cfg, PPOConfig()).run()
    assert rows[0]["eval_reward_per_step"] is None
    if method == "closed":  # nominal interval 0: 2.69 per step over full episodes
        assert rows[0]["reward_per_step"] == pytest.approx(2.69, abs=0.05)
        assert rows[1]["reward_per_step"] < rows[0]["reward_per_step"]  # the plant degraded


def _comparable(rows):
    return [{k: v for k, v in r.items() if k not in TIME_COLUMNS} for r in rows]


@pytest.mark.parametrize("link", ["core", "lcm"])
def test_resume_equals_uninterrupted(tmp_path, link, scenarios):
    kw = dict(intervals=3, link=link, scenario=str(scenarios / "single.toml"))
    full = Controller(_short(tmp_path / "full", **kw), PPOConfig()).run()

    stopped = tmp_path / "stopped"
    Controller(_short(stopped, **kw), PPOConfig()).run(stop_after=2)
    assert len(_rows(stopped)) == 2 and not (stopped / "done.json").exists()
    cfg, ppo = resume_config(str(stopped))
    resumed = Controller(cfg, ppo).run()
    assert _comparable(resumed) == _comparable(full)
    a = torch.load(tmp_path / "full" / "checkpoint.pt", weights_only=True)["agent"]["ppo"]["policy"]
    b = torch.load(stopped / "checkpoint.pt", weights_only=True)["agent"]["ppo"]["policy"]
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_cli_parses_every_option_and_help_explains_them(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    for opt in ("--offline", "--no-offline", "--offline-mode", "--pretrain", "--method",
                "--scenario", "--seed", "--out", "--intervals", "--steps-per-interval",
                "--attach", "--lcm-url", "--prefix", "--resume", "--ppo-learning-rate"):
        assert opt in text
    cfg, ppo = parse_args(["--no-offline", "--method", "ppo", "--ppo-learning-rate",
                           "0.01", "--ppo-trunk-sizes", "32", "32"])
    assert cfg.offline is False and cfg.method == "ppo"
    assert ppo.learning_rate == 0.01 and ppo.trunk_sizes == (32, 32)
    cfg, ppo = parse_args(["--method", "ppo-robust", "--ppo-learning-rate", "0.02"])
    assert cfg.method == "ppo-robust" and ppo.learning_rate == 0.02


def test_background_offline_swaps_in_improved_policies(tmp_path, scenarios):
    cfg = _short(tmp_path, intervals=3, link="core", offline_mode="background",
                 scenario=str(scenarios / "single.toml"))
    ctrl = Controller(cfg, PPOConfig())
    rows = ctrl.run()
    assert len(rows) == 3
    # every offline phase finished and was swapped in: interval k's during interval k + 1
    # (at an update boundary, or waited for at its end), the last one at the end of the run
    assert [r["policy_swaps"] for r in rows] == [0, 1, 1]
    assert ctrl.agent.swaps == 3
    assert all(r.get("model_r2") is not None for r in rows)
    table = _rows(tmp_path)
    assert all(t["model_r2"] != "" for t in table)
    assert (tmp_path / "done.json").exists()


def test_background_resume_restarts_the_offline_phase_in_flight(tmp_path, scenarios):
    cfg = _short(tmp_path, intervals=3, link="core", offline_mode="background",
                 scenario=str(scenarios / "single.toml"))
    Controller(cfg, PPOConfig()).run(stop_after=2)
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert state["agent"]["pending"] is not None and state["agent"]["pending"]["interval"] == 1
    cfg, ppo = resume_config(str(tmp_path))
    rows = Controller(cfg, ppo).run()
    assert [r["interval"] for r in rows] == [0, 1, 2]
    assert all(r.get("model_r2") is not None for r in rows)
