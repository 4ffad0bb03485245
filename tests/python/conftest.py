"""Shared fixtures: paths, and skipping nothing: the build must exist
(scripts/test.sh builds it first). Tests of the files that start processes are
marked ``subprocess``. ``--quick`` (``scripts/test.sh --quick``)
keeps the fast tier: the unit files below, plus the tests marked
``@pytest.mark.quick`` (one real-plant integration per boundary: the LCM
link, the orchestrator, the Gymnasium env)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCENARIOS = REPO / "scenarios"
sys.path.insert(0, str(Path(__file__).resolve().parent))  # reference_sim for the tests


# Test files that start no plant process, orchestrator or subprocess-heavy run.
QUICK_FILES = {
    "test_cli_inputs.py", "test_log_threads.py", "test_native_distill.py", "test_native_ppo.py",
    "test_physics_vs_reference.py", "test_ppo.py", "test_ppo_numpy.py", "test_properties.py",
    "test_reference_sim.py", "test_small_mlp.py", "test_world_model.py", "test_docs.py",
    "test_layers.py", "test_suite_results.py", "test_headroom.py", "test_compare.py",
    "test_scenario_names.py", "test_stuck.py", "test_noisy_identification.py",
}


def pytest_addoption(parser):
    parser.addoption("--quick", action="store_true",
                     help="the fast tier: unit files and one integration per boundary")


def pytest_collection_modifyitems(config, items):
    # every test of a file that starts plant processes, orchestrators or other
    # subprocesses is marked ``subprocess`` (select with -m subprocess or -m "not subprocess")
    for item in items:
        if Path(str(item.fspath)).name not in QUICK_FILES:
            item.add_marker(pytest.mark.subprocess)
    if not config.getoption("--quick"):
        return
    keep, drop = [], []
    for item in items:
        quick = Path(str(item.fspath)).name in QUICK_FILES or item.get_closest_marker("quick")
        (keep if quick else drop).append(item)
    config.hook.pytest_deselected(items=drop)
    items[:] = keep


@pytest.fixture(scope="session", autouse=True)
def _private_run_cache(tmp_path_factory):
    """Benchmarks started by the tests keep their cached runs (the reference's) in
    a directory of this session's, never in the user's ~/.cache."""
    import os

    os.environ["FTC_RUN_CACHE"] = str(tmp_path_factory.mktemp("run-cache"))
    # SB3's learn() makes a log directory (tempdir/SB3-<time>) when no logger is
    # given: keep those in this session's tmp too, not one left in /tmp per call
    os.environ["SB3_LOGDIR"] = str(tmp_path_factory.mktemp("sb3-logs"))


@pytest.fixture
def repo() -> Path:
    return REPO


@pytest.fixture
def scenarios() -> Path:
    return SCENARIOS


def _write_state_log(path: Path, steps: int, drop_per_step: float = 0.01) -> None:
    """An LCM log of ``steps`` + 1 plant states on channel T_STATE (levels
    falling by ``drop_per_step`` per step, valves closed), written by liblcm."""
    import lcm

    from ftc.plant_state_t import plant_state_t

    log = lcm.EventLog(str(path), "w", overwrite=True)
    for k in range(steps + 1):
        m = plant_state_t()
        m.seq, m.command_seq, m.episode, m.step = k + 1, k, 0, k
        m.num_tanks, m.num_engines = 6, 2
        m.level = m.true_level = [1.0 - drop_per_step * k] * 6
        m.valve = [0] * 6
        m.deficit = [0.0, 0.0]
        log.write_event(1000 + k, "T_STATE", m.encode())
    log.close()


@pytest.fixture
def write_state_log():
    """The function that writes a small plant-state log (see _write_state_log)."""
    return _write_state_log


@pytest.fixture()
def one_torch_thread():
    """Torch on one thread, as training runs it (many crawl on a loaded machine)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
