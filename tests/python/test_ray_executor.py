"""--executor ray on a real Ray head (loopback only, token auth, no dashboard,
no usage stats, 2 CPUs): a reduced benchmark and a reduced experiment give the
local executor's results (every non-timing column equal; the experiment's runs
drive real plant processes over LCM and their logs are checked); a killed
driver leaves its finished runs, its tasks' processes die, and --resume on Ray
skips them; a failing task is reported as a failing local run is; bad
addresses and a node running other code are one line, exit 2, nothing written.

The head is started with ``python -m ray.scripts.scripts start --head --block``
in its own session and stopped by its process group (never ``ray stop``, which
stops every Ray on the machine).
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from ftc.control.run.metrics import TIMING_COLUMNS
from ftc.experiments import cli, ray_executor
from ftc.experiments.runs import is_finished

REPO = Path(__file__).resolve().parents[2]
BENCH = ["benchmark", "--scenarios", str(REPO / "scenarios" / "single.toml"),
         "--methods", "closed", "--seeds", "0", "1", "--intervals", "2",
         "--steps-per-interval", "64", "--reference", "oracle-mpc"]
EXPERIMENT = ["single", "--methods", "closed", "balance", "ppo-online", "--seeds", "0",
              "--intervals", "2", "--steps-per-interval", "64",
              "--controller-args", "--update-every 32"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(**extra: str) -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=str(REPO / "python"), OMP_NUM_THREADS="1",
               RAY_USAGE_STATS_ENABLED="0", RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER="0")
    env.update(extra)
    return env


@pytest.fixture(scope="module")
def head() -> dict:
    """A Ray head on 127.0.0.1 (every socket on lo), 2 CPUs, 100 MB object store.
    Ray gives its raylet a fixed 30 s to register (ray/_private/node.py) and
    exits when it is late, which a loaded two-core machine can make it: the head
    is started again once then."""
    temp = tempfile.mkdtemp(prefix="ftcray", dir="/tmp")  # short: Unix socket paths
    auth = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32)}
    log = open(Path(temp) / "head.log", "wb")

    def start() -> tuple[subprocess.Popen, int]:
        port = _free_port()
        return subprocess.Popen(
            [sys.executable, "-m", "ray.scripts.scripts", "start", "--head", "--block",
             "--node-ip-address=127.0.0.1", f"--port={port}", "--include-dashboard=false",
             "--num-cpus=2", f"--temp-dir={temp}", "--object-store-memory=100000000",
             "--disable-usage-stats", f"--ray-client-server-port={_free_port()}"],
            stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, env=_env(**auth),
            start_new_session=True), port

    (proc, port), retried = start(), False
    deadline = time.monotonic() + 120
    try:
        while b"Ray runtime started" not in (Path(temp) / "head.log").read_bytes():
            if proc.poll() is not None:
                text = (Path(temp) / "head.log").read_text()
                assert not retried and "timed out during startup" in text, text[-2000:]
                try:
                    os.killpg(proc.pid, signal.SIGKILL)  # what the late start left running
                except OSError:
                    pass
                (proc, port), retried = start(), True
                deadline = time.monotonic() + 120
            assert time.monotonic() < deadline, "the Ray head did not start"
            time.sleep(0.2)
        yield {"address": f"127.0.0.1:{port}", "env": _env(**auth)}
    finally:
        proc.send_signal(signal.SIGTERM)  # --block: stops what it started
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            pass
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # anything left of its group
        except OSError:
            pass
        proc.wait()
        log.close()
        shutil.rmtree(temp, ignore_errors=True)


def _cli(args: list[str], env: dict, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ftc.experiments", *args], capture_output=True,
                          text=True, timeout=timeout, env=env, cwd=REPO)


def _results(out: Path) -> list[dict]:
    with open(out / "results.csv", newline="") as f:
        return [{k: v for k, v in r.items() if k not in TIMING_COLUMNS + ("wall_time_s",)}
                for r in csv.DictReader(f)]


def _digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.slow  # 10-30 s: the fresh-clone CI stays under its 10 minutes
def test_benchmark_on_ray_equals_the_local_executor(head, tmp_path):
    local, remote = tmp_path / "local", tmp_path / "ray"
    started = time.monotonic()
    a = _cli([*BENCH, "--jobs", "2", "--out", str(local)], _env())
    local_s = time.monotonic() - started
    assert a.returncode == 0, a.stderr[-3000:]
    started = time.monotonic()
    b = _cli([*BENCH, "--executor", "ray", "--ray-address", head["address"], "--out",
              str(remote)], head["env"])
    ray_s = time.monotonic() - started
    assert b.returncode == 0, b.stderr[-3000:]
    print(f"\nreduced benchmark (4 runs): local {local_s:.1f} s, ray {ray_s:.1f} s")
    rows = _results(remote)
    assert len(rows) == 4 * 2 and rows == _results(local)
    meta = json.loads((remote / "benchmark.json").read_text())
    assert meta["executor"]["kind"] == "ray" and meta["executor"]["cpus"] == 2
    assert meta["executor"]["nodes"] == [socket.gethostname()]
    result = json.loads((remote / "runs/single/t00/closed/s0/result.json").read_text())
    assert result["executor"] == "ray" and result["status"] == "ok"
    assert "executor ray at 127.0.0.1:" in b.stderr and "runs done" in b.stderr
    assert (remote / "report.md").read_text().count("on Ray at 127.0.0.1:") == 1


@pytest.mark.slow  # tens of seconds; the default tier keeps the benchmark on Ray
def test_experiment_with_lcm_plants_on_ray_equals_the_local_executor(head, tmp_path):
    local, remote = tmp_path / "local", tmp_path / "ray"
    a = _cli([*EXPERIMENT, "--jobs", "2", "--out", str(local)], _env())
    assert a.returncode == 0, a.stderr[-3000:]
    b = _cli([*EXPERIMENT, "--executor", "ray", "--ray-address", head["address"], "--out",
              str(remote)], head["env"])
    assert b.returncode == 0, b.stderr[-3000:]
    assert _results(remote) == _results(local) and len(_results(local)) == 3 * 2
    # figure (a)'s baseline episodes ran as tasks too: the same episodes, byte for byte
    baselines = sorted(p.name for p in (local / "baselines").iterdir())
    assert len(baselines) == 4
    for name in baselines:
        assert (remote / "baselines" / name).read_bytes() == (local / "baselines" / name)\
            .read_bytes(), name
    records = [json.loads(p.read_text()) for p in remote.glob("runs/**/result.json")]
    assert len(records) == 3 and all(r["log_steps"] > 0 for r in records)  # logs checked
    assert len({r["lcm_url"] for r in records}) == len({r["prefix"] for r in records}) == 3
    for r in records:
        assert (remote / "runs" / r["run"] / "plant.lcmlog").stat().st_size > 1000
    assert (remote / "report.md").is_file() and (remote / "figures").is_dir()


def _task_processes() -> dict[int, str]:
    """Processes that ftc's Ray tasks started (their command lines name the task's
    temporary directory)."""
    found = {}
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                cmd = (p / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            except OSError:
                continue
            if "/ftc-ray-run-" in cmd:
                found[int(p.name)] = cmd
    return found


@pytest.mark.slow  # tens of seconds; the default tier keeps the benchmark on Ray
def test_killed_driver_leaves_finished_runs_and_resume_on_ray_skips_them(head, tmp_path):
    out = tmp_path / "resume"
    args = [*EXPERIMENT[:2], "closed", "open", "--seeds", "0", "1", *EXPERIMENT[7:11],
            "--executor", "ray", "--ray-address", head["address"], "--jobs", "1",
            "--out", str(out)]
    args[args.index("--steps-per-interval") + 1] = "128"  # long enough to be caught running
    proc = subprocess.Popen([sys.executable, "-m", "ftc.experiments", *args],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=head["env"],
                            cwd=REPO)
    deadline = time.monotonic() + 240
    runs = out / "runs" / "single" / "t00"
    while not (any(is_finished(d) for d in runs.glob("*/s*")) and _task_processes()):
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
        assert time.monotonic() < deadline, "no run finished while another ran"
        time.sleep(0.1)
    running = _task_processes()
    proc.kill()
    proc.wait()
    finished = [d for d in runs.glob("*/s*") if is_finished(d)]
    before = {d: _digest(d) for d in finished}
    # Ray ends a dead driver's tasks; each task's guardian then kills its processes.
    deadline = time.monotonic() + 60
    while set(running) & set(_task_processes()):
        assert time.monotonic() < deadline, f"left running: {running}"
        time.sleep(0.2)
    # a task killed hard leaves its directory (removed by a later task, below);
    # one that Ray stopped gently may have removed it itself (seen in CI):
    # test__task_dir_removes_dead_workers_directories checks the sweep alone
    left = [d for d in Path(tempfile.gettempdir()).glob("ftc-ray-run-*")
            if any(str(d) in cmd for cmd in running.values())]
    done = _cli(["--resume", *args], head["env"])
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"({len(finished)} already finished)" in done.stderr
    assert {d: _digest(d) for d in finished} == before
    assert sum(is_finished(d) for d in runs.glob("*/s*")) == 4
    assert not any(d.exists() for d in left), "a later task removes a dead task's directory"


@pytest.mark.slow  # tens of seconds; the default tier keeps the benchmark on Ray
def test_a_failing_task_is_reported_like_a_failing_local_run(head, tmp_path):
    args = [*BENCH[:5], "--seeds", "0", *BENCH[8:], "--run-timeout", "0.001"]
    local = _cli([*args, "--out", str(tmp_path / "local")], _env())
    remote = _cli([*args, "--out", str(tmp_path / "ray"), "--executor", "ray",
                   "--ray-address", head["address"]], head["env"])
    for proc, out in ((local, tmp_path / "local"), (remote, tmp_path / "ray")):
        assert proc.returncode == 1, proc.stderr[-2000:]
        failed = [x for x in proc.stderr.splitlines() if ": FAILED: " in x]
        assert sorted(failed) == ["single/t00/closed/s0: FAILED: timed out after 0 s",
                                  "single/t00/oracle-mpc/s0: FAILED: timed out after 0 s"]
        assert proc.stderr.strip().splitlines()[-1].endswith(
            "2 runs failed: single/t00/closed/s0, single/t00/oracle-mpc/s0")
        run = out / "runs" / "single" / "t00" / "closed" / "s0"
        assert (run / "controller.log").is_file() and not is_finished(run)  # kept to look at


@pytest.mark.parametrize("command", [BENCH, EXPERIMENT])
def test_unreachable_address_is_one_line_exit_2_and_writes_nothing(command, tmp_path):
    out = tmp_path / "out"
    address = f"127.0.0.1:{_free_port()}"  # nobody listens there
    proc = _cli([*command, "--executor", "ray", "--ray-address", address, "--out", str(out)],
                _env(), timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"ftc.experiments{' benchmark' if command is BENCH else ''}: error: --ray-address "
        f"{address}: cannot reach a Ray head there (Connection refused)"]
    assert not out.exists()


def test_ray_address_without_the_ray_executor_is_a_usage_error(tmp_path, capsys):
    for argv in (["single", "--ray-address", "127.0.0.1:1"],
                 ["benchmark", "--ray-address", "127.0.0.1:1"]):
        with pytest.raises(SystemExit) as e:
            cli.main([*argv, "--out", str(tmp_path / "out")])
        assert e.value.code == 2
        assert capsys.readouterr().err.strip().endswith(
            "error: --ray-address 127.0.0.1:1: only with --executor ray")
    assert not (tmp_path / "out").exists()


def test_a_node_with_other_code_is_refused_before_anything_is_written(head, tmp_path):
    """The driver runs a copy of the package with one changed line; the head's
    workers run the repository's: refused, naming the node and what differs."""
    copy = tmp_path / "repo" / "python" / "ftc"
    shutil.copytree(REPO / "python" / "ftc", copy,
                    ignore=shutil.ignore_patterns("__pycache__"))
    with open(copy / "experiments" / "suite.py", "a") as f:
        f.write("# changed\n")
    env = dict(head["env"], PYTHONPATH=str(copy.parent), FTC_BUILD_DIR=str(REPO / "build"))
    out = tmp_path / "out"
    proc = _cli([*BENCH, "--executor", "ray", "--ray-address", head["address"],
                 "--out", str(out)], env, timeout=300)
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        f"ftc.experiments benchmark: error: --ray-address {head['address']}: node "
        f"{socket.gethostname()} runs git revision "), lines
    assert "the driver unknown" in lines[0]  # the copy is no git checkout
    assert not out.exists()


