"""The project installs like a library: ``pip install <checkout>`` into a fresh
virtual environment outside the checkout builds the C++ parts (the bindings,
the plant and its tools, the message classes) into the package, and a user
who never saw the checkout runs the registered Gymnasium environment on a real
plant process (and its batched pool through ``gym.make_vec``) and the benchmark
through its console script.

One test, minutes long: it builds the package (CMake, scikit-build-core) in
build/pip/ of the checkout, incrementally after the first time."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

EPISODE = """
import gymnasium as gym
import ftc
plant = ftc.plant_binary()
env = gym.make("ftc/FuelTransfer-v0")
obs, _ = env.reset(seed=0)
steps, done = 0, False
while not done:
    obs, reward, terminal, truncated, _ = env.step(env.action_space.sample())
    steps, done = steps + 1, terminal or truncated
env.close()
pool = gym.make_vec("ftc/FuelTransferCore-v0", num_envs=8, vectorization_mode="vector_entry_point",
                    scenario="multiple")
pool.reset(seed=0)
for _ in range(100):
    pool_obs = pool.step(pool.action_space.sample())[0]
assert type(pool).__name__ == "FuelTransferVectorEnv" and pool_obs.shape == (8, 6)
print(plant, steps, ftc.__file__)
"""


def _run(cmd: list[str], cwd: Path, env: dict[str, str], timeout: float) -> str:
    done = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"{' '.join(cmd)} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done.stdout


def test_pip_install_into_a_fresh_venv_gives_a_working_package(tmp_path):
    venv, work = tmp_path / "venv", tmp_path / "work"
    work.mkdir()
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "FTC_BUILD_DIR", "FTC_PLANT_BIN", "VIRTUAL_ENV")}
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    start = time.monotonic()
    # the interpreter the checkout's .venv was made from: a venv's own python
    # would give the new venv its packages' site
    _run([getattr(sys, "_base_executable", sys.executable), "-m", "venv", str(venv)], work,
         env, 120)
    _run([str(venv / "bin" / "pip"), "install", "-q", str(REPO)], work, env, 1800)
    installed = time.monotonic() - start

    plant, steps, module = _run([str(venv / "bin" / "python"), "-c", EPISODE], work, env,
                                120).split()
    site = venv / "lib"
    assert Path(module).is_relative_to(site) and Path(plant).is_relative_to(site)
    assert Path(plant).parent.name == "bin" and int(steps) > 0

    out = work / "bench"
    (work / "single.toml").write_bytes((REPO / "scenarios" / "single.toml").read_bytes())
    _run(["ftc-experiments", "benchmark", "--methods", "closed", "--scenarios", "single.toml",
          "--intervals", "1", "--steps-per-interval", "64", "--seeds", "0", "--link", "lcm",
          "--jobs", "1", "--out", str(out)], work, env, 300)
    rows = (out / "results.csv").read_text().splitlines()
    assert len(rows) > 1 and any(",closed," in r for r in rows[1:])

    version = _run(["ftc", "--version"], work, env, 60).strip()
    assert version.startswith("ftc ") and version.split()[1][0].isdigit()
    assert "--scenario" in _run(["ftc-plant", "--help"], work, env, 60)
    for tool in ("ftc-controller", "ftc-mpc"):
        assert "--realtime" in _run([tool, "--help"], work, env, 120)
    print(f"fresh-venv install: {installed:.0f} s")
