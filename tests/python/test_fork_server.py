"""The fork server (ftc/experiments/fork_server.py): a run forked from it is
the process ``python -m MODULE ARGS`` would have been (same results bit for
bit, its own session and niceness, its log, its exit status), and nothing it
starts outlives it."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from ftc.experiments.fork_server import ForkServer, ForkServerGone
from ftc.experiments.processes import RunHandle

PROBE = textwrap.dedent('''
    """What a forked child sees, written where its first argument says."""
    import json, os, sys, time
    out, action = sys.argv[1], sys.argv[2]
    with open(out, "w") as f:
        json.dump({"argv": sys.argv, "pid": os.getpid(), "pgid": os.getpgid(0),
                   "sid": os.getsid(0), "nice": os.nice(0), "main": __name__,
                   "stdin": sys.stdin.read(), "cwd": os.getcwd(),
                   "probe_env": os.environ.get("FS_PROBE")}, f)
    print("to stdout")
    print("to stderr", file=sys.stderr)
    if action == "exit3":
        sys.exit(3)
    if action == "raise":
        raise ValueError("boom")
    if action == "sleep":
        time.sleep(60)
''')


@pytest.fixture
def server(tmp_path, monkeypatch):
    (tmp_path / "fs_probe.py").write_text(PROBE)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), *sys.path]))
    s = ForkServer(["json"])
    yield s
    s.close()


def _probe(server: ForkServer, tmp_path: Path, action: str, nice: int = 0):
    log = tmp_path / f"{action}.log"
    log.write_bytes(b"")
    return server.spawn("fs_probe", [str(tmp_path / f"{action}.json"), action], log, nice)


def test_a_forked_child_is_what_python_dash_m_would_start(server, tmp_path):
    import json

    proc = _probe(server, tmp_path, "ok", nice=3)
    assert proc.wait(timeout=30) == 0
    seen = json.loads((tmp_path / "ok.json").read_text())
    assert seen["main"] == "__main__"
    assert seen["argv"][1:] == [str(tmp_path / "ok.json"), "ok"]
    assert seen["pid"] == proc.pid == seen["pgid"] == seen["sid"]  # its own session
    assert seen["nice"] == os.nice(0) + 3
    assert seen["stdin"] == ""  # /dev/null, not the server's request pipe
    assert (tmp_path / "ok.log").read_text().splitlines() == ["to stdout", "to stderr"]


def test_a_child_can_get_its_own_stderr_directory_and_environment(server, tmp_path):
    import json

    work, log, err = tmp_path / "work", tmp_path / "own.log", tmp_path / "own.err"
    work.mkdir()
    env = {**os.environ, "FS_PROBE": "set for this child"}
    proc = server.spawn("fs_probe", [str(tmp_path / "own.json"), "exit3"], log, err=err,
                        cwd=work, env=env)
    assert proc.wait(timeout=30) == 3
    seen = json.loads((tmp_path / "own.json").read_text())
    assert seen["cwd"] == str(work) and seen["probe_env"] == "set for this child"
    assert log.read_text() == "to stdout\n" and err.read_text() == "to stderr\n"
    # the next child is back to the server's directory and environment
    proc = _probe(server, tmp_path, "ok")
    assert proc.wait(timeout=30) == 0
    seen = json.loads((tmp_path / "ok.json").read_text())
    assert seen["cwd"] == os.getcwd() and seen["probe_env"] is None


def test_a_child_that_cannot_start_says_why_in_its_own_stderr(server, tmp_path):
    err = tmp_path / "gone.err"
    proc = server.spawn("fs_probe", [str(tmp_path / "gone.json"), "ok"], tmp_path / "gone.log",
                        err=err, cwd=tmp_path / "no-such-directory")
    assert proc.wait(timeout=30) == 1
    assert "cannot start fs_probe" in err.read_text() and "no-such-directory" in err.read_text()
    assert not (tmp_path / "gone.json").exists()
    assert _probe(server, tmp_path, "ok").wait(timeout=30) == 0  # the server serves on


@pytest.mark.parametrize("action, code, text", [("exit3", 3, "to stderr"),
                                                ("raise", 1, "ValueError: boom")])
def test_exit_status_and_uncaught_exceptions_are_reported(server, tmp_path, action, code, text):
    proc = _probe(server, tmp_path, action)
    assert proc.wait(timeout=30) == code
    assert text in (tmp_path / f"{action}.log").read_text()


def test_a_killed_child_reports_the_signal_and_wait_times_out_before(server, tmp_path):
    proc = _probe(server, tmp_path, "sleep")
    with pytest.raises(subprocess.TimeoutExpired):
        proc.wait(timeout=0.2)
    assert proc.poll() is None
    os.killpg(proc.pid, signal.SIGTERM)  # how RunHandle.stop stops a run
    assert proc.wait(timeout=30) == -signal.SIGTERM


def test_children_die_with_the_server_and_a_gone_server_refuses(server, tmp_path):
    proc = _probe(server, tmp_path, "sleep")
    deadline = time.monotonic() + 30
    while not (tmp_path / "sleep.json").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    server.process.kill()  # the server dies without closing anything
    assert proc.wait(timeout=30) == -signal.SIGKILL
    deadline = time.monotonic() + 10
    while _alive(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(proc.pid)  # the parent-death signal killed it
    with pytest.raises(ForkServerGone):
        _probe(server, tmp_path, "ok")
    # a run handle then starts a fresh python instead
    handle = RunHandle("k", tmp_path, fork_server=server)
    fresh = handle.launch([sys.executable, "-m", "fs_probe", str(tmp_path / "f.json"), "ok"],
                          tmp_path / "f.log", 0)
    assert isinstance(fresh, subprocess.Popen) and fresh.wait(timeout=60) == 0


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _metrics(path: Path) -> list[dict]:
    timing = ("seconds", "time", "_s", "decisions_per_second")
    return [{k: v for k, v in row.items() if not any(t in k for t in timing)}
            for row in csv.DictReader(path.open())]


def test_a_forked_controller_run_equals_a_fresh_process_bit_for_bit(tmp_path, scenarios):
    """PPO online (torch: sampling, updates, the global generators) over 2 short
    intervals: every metric but the timings equal, as strings (bit for bit)."""
    args = ["--method", "ppo", "--no-offline", "--scenario", str(scenarios / "single.toml"),
            "--seed", "1", "--intervals", "2", "--steps-per-interval", "256", "--link", "core"]
    fresh = subprocess.run([sys.executable, "-m", "ftc.controller", *args,
                            "--out", str(tmp_path / "fresh")], capture_output=True, timeout=300)
    assert fresh.returncode == 0, fresh.stderr.decode()[-2000:]
    server = ForkServer(["ftc.controller"])
    try:
        log = tmp_path / "forked.log"
        log.write_bytes(b"")
        proc = server.spawn("ftc.controller", [*args, "--out", str(tmp_path / "forked")], log)
        assert proc.wait(timeout=300) == 0, log.read_text()[-2000:]
    finally:
        server.close()
    a, b = _metrics(tmp_path / "fresh" / "metrics.csv"), _metrics(tmp_path / "forked" / "metrics.csv")
    assert len(a) == 2 and a == b


def test_the_process_group_exists_as_soon_as_spawn_returns(server, tmp_path):
    """The orchestrator may kill a run's group at once (--run-timeout 0.001): the
    server reports a child only after its setsid, as Popen does after exec."""
    for _ in range(20):
        proc = _probe(server, tmp_path, "sleep")
        os.killpg(proc.pid, signal.SIGKILL)  # ProcessLookupError if the group did not exist
        assert proc.wait(timeout=30) == -signal.SIGKILL


def test_ctrl_c_at_the_orchestrator_leaves_the_server_and_its_runs_to_it(server, tmp_path):
    """SIGINT to the orchestrator's process group (Ctrl-C) reaches the server:
    it ignores it (the orchestrator stops the runs, then closes the server);
    its children get Python's usual SIGINT handling back."""
    import json

    proc = _probe(server, tmp_path, "sleep")
    deadline = time.monotonic() + 30
    while not (tmp_path / "sleep.json").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    server.process.send_signal(signal.SIGINT)
    time.sleep(0.5)
    assert server.process.poll() is None
    assert proc.poll() is None
    os.kill(proc.pid, signal.SIGINT)  # KeyboardInterrupt in the child: traceback, status 1
    assert proc.wait(timeout=30) == 1
    assert "KeyboardInterrupt" in (tmp_path / "sleep.log").read_text()
    assert json.loads((tmp_path / "sleep.json").read_text())["main"] == "__main__"
