"""The batched plant pool (ftc._core.PlantPool, ftc.plant.vector): each env follows
the single env (FuelTransferEnv on the in-process core) step for step, ages as it
does, autoresets as its metadata says, refuses bad input before stepping, and
draws its scenarios from a declared, seeded distribution."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import ftc
from ftc import _core
from ftc.experiments.suite import write_suite
from ftc.plant.env import FuelTransferEnv
from ftc.plant.vector import FuelTransferVectorEnv

SCENARIOS = ftc.REPO_ROOT / "scenarios"
# Abrupt faults and noise early enough for short runs (intervals of 64 steps):
# a factor jump, a stuck-open and a stuck-closed valve, sensor noise.
EVENTS = """
name = "events"
tank_factor = [inf, 12.0, inf, inf, inf, inf]
engine_factor = [20.0, inf]
steps_per_interval = 64
[noise]
std = 0.01
[[event]]
at_step = 70
engine = 2
factor = 3.0
[[event]]
at_step = 100
stuck_valve = 4
state = "open"
[[event]]
at_step = 150
stuck_valve = 1
state = "closed"
"""


def _short(path: Path, tmp: Path) -> Path:
    """The scenario with intervals of 64 steps (so a short run ages several times)."""
    text = path.read_text().replace("steps_per_interval = 512", "steps_per_interval = 64")
    out = tmp / f"{path.parent.name}-{path.name}"
    out.write_text(text)
    return out


def _scenario_files(tmp: Path) -> list[Path]:
    """Every scenario of the suite (scenarios/, scenarios/check/ and the benchmark's
    22) with 64-step intervals, and the events file."""
    files = [_short(p, tmp) for p in sorted(SCENARIOS.glob("*.toml"))]
    files += [_short(p, tmp) for p in sorted((SCENARIOS / "check").glob("*.toml"))]
    suite = tmp / "suite"
    suite.mkdir()
    files += write_suite(suite, steps_per_interval=64)
    (tmp / "events.toml").write_text(EVENTS)
    return files + [tmp / "events.toml"]


def _single_trajectory(path: Path, seed: int, actions: np.ndarray, method: str = "cvode"):
    """What the pool's env should produce (NEXT_STEP autoreset) from the single env:
    after a finished episode, the next step is a reset (reward 0, not done)."""
    if method == "cvode":
        env = FuelTransferEnv(str(path), link="core", plant_seed=seed)
    else:  # the same env driving a closed-form plant: the plant link is the only change
        from ftc.plant.link import CorePlant

        link = CorePlant(str(path), seed)
        link._plant = _core.Plant(link.scenario, seed, method=method)
        env = FuelTransferEnv(str(path), link=link)
    obs, info = env.reset()
    rows, done = [], False
    for a in actions:
        if done:
            obs, info = env.reset()
            r, term, trunc = 0.0, False, False
        else:
            obs, r, term, trunc, info = env.step(a)
        done = term or trunc
        rows.append((obs, r, term, trunc, info["age"], env._last[0].valves))  # as published
    return tuple(np.array([x[k] for x in rows]) for k in range(6))


def _pool_trajectory(env: FuelTransferVectorEnv, actions: np.ndarray):
    env.reset()
    out = [env.step(a) for a in actions]
    return (np.array([o[0] for o in out]), np.array([o[1] for o in out]),
            np.array([o[2] for o in out]), np.array([o[3] for o in out]),
            np.array([o[4]["age"] for o in out]), np.array([o[4]["valves"] for o in out]))


def _random_actions(steps: int, n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 2, (steps, n, 6), dtype=np.int8)


@pytest.mark.parametrize("method", ["cvode", "closed_form"])
def test_each_env_is_the_single_env_bit_for_bit_on_every_suite_scenario(tmp_path, method):
    # The same integrator in both: the pool's env is the same Plant, driven the same
    # way, so every observation, reward, flag, age and applied valve is identical (==,
    # no tolerance), over 200 steps = 3 intervals of aging, with events, stuck valves
    # and noise.
    files = _scenario_files(tmp_path)
    actions = _random_actions(200, len(files))
    pool = FuelTransferVectorEnv(len(files), [str(f) for f in files], plant_seed=7,
                                 method=method, threads=2)
    got = _pool_trajectory(pool, actions)
    assert got[2].sum() > 0 and got[3].sum() > 0  # episodes ended both ways
    events = files.index(tmp_path / "events.toml")  # valve 4 stuck open overrode "closed"
    assert ((got[5][:, events, 3] == 1) & (actions[:, events, 3] == 0)).any()
    for i, path in enumerate(files):
        want = _single_trajectory(path, 7 + i, actions[:, i], method)
        for g, w, what in zip(got, want, ("obs", "reward", "terminated", "truncated", "age",
                                          "applied valves")):
            np.testing.assert_array_equal(g[:, i], w, err_msg=f"{path.name}: {what}")


def test_closed_form_stays_within_the_stated_tolerance_of_cvode(tmp_path):
    # The closed form is exact where CVODE is within its tolerances (rtol 1e-8,
    # atol 1e-10: 2.5e-8 m per step measured in integrator.cpp); over 640 steps (10
    # intervals: pumps die, demand outgrows them, tied groups split and rejoin) the
    # two trajectories' levels stay within 1e-6 m and their episodes end at the same
    # steps. (docs/benchmarks.md quotes the maximum measured over the suite.)
    files = _scenario_files(tmp_path)
    actions = _random_actions(640, len(files), seed=1)
    cvode, closed = (_pool_trajectory(FuelTransferVectorEnv(
        len(files), [str(f) for f in files], method=m, threads=2), actions)
        for m in ("cvode", "closed_form"))
    np.testing.assert_array_equal(cvode[2], closed[2])
    np.testing.assert_array_equal(cvode[3], closed[3])
    assert np.abs(cvode[0] - closed[0]).max() < 1e-6
    assert np.abs(cvode[1] - closed[1]).max() < 1e-5  # the reward moves ~10x the levels
    assert np.abs(cvode[0] - closed[0]).max() > 0  # not the same code path by accident


def test_the_rejoin_after_a_near_tie_is_found_by_cvode(tmp_path):
    # check/noise-10.toml under the test above's actions (its env, seed 7) reaches, at
    # step 563, a tank that falls onto a group, leaves the tie at once (its draw
    # outruns the group by 1.6e-4, relative) and should rejoin it 1.56 ms later after
    # a dip of ~1e-9 m. While the rejoin root was the tank's gap below the group,
    # starting in the levels' rounding noise, CVODE restarted with the tank one ulp
    # above the group, never saw the root and left the tank 4e-4 m above the group:
    # 9.7e-5 m from the closed form at the end of that step. The root is now the
    # leave condition itself (dynamics.cpp, RootsOf; tests/cpp/test_integrator.cpp
    # scans the mechanism). The trajectories agree within 1e-6 m, as everywhere.
    files = _scenario_files(tmp_path)
    assert files[7].name == "check-noise-10.toml"  # the env the defect was found in
    actions = _random_actions(640, len(files), seed=1)[:, 7:8]
    cvode, closed = (_pool_trajectory(FuelTransferVectorEnv(
        1, [str(files[7])], method=m, plant_seed=7), actions) for m in ("cvode", "closed_form"))
    assert np.abs(cvode[0][563] - closed[0][563]).max() < 1e-6  # the step of the defect
    assert np.abs(cvode[0] - closed[0]).max() < 1e-6


def test_thread_count_does_not_change_results():
    actions = _random_actions(150, 96, seed=2)
    one, two = (_pool_trajectory(FuelTransferVectorEnv(96, "multiple", threads=t), actions)
                for t in (1, 2))
    for a, b in zip(one, two):
        np.testing.assert_array_equal(a, b)


def test_envs_age_one_interval_every_steps_per_interval_operating_steps(tmp_path):
    path = _short(SCENARIOS / "single.toml", tmp_path)
    env = FuelTransferVectorEnv(3, str(path))
    env.reset()
    ages, steps = [], 0
    closed = np.zeros((3, 6), np.int8)
    for _ in range(200):
        _, _, term, trunc, info = env.step(closed)
        ages.append(info["age"].copy())
    # truncation at 64, 128, 192 (all-closed episodes last 59 steps at age 0 and
    # shorter as E1 wears): the age in force is floor(operating steps / 64)
    assert {float(a[0]) for a in ages} == {0.0, 1.0, 2.0, 3.0}
    assert env.pool.operating_steps(0) < 200  # reset steps are not operating steps
    assert env.pool.operating_steps(0) == env.pool.operating_steps(2)


def test_next_step_autoreset_resets_on_the_step_after_the_end_and_ignores_its_action():
    env = FuelTransferVectorEnv(2, "nominal")
    assert env.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    env.reset()
    closed = np.zeros((2, 6), np.int8)
    for t in range(59):  # the nominal all-closed episode: 59 steps (plant-model.md)
        _, _, term, _, _ = env.step(closed)
        assert term.all() == (t == 58)
    obs, reward, term, trunc, info = env.step(np.ones((2, 6), np.int8))  # ignored
    np.testing.assert_array_equal(obs, np.ones((2, 6), np.float32))
    assert (reward == 0).all() and not term.any() and not trunc.any()
    assert (info["step"] == 0).all() and (info["activity"] == 0).all()
    _, reward, _, _, info = env.step(closed)
    assert (info["step"] == 1).all() and (reward > 2.0).all()


def test_same_step_autoreset_returns_the_new_episode_and_the_final_observation():
    nxt = FuelTransferVectorEnv(2, "nominal")
    same = FuelTransferVectorEnv(2, "nominal", autoreset="same_step")
    assert same.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    nxt.reset(), same.reset()
    closed = np.zeros((2, 6), np.int8)
    for _ in range(58):
        a, b = nxt.step(closed), same.step(closed)
        np.testing.assert_array_equal(a[0], b[0])
        assert "final_obs" not in b[4]
    last, ended = nxt.step(closed), same.step(closed)
    assert ended[2].all() and last[2].all()
    np.testing.assert_array_equal(ended[4]["final_obs"], last[0])
    assert ended[4]["_final_obs"].all()
    np.testing.assert_array_equal(ended[0], np.ones((2, 6), np.float32))  # the new episode
    nxt.step(closed)  # nxt's reset step
    np.testing.assert_array_equal(nxt.step(closed)[0], same.step(closed)[0])


@pytest.mark.parametrize("actions, message", [
    (np.zeros((3, 6), np.int8), r"shape \(4, 6\), got \(3, 6\)"),
    (np.zeros((4, 5), np.int8), r"shape \(4, 6\), got \(4, 5\)"),
    (np.full((4, 6), 2, np.int8), "0 or 1, got 2 at env 0, valve 0"),
    (np.full((4, 6), 256, np.int64), "0 or 1, got 256 at env 0, valve 0"),
    (np.where(np.eye(4, 6) > 0, np.nan, 0.0), "NaN at env 0, valve 0"),
    (np.full((4, 6), 0.5), "0 or 1, got 0.5"),
    (np.full((4, 6), "1"), "dtype <U1"),
])
def test_bad_actions_are_refused_in_one_line_and_step_nothing(actions, message):
    env, twin = FuelTransferVectorEnv(4, "single"), FuelTransferVectorEnv(4, "single")
    env.reset(), twin.reset()
    good = _random_actions(5, 4, seed=3)
    env.step(good[0]), twin.step(good[0])
    with pytest.raises(ValueError, match=message) as e:
        env.step(actions)
    assert "\n" not in str(e.value)
    for a in good[1:]:  # nothing moved: the env goes on exactly as its twin
        np.testing.assert_array_equal(env.step(a)[0], twin.step(a)[0])


def test_the_core_pool_checks_its_buffers_and_actions():
    pool = _core.PlantPool([_core.Scenario()] * 2, [0, 1])
    n = np.zeros(2)
    arrays = [np.zeros((2, 6), np.float32), n.copy(), np.zeros(2, bool), np.zeros(2, bool),
              n.copy(), np.zeros(2, np.int64), n.copy(), n.copy(), n.copy(),
              np.zeros((2, 6), np.float32), np.zeros(2, bool)]
    with pytest.raises(ValueError, match="bind_outputs"):
        pool.reset()
    bad = list(arrays)
    bad[1] = np.zeros(2, np.float32)
    with pytest.raises(ValueError, match="reward must be float64 of shape \\(2,\\), got float32"):
        pool.bind_outputs(*bad)
    bad[1] = np.zeros((2, 6))[:, 0]
    with pytest.raises(ValueError, match="reward must be C-contiguous"):
        pool.bind_outputs(*bad)
    pool.bind_outputs(*arrays)
    pool.reset()
    with pytest.raises(ValueError, match="int8 of shape \\(2, 6\\), got int64"):
        pool.step(np.zeros((2, 6), np.int64))
    with pytest.raises(ValueError, match="method must be"):
        _core.PlantPool([_core.Scenario()], [0], method="euler")
    with pytest.raises(ValueError, match="2 scenarios and 1 seeds"):
        _core.PlantPool([_core.Scenario()] * 2, [0])


def test_distribution_draws_are_seeded_in_range_and_checked():
    d = _core.ScenarioDistribution(tank_probability=0.3, tank_factor=[8.0, 20.0],
                                   engine_probability=0.5, dead_pump_probability=0.2,
                                   event_probability=0.3, stuck_valve_probability=0.25,
                                   noise_probability=0.5, noise_std=[0.001, 0.01])
    a, b = d.draw(2000, 5), d.draw(2000, 5)
    assert [repr(s) for s in a] == [repr(s) for s in b]
    assert [repr(s) for s in a] != [repr(s) for s in d.draw(2000, 6)]
    tanks = np.array([s.tank_factor for s in a])
    worn = np.isfinite(tanks)
    # binomial fractions within 5 standard deviations (sqrt(p(1-p)/n) ~ 0.004 per tank)
    assert abs(worn.mean() - 0.3) < 5 * np.sqrt(0.3 * 0.7 / worn.size)
    assert tanks[worn].min() >= 8.0 and tanks[worn].max() <= 20.0
    stuck = [e for s in a for e in s.events if "stuck_valve" in e]
    dead = [e for s in a for e in s.events if e.get("factor") == 1e-3]
    assert abs(len(stuck) / 2000 - 0.25) < 5 * np.sqrt(0.25 * 0.75 / 2000)
    assert abs(len(dead) / 2000 - 0.2) < 5 * np.sqrt(0.2 * 0.8 / 2000)
    assert all(512 <= e["at_step"] < 5120 for e in dead)
    for s in a:
        d.check(s)  # every draw is one the distribution declares


@pytest.mark.parametrize("fields, message", [
    ({"tank_probability": 1.5}, "tank_probability must be in \\[0, 1\\], got 1.5"),
    ({"tank_factor": [30.0, 6.0]}, "tank_factor must be a finite \\[low, high\\]"),
    ({"engine_factor": [0.0, 6.0]}, "engine_factor must be >= 0.001"),
    ({"noise_std": [-1.0, 0.0]}, "noise_std must be >= 0"),
    ({"life_intervals": 0}, "life_intervals must be >= 1"),
    ({"colour": 1}, "unknown field 'colour'"),
])
def test_bad_distributions_are_refused_in_one_line(fields, message):
    with pytest.raises(ValueError, match=message) as e:
        _core.ScenarioDistribution(**fields)
    assert "\n" not in str(e.value)


def test_a_scenario_outside_the_declared_ranges_is_refused():
    d = _core.ScenarioDistribution(tank_factor=[10.0, 30.0])
    s = _core.load_scenario(str(SCENARIOS / "check" / "deadpump.toml"))  # D_T = 8 on tank 1
    with pytest.raises(ValueError, match=r"tank_factor\[0\] = 8 is outside the declared range "
                                         r"\[10, 30\]"):
        d.check(s)
    s.tank_factor = [float("inf")] * 6
    s.engine_factor = [12.0, float("inf")]
    d.check(s)
    s.noise_std = 0.01  # the default distribution draws no noise
    with pytest.raises(ValueError, match="noise_std = 0.01 is outside"):
        d.check(s)


def test_a_distribution_pool_draws_its_scenarios_and_renews_plants_after_their_life():
    d = {"steps_per_interval": 32, "life_intervals": 2, "tank_probability": 0.5}
    env = FuelTransferVectorEnv(8, d, plant_seed=3)
    drawn = _core.ScenarioDistribution(**d).draw(8, 3)
    assert [repr(env.pool.scenario(i)) for i in range(8)] == [repr(s) for s in drawn]
    env.reset()
    closed = np.zeros((8, 6), np.int8)
    for _ in range(150):  # past 64 operating steps: each plant renewed at least once
        env.step(closed)
    assert all(env.pool.operating_steps(i) < 64 for i in range(8))
    assert [repr(env.pool.scenario(i)) for i in range(8)] != [repr(s) for s in drawn]
    first = [repr(env.pool.scenario(i)) for i in range(8)]
    env.reset(seed=3)  # fresh plants, the same draw again
    assert [repr(env.pool.scenario(i)) for i in range(8)] == [repr(s) for s in drawn]
    assert first != [repr(s) for s in drawn]


def test_make_vec_gives_the_pool_for_both_ids_in_a_fresh_interpreter():
    code = """
