"""No result is ever overwritten, no flag is ever silently ignored.

Every tool that writes results (ftc.controller, ftc.mpc, ftc.simulate,
ftc.export, ftc.experiments, ftc.experiments benchmark) is tried, as a
subprocess, on three kinds of --out: one that holds finished results, one a
live process is writing, and one whose writer was SIGKILLed (a stale lock).
The first two are refused with one line and exit 2, the old files
byte-identical afterwards; the third is taken over with one line saying so.
Then: --resume honours or refuses every option (2 + 2 resumed intervals
equal 4 uninterrupted ones), --overwrite replaces only once the new run has
proved itself, and atomic files honour the umask.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from forked_tools import run_tool

from ftc.common.atomic import atomic_torch_save, atomic_write_bytes, atomic_write_text
from ftc.tools import controller as controller_cli
from ftc.tools.controller import Controller
from ftc.control.agents.ppo import ControllerConfig
from ftc.learning.ppo import PPOConfig

REPO = Path(__file__).resolve().parents[2]
SINGLE = str(REPO / "scenarios" / "single.toml")
MULTIPLE = str(REPO / "scenarios" / "multiple.toml")
PY = sys.executable
CORE = ["--link", "core", "--quiet"]
TIME_COLUMNS = {"online_seconds", "offline_seconds", "wall_time", "refit_seconds",
                "pretrain_seconds", "model_pretrain_seconds"}


def _tool(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    """``python -m args``, forked from a process that imported the tools once
    (tests/python/forked_tools.py)."""
    return run_tool(args[0], args[1:], cwd=REPO, timeout=timeout)


def _digest(path: Path) -> dict[str, str]:
    """sha256 of every result file under ``path`` (or of the file itself); lock
    files are not results (a SIGKILLed test writer leaves its own behind)."""
    files = [path] if path.is_file() else sorted(
        p for p in path.rglob("*") if p.is_file() and not p.name.endswith(".lock"))
    return {str(p.relative_to(path.parent)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in files}


def _one_error_line(proc: subprocess.CompletedProcess, tool: str, *words: str) -> str:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"{tool}: error: "), lines[0]
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


_HOLDER = ("import sys, time\n"
           "from ftc.common.run_lock import RunLock\n"
           "RunLock(sys.argv[1], 'a test writer', sys.argv[2], sys.argv[3] == '1').acquire()\n"
           "print('held', flush=True)\n"
           "time.sleep(600)\n")


class Writer:
    """A live process holding the lock of ``target`` (as another run would)."""

    def __init__(self, target: Path, name: str = "run.lock", beside: bool = False) -> None:
        self.proc = subprocess.Popen([PY, "-c", _HOLDER, str(target), name, str(int(beside))],
                                     stdout=subprocess.PIPE, text=True, cwd=REPO)
        assert self.proc.stdout.readline().strip() == "held"
        self.pid = self.proc.pid

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()
        self.proc.stdout.close()

    def __enter__(self) -> "Writer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.kill()


def _stale(target: Path, name: str = "run.lock", beside: bool = False) -> int:
    """Leave a stale lock on ``target``: its writer SIGKILLed; returns the dead pid."""
    writer = Writer(target, name, beside)
    writer.kill()
    return writer.pid


# ---------------------------------------------------------------------------
# Finished results of every tool (made once; each test copies what it changes)
# ---------------------------------------------------------------------------

SHORT_RUN = ["--intervals", "2", "--steps-per-interval", "64", *CORE]
BENCH = ["--scenarios", SINGLE, "--methods", "closed", "--seeds", "0", "--intervals", "1",
         "--steps-per-interval", "32", "--link", "core", "--jobs", "2",
         "--reference", "oracle-mpc"]
EXPERIMENT = ["single", "--methods", "closed", "--intervals", "1", "--steps-per-interval",
              "32", "--jobs", "1"]


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("finished")
    made = {"controller": base / "controller", "mpc": base / "mpc",
            "simulate": base / "traj.csv", "export": base / "policy.onnx",
            "experiments": base / "experiments", "benchmark": base / "benchmark"}
    commands = [
        ("ftc.controller", "--method", "closed", "--scenario", SINGLE, *SHORT_RUN,
         "--out", str(made["controller"])),
        ("ftc.mpc", "--method", "oracle-mpc", "--scenario", SINGLE, "--intervals", "1",
         "--steps-per-interval", "16", *CORE, "--out", str(made["mpc"])),
        ("ftc.simulate", "--steps", "20", "--out", str(made["simulate"])),
        ("ftc.controller", "--method", "ppo", "--no-offline", "--update-every", "32",
         "--scenario", SINGLE, "--intervals", "1", "--steps-per-interval", "64", *CORE,
         "--out", str(base / "ppo")),
        ("ftc.export", str(base / "ppo"), "--verify-states", "64", "--out",
         str(made["export"])),
        ("ftc.experiments", *EXPERIMENT, "--out", str(made["experiments"])),
        ("ftc.experiments", "benchmark", *BENCH, "--out", str(made["benchmark"])),
    ]
    for cmd in commands:
        proc = _tool(*cmd)
        assert proc.returncode == 0, (cmd, proc.stderr[-3000:])
    return made


# How each tool is asked to write into an --out that holds results, and
# what it writes, per case: (argv without --out, the lock's name, beside a file)
AGAIN = {
    "controller": (["ftc.controller", "--method", "closed", "--scenario", SINGLE, *SHORT_RUN],
                   "run.lock", False),
    "mpc": (["ftc.mpc", "--method", "oracle-mpc", "--scenario", SINGLE, "--intervals", "1",
             "--steps-per-interval", "16", *CORE], "run.lock", False),
    "simulate": (["ftc.simulate", "--steps", "20"], "", True),
    "export": (["ftc.export", "PPO", "--verify-states", "64"], "", True),
    "experiments": (["ftc.experiments", *EXPERIMENT], "orchestrator.lock", False),
    "benchmark": (["ftc.experiments", "benchmark", *BENCH], "orchestrator.lock", False),
}
TOOL_NAME = {"controller": "ftc.controller", "mpc": "ftc.mpc", "simulate": "ftc.simulate",
             "export": "ftc.export", "experiments": "ftc.experiments",
             "benchmark": "ftc.experiments benchmark"}
# the same tool taking the results over deliberately (a lock must still stop it)
TAKE_OVER = {"controller": "--resume", "mpc": "--resume", "simulate": "--overwrite",
             "export": "--overwrite", "experiments": "--resume", "benchmark": "--resume"}


def _argv(kind: str, finished: dict[str, Path], out: Path, *extra: str) -> list[str]:
    argv, _, _ = AGAIN[kind]
    argv = [str(finished["export"].parent / "ppo") if a == "PPO" else a for a in argv]
    if extra[:1] == ("--resume",) and kind in ("controller", "mpc"):
        return [argv[0], "--resume", str(out), *CORE]
    return [*argv, "--out", str(out), *extra]


@pytest.mark.parametrize("kind", list(AGAIN))
def test_an_out_holding_results_is_refused_and_left_byte_identical(finished, kind):
    out = finished[kind]
    before = _digest(out)
    proc = _tool(*_argv(kind, finished, out))
    line = _one_error_line(proc, TOOL_NAME[kind], str(out))
    assert "--overwrite" in line, line  # the way to replace it deliberately
    if kind not in ("simulate", "export"):
        assert "--resume" in line, line  # and the way to continue it
    assert _digest(out) == before


@pytest.mark.parametrize("kind", list(AGAIN))
def test_a_live_writer_is_refused_by_name_and_its_results_left_byte_identical(finished, kind):
    out = finished[kind]
    _, name, beside = AGAIN[kind]
    before = _digest(out)
    with Writer(out, name, beside) as writer:
        proc = _tool(*_argv(kind, finished, out, TAKE_OVER[kind]))
        _one_error_line(proc, TOOL_NAME[kind], f"pid {writer.pid}", "in use", "a test writer")
    assert _digest(out) == before


@pytest.mark.parametrize("kind", list(AGAIN))
def test_a_stale_lock_is_taken_over_with_a_line_saying_so(finished, kind, tmp_path):
    out = tmp_path / finished[kind].name
    _, name, beside = AGAIN[kind]
    dead = _stale(out, name, beside)
    lock = out.parent / f".{out.name}.lock" if beside else out / name
    assert lock.is_file()
    proc = _tool(*_argv(kind, finished, out))
    assert proc.returncode == 0, proc.stderr[-3000:]
    notes = [x for x in proc.stderr.splitlines() if "stale lock" in x]
    assert len(notes) == 1 and f"pid {dead}" in notes[0] and "no longer running" in notes[0], \
        proc.stderr[-2000:]
    assert out.exists() and not lock.exists()  # written, and the lock released


# ---------------------------------------------------------------------------
# --resume: every option honoured or refused
# ---------------------------------------------------------------------------

def _short(out: Path, **kw) -> ControllerConfig:
    base = dict(out=str(out), intervals=2, steps_per_interval=128, update_every=64,
                offline_steps=512, offline_envs=8, offline_rollout=32, model_episodes=6,
                quiet=True, seed=3, link="core", scenario=SINGLE)
    base.update(kw)
    return ControllerConfig(**base)


def _rows(out: Path) -> list[dict[str, str]]:
    with open(out / "metrics.csv") as f:
        return [{k: v for k, v in r.items() if k not in TIME_COLUMNS} for r in csv.DictReader(f)]


def _assert_same(a, b, where: str) -> None:
    """Nested checkpoint state equal bit for bit (tensors, arrays, containers)."""
    assert type(a) is type(b), where
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _assert_same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{where}[{i}]")
    elif torch.is_tensor(a):
        assert torch.equal(a, b), where
    elif isinstance(a, np.ndarray):
        assert np.array_equal(a, b), where
    else:
        assert a == b, where


def test_two_intervals_extended_by_two_equal_four_uninterrupted(tmp_path):
    """PPO online + offline on the world model: continued control and learning."""
    Controller(_short(tmp_path / "four", intervals=4), PPOConfig()).run()
    two = tmp_path / "two"
    Controller(_short(two), PPOConfig()).run()
    assert (two / "done.json").is_file() and len(_rows(two)) == 2
    assert controller_cli.main(["--resume", str(two), "--intervals", "4", "--quiet"]) == 0
    assert _rows(two) == _rows(tmp_path / "four")
    a = torch.load(tmp_path / "four" / "checkpoint.pt", weights_only=True)
    b = torch.load(two / "checkpoint.pt", weights_only=True)
    assert b["interval"] == 4 and a["agent"]["model"] is not None
    # policy, optimiser, world model, data window, generators: bit for bit
    _assert_same(a["agent"], b["agent"], "agent")
    _assert_same(a["torch_rng"], b["torch_rng"], "torch_rng")
    doc = json.loads((two / "config.json").read_text())
    assert doc["controller"]["intervals"] == 4 and "intervals" not in doc["ppo"]
    assert [e["to"] for e in doc["extended"]] == [4] and doc["extended"][0]["from"] == 2
    # a run stopped, resumed and stopped again resumes again (config.json stays readable)
    three = tmp_path / "three"
    Controller(_short(three, intervals=4), PPOConfig()).run(stop_after=1)
    cfg, ppo = controller_cli.resume_config(str(three))
    Controller(cfg, ppo).run(stop_after=2)
    assert controller_cli.main(["--resume", str(three), "--quiet"]) == 0
    assert _rows(three) == _rows(tmp_path / "four")
    assert "extended" not in json.loads((three / "config.json").read_text())


@pytest.fixture(scope="module")
def closed_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("resume") / "run"
    proc = _tool("ftc.controller", "--method", "closed", "--scenario", SINGLE, "--seed", "5",
                 "--out", str(out), *SHORT_RUN)
    assert proc.returncode == 0, proc.stderr
    return out


@pytest.mark.parametrize("given,named", [
    (["--seed", "6"], "--seed 6"),
    (["--scenario", MULTIPLE], "--scenario"),
    (["--method", "open"], "--method open"),
    (["--steps-per-interval", "32"], "--steps-per-interval 32"),
    (["--ppo-trunk-sizes", "32", "32"], "--ppo-trunk-sizes"),  # no effect on a baseline
    (["--intervals", "1"], "below the run's 2"),
    (["--out", "elsewhere"], "--out elsewhere"),
    (["--ppo-learning-rate", "0.5"], "is not an option of --method closed"),
])
def test_resume_refuses_an_option_that_fixes_results(closed_run, given, named):
    before = _digest(closed_run)
    proc = _tool("ftc.controller", "--resume", str(closed_run), *given)
    _one_error_line(proc, "ftc.controller", named)
    assert _digest(closed_run) == before


def test_resume_accepts_the_runs_own_values_and_says_when_nothing_is_left(closed_run):
    before = _digest(closed_run)
    proc = _tool("ftc.controller", "--resume", str(closed_run), "--seed", "5", "--scenario",
                 SINGLE, "--method", "closed", "--intervals", "2", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert "has finished its 2 intervals; nothing to do" in proc.stdout
    assert _digest(closed_run) == before


def test_mpc_resume_refuses_another_horizon_and_accepts_no_ppo_options(finished):
    out = finished["mpc"]
    before = _digest(out)
    _one_error_line(_tool("ftc.mpc", "--resume", str(out), "--horizon", "5"), "ftc.mpc",
                    "--horizon 5", "differs")
    for option in (["--pretrain"], ["--offline-steps", "0"], ["--update-every", "32"]):
        _one_error_line(_tool("ftc.mpc", *option, "--out", str(out.parent / "x")), "ftc.mpc",
                        option[0])
    assert _digest(out) == before and not (out.parent / "x").exists()


@pytest.mark.parametrize("option", [["--offline-steps", "10"], ["--pretrain"],
                                    ["--ppo-learning-rate", "0.1"]])
@pytest.mark.parametrize("method", ["closed", "balance"])
def test_a_baseline_refuses_ppo_options_it_does_not_have(tmp_path, method, option):
    proc = _tool("ftc.controller", "--method", method, *option, "--out", str(tmp_path / "r"))
    _one_error_line(proc, "ftc.controller", option[0], f"is not an option of --method {method}")
    assert not (tmp_path / "r").exists()


def test_experiment_args_go_only_to_methods_that_take_them(tmp_path):
    proc = _tool("ftc.experiments", "benchmark", *BENCH, "--controller-args",
                 "--update-every 32", "--out", str(tmp_path / "b"))
    _one_error_line(proc, "ftc.experiments benchmark", "--update-every", "no method")
    assert not (tmp_path / "b").exists()


# ---------------------------------------------------------------------------
# --overwrite
# ---------------------------------------------------------------------------

def test_overwrite_that_fails_before_its_first_interval_puts_the_old_run_back(finished,
                                                                              tmp_path):
    out = tmp_path / "run"
    shutil.copytree(finished["controller"], out)
    before = _digest(out)
    # nothing listens there: the plant is gone before the first step (exit 3)
    proc = _tool("ftc.controller", "--method", "open", "--scenario", SINGLE, "--overwrite",
                 "--attach", "--lcm-url", "udpm://239.255.76.97:7993?ttl=0",
                 "--link-give-up-timeout", "0.3", "--link-retry-timeout", "0.1",
                 "--out", str(out))
    assert proc.returncode == 3, proc.stderr
    assert _digest(out) == before and sorted(os.listdir(out)) == sorted(
        ["checkpoint.pt", "config.json", "done.json", "metrics.csv"])


def test_overwrite_replaces_the_run_once_the_new_one_saved_an_interval(finished, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(finished["controller"], out)
    proc = _tool("ftc.controller", "--method", "open", "--scenario", SINGLE, "--overwrite",
                 "--out", str(out), *SHORT_RUN)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((out / "config.json").read_text())["controller"]["method"] == "open"
    assert sorted(os.listdir(out)) == ["checkpoint.pt", "config.json", "done.json",
                                       "metrics.csv"]  # the old run gone, no stash left


def test_benchmark_overwrite_with_no_run_finished_puts_the_old_one_back(finished, tmp_path):
    out = tmp_path / "bench"
    shutil.copytree(finished["benchmark"], out)
    before = _digest(out)
    # every run killed after a millisecond: none finishes
    proc = _tool("ftc.experiments", "benchmark", *BENCH, "--run-timeout", "0.001",
                 "--overwrite", "--out", str(out))
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert "is back in place" in proc.stderr
    assert _digest(out) == before


def test_benchmark_overwrite_replaces_it_once_a_run_finished(finished, tmp_path):
    out = tmp_path / "bench"
    shutil.copytree(finished["benchmark"], out)
    # another method and seed (closed always runs, as the normalized score's 0)
    proc = _tool("ftc.experiments", "benchmark", *BENCH[:3], "open", BENCH[4], "1",
                 *BENCH[6:], "--overwrite", "--out", str(out))
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert not (out / ".replaced").exists()
    assert not list(out.glob("runs/*/t00/*/s0")) and list(out.glob("runs/*/t00/open/s1"))


# ---------------------------------------------------------------------------
# Modes
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("umask,mode", [(0o022, 0o644), (0o027, 0o640), (0o002, 0o664)])
def test_atomic_files_honour_the_umask(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        atomic_write_text(tmp_path / "a.txt", "x")
        atomic_write_bytes(tmp_path / "b.onnx", b"x")
        atomic_torch_save(tmp_path / "c.pt", {"x": 1})
    finally:
        os.umask(old)
    for name in ("a.txt", "b.onnx", "c.pt"):
        assert (tmp_path / name).stat().st_mode & 0o777 == mode, name


def test_resume_and_overwrite_exclude_each_other(closed_run):
    before = _digest(closed_run)
    _one_error_line(_tool("ftc.controller", "--resume", str(closed_run), "--overwrite"),
                    "ftc.controller", "--overwrite", "--resume")
    assert _digest(closed_run) == before


# ---------------------------------------------------------------------------
# Cut short: stashes, locks and runs that fail before their first interval
# ---------------------------------------------------------------------------

def _replacement(d: Path):
    from ftc.common.replacing import Replacement

    return Replacement(d, ["a", "b"], lambda p: (p / "b").exists())


def _files(d: Path) -> dict[str, str]:
    return {str(p.relative_to(d)): p.read_text() for p in sorted(d.rglob("*")) if p.is_file()}


def test_a_killed_overwrite_keeps_the_original_until_its_replacement_proves_itself(tmp_path):
    d = tmp_path / "run"
    d.mkdir()
    (d / "a").write_text("old a")
    (d / "b").write_text("old b")
    _replacement(d).stash_old()  # --overwrite started ... and was killed with a partial result
    (d / "a").write_text("partial a")
    _replacement(d).stash_old()  # the next --overwrite: the partial goes, the original stays
    assert _files(d) == {".replaced/a": "old a", ".replaced/b": "old b"}
    _replacement(d).restore()  # which fails before proving itself: the original is back
    assert _files(d) == {"a": "old a", "b": "old b"}
    _replacement(d).stash_old()
    (d / "a").write_text("new a")
    (d / "b").write_text("new b")  # proven; killed before it could commit
    _replacement(d).settle()  # whoever holds it next commits the stash
    assert _files(d) == {"a": "new a", "b": "new b"}


def test_a_proven_replacement_is_never_taken_for_a_partial_one(tmp_path):
    d = tmp_path / "run"
    d.mkdir()
    (d / "a").write_text("old a")
    _replacement(d).stash_old()
    (d / "a").write_text("new a")
    (d / "b").write_text("new b")  # proven, then killed before the commit
    _replacement(d).stash_old()  # a later --overwrite replaces the proven run, not the old one
    assert _files(d) == {".replaced/a": "new a", ".replaced/b": "new b"}


def test_a_restore_cut_short_is_completed_by_the_next_holder(tmp_path):
    from ftc.common.replacing import BUILDING

    d = tmp_path / "run"
    d.mkdir()
    (d / "a").write_text("old a")
    (d / "b").write_text("old b")
    _replacement(d).stash_old()
    os.rename(d / ".replaced", d / BUILDING)  # restore() stopped after taking the stash apart
    os.rename(d / BUILDING / "a", d / "a")   # ... and moving one entry back
    _replacement(d).stash_old()  # the next holder first puts the rest back, then stashes all
    assert _files(d) == {".replaced/a": "old a", ".replaced/b": "old b"}


def test_a_lock_on_a_file_its_holder_unlinked_meanwhile_is_not_taken(tmp_path):
    import fcntl

    from ftc.common.run_lock import RunLock, _still_linked

    first = RunLock(tmp_path, "first").acquire()
    late = os.open(first.path, os.O_RDWR)  # opened just before the holder released it
    first.release()
    fcntl.flock(late, fcntl.LOCK_EX | fcntl.LOCK_NB)  # locks the unlinked file: nothing
    assert not _still_linked(late, first.path)
    second = RunLock(tmp_path, "second").acquire()  # on the file that is there
    assert _still_linked(second._fd, second.path)
    os.close(late)
    second.release()


def test_a_fresh_run_that_fails_before_its_first_interval_leaves_nothing(tmp_path):
    out = tmp_path / "run"
    proc = _tool("ftc.controller", "--method", "open", "--scenario", SINGLE, "--attach",
                 "--lcm-url", "udpm://239.255.76.97:7992?ttl=0", "--link-give-up-timeout",
                 "0.3", "--link-retry-timeout", "0.1", "--out", str(out))
    assert proc.returncode == 3, proc.stderr
    assert not out.exists() or os.listdir(out) == []  # the same command can simply run again


def test_each_experiment_option_goes_to_the_methods_it_acts_on():
    from ftc.experiments.method_args import method_args, untaken
    from ftc.experiments.methods import METHODS

    extra = ["--update-every", "32", "--model-episodes", "4", "--link-retry-timeout", "0.1"]
    assert method_args(METHODS["ppo-offline"], extra) == extra
    # ppo-online has no offline phase, so no world model to pretrain
    assert method_args(METHODS["ppo-online"], extra) == extra[:2] + extra[4:]
    assert method_args(METHODS["model-mpc"], extra) == extra[2:]  # MPC: its own option
    assert method_args(METHODS["closed"], extra) == extra[4:]  # a baseline: run options only
    assert untaken(["closed", "oracle-mpc"], ["--update-every", "32", "--nope"]) == [
        "--update-every", "--nope"]


def test_an_orchestrator_overwrites_only_an_experiment(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    proc = _tool("ftc.experiments", "benchmark", *BENCH, "--overwrite", "--out", str(tmp_path))
    _one_error_line(proc, "ftc.experiments benchmark", "holds no benchmark")
    assert _files(tmp_path) == {"notes.txt": "mine"}


def test_the_runner_itself_refuses_a_live_writer_past_the_command_lines_check(tmp_path):
    """The command line's check is early; the lock the runner takes is what
    holds when a second writer starts between the two."""
    from ftc.common.run_lock import InUse

    out = tmp_path / "run"
    with Writer(out) as writer:
        with pytest.raises(InUse, match=f"pid {writer.pid}"):
            Controller(_short(out, method="closed"), PPOConfig()).run()
    assert sorted(os.listdir(out)) == ["run.lock"]  # the writer's own (SIGKILLed) lock only


@pytest.mark.parametrize("kind", ["simulate", "export"])
def test_overwrite_replaces_a_file_atomically(finished, kind, tmp_path):
    out = tmp_path / finished[kind].name
    shutil.copy(finished[kind], out)
    out.write_bytes(b"old")
    proc = _tool(*_argv(kind, finished, out, "--overwrite"))
    assert proc.returncode == 0, proc.stderr
    assert out.read_bytes() != b"old" and out.stat().st_size > 100
    assert not list(tmp_path.glob("*.tmp")) and not list(tmp_path.glob(".*.lock"))
