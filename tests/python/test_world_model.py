"""The world model and the model environment: pretraining accuracy on the
paper's nominal data set (collected from the C++ core), refitting after
degradation, warm starts that genuinely train, the model environment's
episode rules, the demand estimate, and save/load round trips."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from ftc.learning.model_env import ModelEnv, estimate_demand
from ftc.learning.transitions import Transitions, collect_nominal_dataset, collect_random_episodes
from ftc.learning.world_model import (WorldModel, WorldModelConfig, cross_validated_scores,
                                      evaluate_model)
from ftc.plant import CorePlant
from ftc.plant.reward import reward_torch

# The degraded plant of the refit test: engine E1 with D_E = 5 and tanks 5, 6
# with D_T = 10, at age 5 (intervals). Demand then is
# d1 = 0.05 (1 + 5/5) = 0.10 and d2 = 0.05 m^3/s: 0.15 m^3 per 1 s step.
DEGRADED_TOML = """name = "test-degraded"
tank_factor = [inf, inf, inf, inf, 10.0, 10.0]
engine_factor = [5.0, inf]
"""
DEGRADED_AGE = 5
DEGRADED_DEMAND = 0.05 * (1 + DEGRADED_AGE / 5.0) + 0.05


@pytest.fixture(scope="module")
def nominal() -> Transitions:
    return collect_nominal_dataset(episodes=50, seed=0)


@pytest.fixture(scope="module")
def pretrained(nominal: Transitions) -> tuple[WorldModel, object]:
    model = WorldModel(WorldModelConfig(seed=0))
    report = model.fit(nominal, warm_start=False)
    return model, report


@pytest.fixture(scope="module")
def degraded(tmp_path_factory) -> tuple[Transitions, Transitions]:
    """(refit data, test data) from the degraded plant at age 5: evaluation
    episodes, so the age stays frozen; different seeds, different episodes."""
    path = tmp_path_factory.mktemp("scenario") / "degraded.toml"
    path.write_text(DEGRADED_TOML)
    parts = []
    for seed, episodes in ((1, 12), (2, 6)):
        plant = CorePlant(str(path), seed, start_step=DEGRADED_AGE * 512 + 1)
        parts.append(collect_random_episodes(plant, episodes, seed, evaluation=True))
        plant.close()
    return parts[0], parts[1]


def test_nominal_dataset_is_the_papers(nominal: Transitions):
    # 50 episodes of about 59 steps (fuel for 60 s at 0.1 m^3/s), full tanks at the start.
    assert len(np.unique(nominal.episode)) == 50
    assert len(np.unique(nominal.segments())) == 50
    assert 50 * 55 <= len(nominal) <= 50 * 62
    starts = np.flatnonzero(np.r_[True, nominal.segments()[1:] != nominal.segments()[:-1]])
    np.testing.assert_allclose(nominal.level[starts], 1.0)
    assert set(np.unique(nominal.valves)) == {0, 1}


def test_pretraining_reaches_the_papers_r2_and_beats_persistence(nominal: Transitions):
    scores = cross_validated_scores(nominal, WorldModelConfig(seed=0), folds=3)
    print("nominal 3-fold CV:", scores)
    assert scores["r2"] >= 0.99  # next-level R^2; the paper reports 0.996
    # next-level R^2 is lenient (no dynamics at all scores 0.994): the model must
    # also explain most of the change of level and beat persistence clearly
    # (measured: r2_change 0.62, RMSE 0.0136 m against 0.0271 m).
    assert scores["r2_change"] >= 0.5
    assert scores["one_step_rmse"] <= 0.6 * scores["persistence_rmse"]


def test_refit_after_degradation_lowers_the_error_on_degraded_data(pretrained, degraded):
    model, _ = pretrained
    model = copy.deepcopy(model)
    refit_data, test_data = degraded
    before = evaluate_model(model, test_data)
    report = model.fit(refit_data, warm_start=True)
    after = evaluate_model(model, test_data)
    print("degraded before:", before, "\nafter:", after, "\n", report)
    assert report.warm_start and report.epochs >= 1
    assert after["one_step_rmse"] < 0.8 * before["one_step_rmse"]
    assert after["ten_step_rmse"] < before["ten_step_rmse"]


def test_warm_start_trains_even_after_an_early_stopped_fit(pretrained, nominal):
    model, report = pretrained
    assert report.stopped_early and report.best_epoch < report.epochs
    model = copy.deepcopy(model)
    weights = {k: v.clone() for k, v in model.state_dict().items()}
    cfg = WorldModelConfig(seed=0, max_epochs=15, patience=3)
    refit = model.fit(nominal, cfg, warm_start=True)
    # fresh early stopping: at least `patience` epochs after the first best
    assert refit.epochs >= cfg.patience and refit.best_epoch >= 1
    changed = [k for k in weights if not torch.equal(weights[k], model.state_dict()[k])]
    assert any(k.startswith("net.") for k in changed), "the weights must move"
    assert not any(k.endswith(("_mean", "_std")) for k in changed), \
        "warm starts keep the normalisers"
    # a cold fit recomputes them
    cold = WorldModel(cfg)
    cold.fit(nominal.tail(300), cfg, warm_start=False)
    assert not torch.equal(cold.out_std, model.out_std)


def test_estimate_demand_recovers_the_true_demand(nominal, degraded):
    assert estimate_demand(nominal) == pytest.approx(0.1, rel=0.01)
    assert estimate_demand(degraded[0]) == pytest.approx(DEGRADED_DEMAND, rel=0.03)


def _constant_model(change: float) -> WorldModel:
    """A world model whose every tank changes by ``change`` m per step."""
    model = WorldModel()
    last = model.net[-1]
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.zeros_(last.bias)
    model.out_mean.fill_(change)
    return model


def test_model_env_steps_terminates_and_auto_resets():
    # -0.0625 m per tank per step from full: volume 6 - 0.375 k (exact in binary);
    # with demand 0.375 the episode is terminal after step 15 (volume 0.375 < 0.375 + 1e-6).
    n = 8
    env = ModelEnv(_constant_model(-0.0625), n, demand_per_step=0.375, max_episode_steps=100)
    obs = env.reset()
    assert obs.shape == (n, 6) and torch.all(obs == 1.0)
    env.level[:2] = 0.05  # two envs nearly empty: they end at their first step
    actions = torch.zeros(n, 6)
    actions[:, 0] = 1
    out = env.step(actions)
    assert out.obs.shape == out.final_obs.shape == (n, 6)
    assert out.reward.shape == out.terminal.shape == out.truncated.shape == (n,)
    assert out.terminal.dtype == out.truncated.dtype == torch.bool
    assert out.terminal.tolist() == [True, True] + [False] * (n - 2)
    assert not out.truncated.any()
    assert torch.all(out.final_obs[:2] == 0.0)  # clipped at empty, before the reset
    assert torch.all(out.obs[:2] == 1.0) and torch.all(out.obs[2:] == 0.9375)
    torch.testing.assert_close(out.reward, reward_torch(out.final_obs, actions))
    for k in range(2, 16):
        out = env.step(actions)
        assert out.terminal[2:].tolist() == [k == 15] * (n - 2), k
    torch.testing.assert_close(out.final_obs[2:], torch.full((n - 2, 6), 0.0625))
    assert torch.all(out.obs[2:] == 1.0) and torch.all(env.steps[2:] == 0)


def test_model_env_truncates_at_max_episode_steps():
    env = ModelEnv(_constant_model(-0.01), 4, demand_per_step=0.1, max_episode_steps=10)
    env.reset()
    for k in range(1, 11):
        out = env.step(torch.ones(4, 6, dtype=torch.int64))
        assert out.truncated.tolist() == [k == 10] * 4 and not out.terminal.any()
    torch.testing.assert_close(out.final_obs, torch.full((4, 6), 0.9))
    assert torch.all(out.obs == 1.0)
    with pytest.raises(ValueError):
        env.step(torch.ones(3, 6))


def test_model_env_clips_predictions_to_the_tanks():
    env = ModelEnv(_constant_model(+0.3), 2, demand_per_step=0.1)
    env.reset()
    assert torch.all(env.step(torch.zeros(2, 6)).obs == 1.0)


def test_transitions_and_model_round_trip(tmp_path, pretrained, nominal):
    path = tmp_path / "data.npz"
    nominal.save_npz(path)
    loaded = Transitions.load_npz(path)
    for name in ("level", "valves", "next_level", "episode"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(nominal, name))
        assert getattr(loaded, name).dtype == getattr(nominal, name).dtype
    both = Transitions.concat([nominal, loaded])
    assert len(both) == 2 * len(nominal)
    assert len(np.unique(both.segments())) == 100  # same ids, still two runs each

    model, _ = pretrained
    torch.save(model.state_dict(), tmp_path / "model.pt")
    clone = WorldModel(model.config)
    clone.load_state_dict(torch.load(tmp_path / "model.pt", weights_only=True))
    assert bool(clone.fitted)
    x, u = torch.as_tensor(nominal.level[:50]), torch.as_tensor(nominal.valves[:50])
    with torch.no_grad():
        torch.testing.assert_close(clone.predict(x, u), model.predict(x, u))
