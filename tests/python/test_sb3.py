"""Stable-Baselines3 on the registered env: PPO (stable-baselines3==2.9.2,
requirements-extra.txt) trains through SubprocVecEnv on two real plant
processes over LCM and gets better, and examples/sb3_ppo.py runs as a user would
run it. The training is examples/sb3_ppo.py's own train(), so the example is
what is tested."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from stable_baselines3 import PPO

import ftc
from ftc.common.build_info import plant_binary

EXAMPLE = ftc.REPO_ROOT / "examples" / "sb3_ppo.py"


def _load_example():
    spec = importlib.util.spec_from_file_location("sb3_ppo", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    sys.modules["sb3_ppo"] = module  # dataclasses look their module up here
    spec.loader.exec_module(module)
    return module


def _plants_below(pid: int) -> list[int]:
    """Plant processes (not zombies) among the descendants of ``pid``."""
    parent, cmd = {}, {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            argv0 = (entry / "cmdline").read_bytes().split(b"\0")[0]
        except OSError:
            continue
        if stat[0] != "Z":
            parent[int(entry.name)] = int(stat[1])
            cmd[int(entry.name)] = argv0
    binary = os.fsencode(plant_binary())

    def below(p: int) -> bool:
        while p in parent and p != pid:
            p = parent[p]
        return p == pid

    return [p for p, argv0 in cmd.items() if argv0 == binary and below(p)]


def test_ppo_improves_on_real_plants_through_subproc_vec_env():
    # 6,144 steps = 12 rollouts of 2 workers x 256 steps, seed 0, one torch thread.
    # Measured (seeds 0, 1, 2): the first rollout, from the untrained policy that
    # opens half the valves, earns 1.858 / 1.866 / 1.851 per step; the last three
    # average 2.172 / 2.162 / 2.167, and the last opens 23-24% of valves. The bar
    # (+0.15, half the measured gain, and below 40% open) fails for a policy that
    # does not learn: the first three rollouts of those seeds range 1.82-1.90 and
    # it would stay near 50% open. The plant degrades meanwhile (3 intervals per
    # plant: E1 burns 15% more), which lowers what any fixed policy earns, so the
    # gain is conservative. Same seed, same numbers: the run is deterministic.
    example = _load_example()
    torch_threads = torch.get_num_threads()
    model, rollouts = example.train(example.Config(steps=6144, seed=0), quiet=True)
    torch.set_num_threads(torch_threads)
    assert len(rollouts) == 12 and rollouts[-1].steps == 6144
    assert sum(r.episodes for r in rollouts) >= 6144 // 59 - 4  # ~59-step episodes ran
    first = rollouts[0]
    last3 = float(np.mean([r.mean_reward for r in rollouts[-3:]]))
    assert 0.45 < first.open_valves < 0.55, "the untrained policy should open about half"
    assert last3 > first.mean_reward + 0.15, [round(r.mean_reward, 3) for r in rollouts]
    assert rollouts[-1].open_valves < 0.40, [round(r.open_valves, 2) for r in rollouts]
    # the trained policy acts in the env's action space
    action, _ = model.predict(np.ones(6, dtype=np.float32), deterministic=True)
    assert action.shape == (6,) and set(np.unique(action)) <= {0, 1}
    assert _plants_below(os.getpid()) == [], "plant processes were left behind"


def _run(*args: str, tmp: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join([str(ftc.REPO_ROOT / "python"),
                                         env.get("PYTHONPATH", "")])
    return subprocess.run([sys.executable, str(EXAMPLE), *args], capture_output=True,
                          text=True, timeout=300, cwd=tmp, env=env)


def test_example_trains_briefly_and_saves_a_model(tmp_path):
    proc = _run("--steps", "1024", "--out", "m/ppo.zip", tmp=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    assert [ln.split()[:2] for ln in lines[:2]] == [["steps", "512"], ["steps", "1024"]]
    assert "mean reward/step" in lines[0] and "steps/s" in lines[0]
    assert lines[-1].startswith("saved m/ppo.zip (2 rollouts; mean reward/step ")
    model = PPO.load(tmp_path / "m" / "ppo.zip", device="cpu")
    action, _ = model.predict(np.full(6, 0.5, dtype=np.float32), deterministic=True)
    assert action.shape == (6,)



@pytest.mark.parametrize("args, message", [
    (["--steps", "0"], "sb3_ppo: error: argument --steps: must be >= 1, got 0"),
    (["--scenario", "nope"], "sb3_ppo: error: FuelTransferEnv: unknown scenario name 'nope'"),
    (["--out", "."], "sb3_ppo: error: argument --out: . is a directory"),
])
def test_example_refuses_bad_input_with_one_line(args, message, capsys, tmp_path, monkeypatch):
    # in this process (the CLI run above already starts one interpreter): main()
    # exits 2, or returns 2 for what only the env can judge (the scenario)
    monkeypatch.chdir(tmp_path)
    example = _load_example()
    try:
        code = example.main(args)
    except SystemExit as e:
        code = e.code
    err = capsys.readouterr().err
    assert code == 2 and err.startswith(message), err
    assert err.count("\n") == 1, err
    assert not (tmp_path / "runs").exists()


def test_example_help_names_its_options(capsys):
    with pytest.raises(SystemExit) as e:
        _load_example().main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert all(f"--{name}" in out for name in ("steps", "scenario", "out", "seed", "envs"))
