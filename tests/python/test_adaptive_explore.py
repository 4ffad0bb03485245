"""The training's perturbations (TrainingConfig.explore): random valve settings
held in place of the student's commands, in the plants the student drives only,
so that the teacher labels states off both their paths (docs/adaptive.md)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from ftc.experiments.adaptive import dagger, distribution
from ftc.control.planning.physics.teacher import PoolTeacher
from ftc.learning.history_policy import HistoryPolicy, TrainingConfig


def perturbation(envs: int, explore: float, hold: int, eligible=None, seed: int = 0):
    config = TrainingConfig(explore=explore, explore_hold=hold, seed=seed)
    mask = np.ones(envs, bool) if eligible is None else eligible
    return dagger.Perturbation(config, iteration=1, eligible=mask)


def test_a_perturbation_holds_one_random_setting_for_at_most_explore_hold_steps():
    envs, hold, steps = 32, 5, 3000
    p = perturbation(envs, 0.05, hold)
    commands = np.full((envs, 6), 7, np.int8)  # never a valve value: tells a perturbed step
    lengths, perturbed, previous = [], 0, commands
    for _ in range(steps):
        left = p.left.copy()  # steps each running perturbation still holds
        u = commands.copy()
        p.apply(u)
        on = (u != 7).all(axis=1)
        assert ((u == 7).all(axis=1) | on).all()  # a plant is perturbed whole or not at all
        going = left > 0
        assert on[going].all() and (u[going] == previous[going]).all()  # held, unchanged
        began = on & ~going
        lengths += list(p.left[began] + 1)  # this step and the steps still to hold
        perturbed += int(on.sum())
        previous = u
    assert set(lengths) == set(range(1, hold + 1))  # every length 1..hold, none longer
    assert p.steps == perturbed


def test_the_perturbed_share_is_the_renewal_share_and_the_settings_are_uniform():
    # A plant free of a perturbation begins one with chance c per step (that
    # step is perturbed already) and it lasts m = (hold + 1) / 2 steps on
    # average: a renewal process of (1 - c) / c free steps, then m perturbed
    # ones, so the share of perturbed steps is c m / (1 - c + c m), 0.356 here.
    # NumPy's generator is the same on every machine: the share measured is the
    # same everywhere; the bound, 0.01, is four times the share's spread between
    # seeds (0.351 to 0.358 over seeds 0 to 5, standard deviation 0.0023).
    envs, c, hold, steps = 64, 0.05, 20, 4000
    p = perturbation(envs, c, hold)
    seen = []
    for _ in range(steps):
        u = np.full((envs, 6), 7, np.int8)
        p.apply(u)
        seen.append(u[(u != 7).all(axis=1)])
    m = (hold + 1) / 2
    assert p.steps / (envs * steps) == pytest.approx(c * m / (1 - c + c * m), abs=0.01)
    settings = np.concatenate(seen)
    assert set(np.unique(settings)) == {0, 1}
    # every valve open about half the time (the 8,000-odd perturbations: 0.5 +- 0.02)
    assert np.abs(settings.mean(axis=0) - 0.5).max() < 0.05


def test_only_the_eligible_plants_are_perturbed_and_a_finished_episode_ends_its_perturbation():
    eligible = np.array([True, False, True, False])
    p = perturbation(4, 1.0, 50, eligible)  # chance 1: a perturbation begins at once
    u = np.full((4, 6), 7, np.int8)
    p.apply(u)
    assert (u[~eligible] == 7).all() and (u[eligible] != 7).all()
    p.end(np.array([True, False, False, False]))
    assert p.left[0] == 0 and p.left[2] > 0


def tiny_config(**kw) -> TrainingConfig:
    """A tiny training, without perturbations unless ``kw`` asks for them."""
    return TrainingConfig(**{"envs": 4, "life_intervals": 1, "window": 2, "hidden": (8,),
                             "hold": 2, "horizon": 3, "extra_holds": (), "recheck": 0,
                             "recheck_rule": "closed", "members": 1, "explore": 0.0, **kw})


def rollouts(config: TrainingConfig, beta: float) -> dict:
    torch.manual_seed(0)
    policy = HistoryPolicy(config.student())
    return dagger.collect(policy, PoolTeacher.from_config(config), distribution.load(), config,
                          1, beta)


def test_the_teachers_plants_and_every_other_draw_are_untouched_by_the_perturbations(
        one_torch_thread):
    plain = tiny_config()
    explored = dataclasses.replace(plain, explore=0.05, explore_hold=16)
    # all four plants driven by the teacher: nothing to perturb, the same data
    a, b = rollouts(plain, 1.0), rollouts(explored, 1.0)
    assert a["perturbed"] is None and b["perturbed"] == 0.0
    assert np.array_equal(a["x"], b["x"]) and np.array_equal(a["y"], b["y"])
    # half of them the student's: those are perturbed, and their states change
    c, d = rollouts(plain, 0.5), rollouts(explored, 0.5)
    # two of four plants eligible: about half of 0.05 x 8.5 / (0.95 + 0.05 x 8.5), 0.15
    assert 0.05 < d["perturbed"] < 0.25
    assert not np.array_equal(c["x"], d["x"])
    # the same states labelled (the label draws are not the perturbations'): as many
    assert len(c["x"]) == len(d["x"])


def test_bad_perturbation_options_are_one_clear_error(tmp_path, capsys):
    from ftc.experiments.adaptive.cli import main

    assert TrainingConfig().explore == 0.004 and TrainingConfig().explore_hold == 64  # default
    for bad in ({"explore": -0.1}, {"explore": 1.5}, {"explore_hold": 0}):
        with pytest.raises(ValueError, match="explore must be in"):
            TrainingConfig(**bad)
    assert main(["train", "--explore", "2", "--cache", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("adaptive: error: ")
    assert not list(tmp_path.iterdir())
