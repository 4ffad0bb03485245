"""The plant as a Gymnasium citizen: the registered ids (made with and without a
prior ``import ftc``), gymnasium's env checker with no warnings for both links,
rgb_array frames that show the state, seeded resets, AsyncVectorEnv with one
private plant per worker and nothing left running afterwards, and one-line
errors for bad input. Every LCM plant is a real process on a private port."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import ftc  # noqa: F401  (registers the ids)
from ftc.plant.env import FuelTransferEnv
from ftc.plant.render import CG_RGB, FUEL_RGB, OPEN_VALVE_RGB, draw_plant

IDS = ("ftc/FuelTransfer-v0", "ftc/FuelTransferCore-v0")
CLOSED = np.zeros(6, dtype=np.int8)


def _subprocess_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ftc.REPO_ROOT / "python"),
                                         env.get("PYTHONPATH", "")])
    return env


def test_module_prefixed_id_works_in_a_fresh_interpreter_with_the_single_fault():
    # No prior import of ftc: gymnasium imports it for "ftc:...". The default
    # scenario must be the paper's single fault: after one 512-step interval with
    # valves closed, E1 (left wing) burns 5% more, so the right wing is heavier
    # (cg > 0) late in the next episode; on the nominal plant cg stays 0.
    code = textwrap.dedent("""
        import sys
        import gymnasium as gym
        assert "ftc" not in sys.modules
        env = gym.make("ftc:ftc/FuelTransfer-v0")
        assert env.spec.max_episode_steps == 512, env.spec
        env.reset(seed=0)
        truncated_at = None
        for t in range(1, 600):
            _, _, terminated, truncated, info = env.step([0] * 6)
            if truncated:
                truncated_at = t
                break
            if terminated:
                env.reset()
        assert truncated_at is not None and info["age"] == 0.0
        env.reset()
        cgs = []
        while True:
            _, _, terminated, truncated, info = env.step([0] * 6)
            cgs.append(info["cg"])
            if terminated or truncated:
                break
        env.close()
        print(truncated_at, info["age"], max(cgs))
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env=_subprocess_env())
    assert proc.returncode == 0, proc.stderr[-2000:]
    truncated_at, age, max_cg = proc.stdout.split()
    assert int(truncated_at) == 512  # 8 full 59-step episodes, then cut off at the boundary
    assert float(age) == 1.0
    assert float(max_cg) > 0.01


@pytest.mark.parametrize("env_id", IDS)
def test_env_checker_passes_with_no_warnings(env_id):
    # check_env on the unwrapped env (as gymnasium asks), with the spec that
    # gym.make gives it, so it also remakes the env for every render mode and
    # closes one twice; the passive checker of gym.make's own wrappers runs too.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        env = gym.make(env_id, render_mode="rgb_array")
        try:
            check_env(env.unwrapped)
            env.reset(seed=1)
            env.step(env.action_space.sample())
            assert env.render().shape == (400, 640, 3)
        finally:
            env.close()
    assert [str(w.message) for w in caught] == []


@pytest.mark.quick  # the fast tier's integration of this boundary
def test_both_links_give_the_same_trajectory_and_seeded_resets_repeat_it(scenarios):
    # A noisy scenario, so the seed matters: reset(seed=s) starts a fresh plant
    # seeded s on either link, identical to the bit; another seed differs.
    noisy = str(scenarios.parent / "tests" / "data" / "noisy_multiple.toml")
    rng = np.random.default_rng(5)
    actions = rng.integers(0, 2, (40, 6)).astype(np.int8)

    def run(env: gym.Env, seed: int) -> np.ndarray:
        obs = [env.reset(seed=seed)[0]]
        obs += [env.step(a)[0] for a in actions]
        return np.array(obs)

    lcm = gym.make("ftc/FuelTransfer-v0", scenario=noisy)
    core = gym.make("ftc/FuelTransferCore-v0", scenario=noisy)
    try:
        a = run(lcm, 7)
        np.testing.assert_array_equal(a, run(core, 7))
        np.testing.assert_array_equal(a, run(lcm, 7))
        assert not np.array_equal(a, run(lcm, 8))
    finally:
        lcm.close()
        core.close()


def _fuel_bands(frame: np.ndarray) -> list[int]:
    """Fuel-coloured pixels of each tank, left to right (tanks are separate
    column bands of the frame)."""
    fuel = np.all(frame == FUEL_RGB, axis=-1)
    cols = np.flatnonzero(fuel.any(axis=0))
    bands = np.split(cols, np.flatnonzero(np.diff(cols) > 1) + 1)
    return [int(fuel[:, band].sum()) for band in bands]


def test_frame_shows_levels_valves_and_centre_of_gravity():
    full = np.ones(6)
    levels = np.array([1.0, 0.8, 0.6, 0.4, 0.2, 0.9])
    frame_full = draw_plant(full, CLOSED, 0.0)
    assert frame_full.shape == (400, 640, 3) and frame_full.dtype == np.uint8
    # fuel drawn in proportion to each level (1-pixel rounding at the edges)
    assert len(_fuel_bands(frame_full)) == 6
    ratio = np.array(_fuel_bands(draw_plant(levels, CLOSED, 0.0))) / _fuel_bands(frame_full)
    np.testing.assert_allclose(ratio, levels, atol=0.02)
    # an open valve is drawn under its own tank only
    assert not np.all(frame_full == OPEN_VALVE_RGB, axis=-1).any()
    opened = np.array([0, 0, 0, 0, 1, 0], dtype=np.int8)
    green = np.all(draw_plant(full, opened, 0.0) == OPEN_VALVE_RGB, axis=-1)
    fuel_cols = np.flatnonzero(np.all(frame_full == FUEL_RGB, axis=-1).any(axis=0))
    tank5 = np.split(fuel_cols, np.flatnonzero(np.diff(fuel_cols) > 1) + 1)[4]
    green_cols = np.flatnonzero(green.any(axis=0))
    assert green_cols.size > 0 and tank5.min() <= green_cols.mean() <= tank5.max()
    # the cg marker sits left of centre for a heavy left wing, right for the right
    def marker_x(cg: float) -> float:
        return float(np.flatnonzero(np.all(draw_plant(full, CLOSED, cg) == CG_RGB,
                                           axis=-1).any(axis=0)).mean())
    assert marker_x(-1.5) < 320 - 50 < 320 + 50 < marker_x(1.5)