def test_identity_names_what_differs():
    me = ray_executor.code_identity()
    assert ray_executor.identity_problem(me, {**me, "host": "n1"}) is None
    other = {**me, "host": "n1", "sources": "0" * 16}
    assert ray_executor.identity_problem(me, other) == (
        f"node n1 runs sources {'0' * 16}, the driver {me['sources']}; every node needs the "
        "repository at the driver's revision, built")


def test__task_dir_removes_dead_workers_directories(tmp_path, monkeypatch):
    # the sweep that keeps a node's temporary directory from filling with the
    # directories of tasks killed with their driver: a dead worker's go, a
    # live worker's stay, and the new one is named with this worker's pid
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    dead_pid = next(p for p in range(4_000_000, 4_100_000) if not Path(f"/proc/{p}").exists())
    dead = tmp_path / f"ftc-ray-run-{dead_pid}-abc"
    live = tmp_path / f"ftc-ray-run-{os.getpid()}-def"
    other_kind = tmp_path / f"ftc-ray-baseline-{dead_pid}-ghi"
    for d in (dead, live, other_kind):
        (d / "runs").mkdir(parents=True)
    new = ray_executor._task_dir("run")
    assert not dead.exists() and live.exists() and other_kind.exists()
    assert new.parent == tmp_path and new.name.startswith(f"ftc-ray-run-{os.getpid()}-")
