"""The project installs like a library: ``pip install <checkout>`` into a fresh
virtual environment outside the checkout builds the C++ parts (the bindings,
the plant and its tools, the message classes) into the package, and a user
who never saw the checkout runs the registered Gymnasium environment on a real
plant process (and its batched pool through ``gym.make_vec``), and the README's
install commands (the benchmark, the controller with its default scenario, the
MPC with a scenario's name: no file of the checkout needed) through the console
scripts.

One test, a minute or two long: it builds the package (CMake, scikit-build-core)
in build/pip/ of the checkout, incrementally after the first time. Tests reach
no address off this machine, so pip gets no index (``--no-index``): the new
venv sees the checkout venv's site-packages (one path line in a .pth file,
which adds no package of the checkout, its ``ftc-checkout.pth`` unread) as the
layer that holds the pinned dependencies and the build backend, and pip checks
that they satisfy the package's declared ones. lcm, whose shared library the
plant finds beside the package, is installed into the venv itself from the
wheel scripts/setup.sh keeps (.venv/wheelhouse). What pip gets from an index
for a user is the same pins (requirements.txt)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import time
from pathlib import Path

from doc_commands import marked

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
    # the venv is made afresh at one place of the checkout's build/ (ignored by
    # git): the compiler sees its headers (lcm's) at the same relative path each
    # time, so ccache serves a later run, or a fresh clone, the objects of an
    # earlier one (a venv under a new tmp dir each run made every object a miss)
    venv, work = REPO / "build" / "test-install-venv", tmp_path / "work"
    shutil.rmtree(venv, ignore_errors=True)
    work.mkdir()
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "FTC_BUILD_DIR", "FTC_PLANT_BIN", "VIRTUAL_ENV")}
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    start = time.monotonic()
    # the interpreter the checkout's .venv was made from: a venv's own python
    # would give the new venv its packages' site
    _run([getattr(sys, "_base_executable", sys.executable), "-m", "venv", str(venv)], work,
         env, 120)
    site = Path(_run([str(venv / "bin" / "python"), "-c",
                      "import sysconfig; print(sysconfig.get_paths()['purelib'])"], work, env,
                     60).strip())
    (site / "checkout-dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    # the venv's bundled setuptools (older than torch asks for) would hide the layer's;
    # from an index, pip would upgrade it
    _run([str(venv / "bin" / "pip"), "uninstall", "-q", "-y", "setuptools"], work, env, 120)
    # lcm installed into the venv itself, as from an index: the plant finds liblcm
    # beside the package (its RUNPATH), not in the layer
    _run([str(venv / "bin" / "pip"), "install", "-q", "--no-index", "--no-deps",
          "--ignore-installed", "--find-links", str(REPO / ".venv" / "wheelhouse"), "lcm==1.5.3"],
         work, env, 300)
    _run([str(venv / "bin" / "pip"), "install", "-q", "--no-index", "--no-build-isolation",
          str(REPO)], work, env, 1800)
    installed = time.monotonic() - start

    plant, steps, module = _run([str(venv / "bin" / "python"), "-c", EPISODE], work, env,
                                120).split()
    assert Path(module).is_relative_to(site) and Path(plant).is_relative_to(site)
    assert Path(plant).parent.name == "bin" and int(steps) > 0
    # the installed programs and modules load nothing from the checkout (its
    # build/ may be gone): every shared library resolves outside it
    for binary in [Path(plant), *Path(module).parent.glob("_*.so")]:
        linked = _run(["ldd", str(binary)], work, env, 60)
        # nothing resolves into the checkout (the venv aside, which lives in build/)
        outside = linked.replace(str(venv), "<venv>")
        assert "not found" not in linked and str(REPO) not in outside, (binary, linked)

    # the README's install commands, as written, beside the venv (myenv), outside the
    # checkout: scenario names and the tools' default scenario from the installed package
    (work / "myenv").symlink_to(venv)
    for doc, command in marked("install"):
        _run(["bash", "-euo", "pipefail", "-c", command], work, env, 300)
    rows = (work / "bench" / "results.csv").read_text().splitlines()
    assert len(rows) > 1 and any(",closed," in r for r in rows[1:])
    for run in ("run", "mpc"):
        assert (work / run / "done.json").is_file()
        scenario = json.loads((work / run / "config.json").read_text())
        scenario = next(v["scenario"] for v in scenario.values() if isinstance(v, dict)
                        and "scenario" in v)
        assert Path(scenario).is_relative_to(site) and Path(scenario).parent.name == "scenarios"
    assert Path(scenario).name == "multiple.toml"  # ftc-mpc --scenario multiple

    version = _run(["ftc", "--version"], work, env, 60).strip()
    assert version.startswith("ftc ") and version.split()[1][0].isdigit()
    for tool in ("ftc-controller", "ftc-mpc"):
        assert "--realtime" in _run([tool, "--help"], work, env, 120)
    print(f"fresh-venv install: {installed:.0f} s")


def test_cmake_on_a_fresh_clone_works_or_says_what_to_run_first(tmp_path):
    """``cmake -B build`` in a copy of the tracked files (no .venv, no build/):
    where a dependency is missing, one line names it and scripts/setup.sh."""
    files = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True,
                           check=True).stdout.decode().split("\0")
    clone = tmp_path / "clone"
    for rel in filter(None, files):
        if (REPO / rel).is_file() and not rel.startswith("tests/data/"):
            (clone / rel).parent.mkdir(parents=True, exist_ok=True)
            (clone / rel).write_bytes((REPO / rel).read_bytes())
    done = subprocess.run(["cmake", "-B", "build"], cwd=clone, capture_output=True, text=True,
                          timeout=300)
    if done.returncode != 0:
        said = [line.strip() for line in done.stderr.splitlines()
                if "not found: run `bash scripts/setup.sh` first" in line]
        assert len(said) == 1, done.stderr[-3000:]
