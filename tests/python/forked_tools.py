"""``python -m MODULE ARGS`` for tests that start a tool many times: forked
from one process per test worker that has imported the tools once
(:mod:`ftc.experiments.fork_server`, the experiments' own way of starting
runs). The child is the process the command would have started: its own
session, argv and ``__main__``, stdin from /dev/null, its exit status
(tests/python/test_fork_server.py, bit for bit on a PPO run). A start costs
a fork instead of the 3-6 s of importing torch and the controllers that a
fresh ``ftc.mpc`` or ``ftc.controller`` spends before it reads its first flag.
What those modules do at import time happens once, in the server: tests of
that stay on a fresh ``python -m`` (test_fault_injection keeps one per tool).
"""

from __future__ import annotations

import atexit
import contextlib
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Sequence

from ftc.experiments.fork_server import ForkServer

PRELOADED = ("ftc.controller", "ftc.mpc")  # what the server imports (their imports stay)
_server: ForkServer | None = None


def _fork_server() -> ForkServer:
    global _server
    if _server is None or _server.gone:
        _server = ForkServer(list(PRELOADED))
        atexit.register(_server.close)
    return _server


def run_tool(module: str, args: Sequence[str], cwd: Path | str, env: dict[str, str] | None = None,
             timeout: float = 600) -> subprocess.CompletedProcess:
    """What ``subprocess.run([python, "-m", module, *args], capture_output=True,
    text=True, cwd=cwd, env=env, timeout=timeout)`` returns, the process forked;
    on a timeout its process group is killed and TimeoutExpired raised."""
    argv = [sys.executable, "-m", module, *args]
    with tempfile.TemporaryDirectory(prefix="ftc-forked-") as d:
        out, err = Path(d) / "stdout", Path(d) / "stderr"
        # the environment of the moment, as subprocess.run would take it (the
        # server's is the one it started with)
        proc = _fork_server().spawn(module, list(args), out, err=err, cwd=Path(cwd),
                                    env=dict(os.environ) if env is None else env)
        try:
            code = proc.wait(timeout)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):  # it may have just ended
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(30)
            raise
        return subprocess.CompletedProcess(argv, code, out.read_text(), err.read_text())