def test_env_frames_follow_the_plant():
    env = gym.make("ftc/FuelTransferCore-v0", render_mode="rgb_array")
    try:
        env.reset(seed=0)
        first = _fuel_bands(env.render())
        assert not np.all(env.render() == OPEN_VALVE_RGB, axis=-1).any()  # all shut
        for _ in range(10):  # tank 3 feeds E1 and takes fuel from tank 1 (both open)
            level, _, _, _, _ = env.step(np.array([1, 0, 1, 0, 0, 0], dtype=np.int8))
        frame = env.render()
        assert np.array_equal(env.render(), frame)  # render does not step
        assert len(set(np.round(level, 2))) >= 3
        np.testing.assert_allclose(np.array(_fuel_bands(frame)) / first, level, atol=0.02)
        assert np.all(frame == OPEN_VALVE_RGB, axis=-1).any()
    finally:
        env.close()
    assert FuelTransferEnv(link="core").render() is None  # no render_mode: nothing drawn


def _alive(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def _make_lcm_env() -> gym.Env:
    return gym.make("ftc/FuelTransfer-v0")


@pytest.mark.parametrize("terminate", [False, True])
def test_async_vector_env_runs_a_private_plant_per_worker(terminate):
    # terminate=True kills the workers without letting them close their envs:
    # the plants must die with them (the parent-death signal), not idle forever.
    vec = gym.vector.AsyncVectorEnv([_make_lcm_env, _make_lcm_env])
    try:
        obs, _ = vec.reset(seed=[0, 1])
        assert obs.shape == (2, 6) and np.all(obs == 1.0)
        pids = vec.get_attr("plant_pid")
        assert len(set(pids)) == 2 and all(_alive(p) for p in pids)
        # worker 0 keeps its valves closed, worker 1 opens tanks 1 and 3 (fuel flows
        # from 1 into 3 as E1 drains 3): after one step the two plants differ
        actions = np.array([CLOSED, [1, 0, 1, 0, 0, 0]], dtype=np.int8)
        ends = np.zeros(2, dtype=int)
        for t in range(130):  # two 59-step episodes each, autoreset in between
            obs, reward, terminated, truncated, info = vec.step(actions)
            ends += terminated
            if t == 0:
                assert not np.array_equal(obs[0], obs[1])
                assert reward[0] - reward[1] == pytest.approx(2 / 6, abs=0.05)
        assert list(ends) == [2, 2]
        obs, _ = vec.reset()  # a reset of both mid-episode: full tanks again
        assert np.all(obs == 1.0) and vec.get_attr("plant_pid") == pids
    finally:
        vec.close(terminate=terminate)
    deadline = time.monotonic() + 5.0  # a killed plant's exit is asynchronous
    while any(_alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not any(_alive(p) for p in pids), "plant processes were left behind"


@pytest.mark.parametrize("kwargs, error, message", [
    ({"scenario": "no_such"}, ValueError, r"unknown scenario name 'no_such' .*known: abrupt, "),
    ({"scenario": "/nonexistent/fault.toml"}, FileNotFoundError,
     r"scenario file not found: /nonexistent/fault.toml"),
    ({"link": "udp"}, ValueError, r"link must be one of lcm, core or a PlantLink, got 'udp'"),
    ({"plant_seed": -1}, ValueError, r"plant_seed must be an integer in \[0, 2\*\*64\), got -1"),
    ({"render_mode": "ascii"}, ValueError, r"render_mode must be None or one of \['rgb_array'\]"),
    ({"scenarion": "single"}, TypeError, r"unexpected keyword argument 'scenarion'"),
])
def test_bad_arguments_give_one_clear_line(kwargs, error, message):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # gym.make's own note on an unknown render mode
        with pytest.raises(error, match=message) as e:
            gym.make("ftc/FuelTransfer-v0", **kwargs)
    assert "\n" not in str(e.value)


def test_malformed_scenario_fails_at_make_with_file_and_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\nengine_factor = [20.0,\n')
    with pytest.raises(ValueError, match=rf"bad scenario file: {bad}:\d+:\d+") as e:
        gym.make("ftc/FuelTransferCore-v0", scenario=str(bad))
    assert "\n" not in str(e.value)


def test_bad_reset_arguments_are_refused():
    env = FuelTransferEnv(link="core")
    with pytest.raises(ValueError, match=r"no options are supported, got \['evaluate'\]"):
        env.reset(options={"evaluate": True})
    with pytest.raises(ValueError, match=r"seed must be an integer in \[0, 2\*\*64\)"):
        env.reset(seed=-3)
    with pytest.raises(gym.error.ResetNeeded, match="call reset"):
        env.step(CLOSED)