import gymnasium as gym, numpy as np
for env_id in ("ftc:ftc/FuelTransfer-v0", "ftc:ftc/FuelTransferCore-v0"):
    env = gym.make_vec(env_id, num_envs=4, vectorization_mode="vector_entry_point",
                       scenario="multiple")
    obs, info = env.reset(seed=0)
    obs, r, term, trunc, info = env.step(env.action_space.sample())
    print(type(env).__name__, obs.shape, r.dtype, env.single_action_space,
          env.metadata["autoreset_mode"].name)
"""
    out = subprocess.run([sys.executable, "-W", "error", "-c", code], capture_output=True,
                         text=True, check=True, timeout=120).stdout.split("\n")
    for line in out[:2]:
        assert line == "FuelTransferVectorEnv (4, 6) float64 MultiBinary(6) NEXT_STEP"


def test_sb3_ppo_collects_through_the_adapter_the_pools_own_steps():
    # PPO's rollout buffer holds exactly what the pool gives for the actions PPO
    # took: replayed on a fresh pool, every reward matches (float32, as SB3 stores).
    import torch
    from stable_baselines3 import PPO

    from ftc.plant.sb3_vec import PoolVecEnv

    torch.set_num_threads(1)
    venv = PoolVecEnv(num_envs=8, scenario="single", plant_seed=0)
    model = PPO("MlpPolicy", venv, n_steps=80, batch_size=640, n_epochs=1, seed=0, device="cpu")
    model.learn(80 * 8)
    buf = model.rollout_buffer
    # the update flattened the actions env-major: back to (steps, envs, 6)
    actions = buf.actions.reshape(8, 80, 6).transpose(1, 0, 2).astype(np.int8)
    replay = FuelTransferVectorEnv(8, "single", plant_seed=0, autoreset="same_step")
    replay.reset()
    rewards = np.array([replay.step(a)[1] for a in actions], np.float32)
    np.testing.assert_array_equal(rewards, buf.rewards)
    assert buf.episode_starts[1:].sum() > 0  # episodes ended (and SB3 saw them end)


def test_the_adapters_arrays_are_its_own_and_match_a_same_step_pool(tmp_path):
    # PoolVecEnv's pool hands over its own arrays, overwritten by the next step;
    # what SB3 keeps (the observation, each terminal observation) must be copies:
    # after the next step they still equal what a copy=True pool returned.
    from ftc.plant.sb3_vec import PoolVecEnv

    path = str(_short(SCENARIOS / "single.toml", tmp_path))
    venv = PoolVecEnv(num_envs=4, scenario=path, plant_seed=3)
    twin = FuelTransferVectorEnv(4, path, plant_seed=3, autoreset="same_step")
    kept, ends = [venv.reset()], 0
    np.testing.assert_array_equal(kept[0], twin.reset()[0])
    for a in _random_actions(150, 4, seed=5).astype(np.float32):  # SB3 hands floats
        obs, reward, dones, infos = venv.step(a)
        want_obs, want_r, term, trunc, info = twin.step(a)
        np.testing.assert_array_equal(reward, want_r.astype(np.float32))
        np.testing.assert_array_equal(dones, term | trunc)
        for i in np.flatnonzero(dones):
            ends += 1
            assert infos[i]["TimeLimit.truncated"] == bool(trunc[i])
            kept.append(infos[i]["terminal_observation"])
            kept.append(info["final_obs"][i])
        kept.append(obs)
        kept.append(want_obs)
    assert ends > 4  # episodes ended (64-step intervals)
    for ours, theirs in zip(kept[1::2], kept[2::2]):
        np.testing.assert_array_equal(ours, theirs)


@pytest.mark.slow
def test_sb3_ppo_learns_to_close_the_valves_of_healthy_plants_through_the_adapter():
    # Healthy plants: all valves closed is optimal (plant-model.md: 2.690 per step
    # against 1.393 all open), and the activity penalty pays at once for every
    # closed valve. Untrained, the policy opens about half; after 64 envs x 1,536
    # steps it must open under a quarter of them, deterministically. (A threshold
    # with a wide margin, not a figure measured on one machine.)
    import torch
    from stable_baselines3 import PPO

    from ftc.plant.sb3_vec import PoolVecEnv

    torch.set_num_threads(1)
    venv = PoolVecEnv(num_envs=64, scenario="nominal")
    model = PPO("MlpPolicy", venv, n_steps=64, batch_size=1024, learning_rate=1e-3, gamma=0.9,
                seed=0, device="cpu")
    obs = venv.reset()
    before = model.predict(obs, deterministic=False)[0].mean()
    model.learn(64 * 1536)
    after = model.predict(venv.reset(), deterministic=True)[0].mean()
    assert before > 0.35 and after < 0.25


@pytest.mark.slow
def test_train_vector_example_runs_and_writes_its_curve(tmp_path):
    out = tmp_path / "curve.csv"
    done = subprocess.run(
        [sys.executable, str(ftc.REPO_ROOT / "examples" / "train_vector.py"), "--minutes",
         "0.1", "--envs", "16", "--n-steps", "32", "--eval-envs", "2", "--life", "2",
         "--tensorboard", str(tmp_path / "tb"), "--results", str(out)],
        capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "held-out plants (2 x 2 intervals)" in done.stdout
    rows = [r for r in out.read_text().splitlines() if not r.startswith("#")]
    assert rows[0] == "steps,seconds,reward_per_step" and len(rows) >= 2  # a rollout at least
    assert any((tmp_path / "tb").rglob("events.out.tfevents.*"))
    bad = subprocess.run([sys.executable, str(ftc.REPO_ROOT / "examples" / "train_vector.py"),
                          "--envs", "0"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--envs: must be > 0" in bad.stderr
