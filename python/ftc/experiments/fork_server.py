"""Runs started by forking a process that has already imported the controllers.

Every run is a fresh ``python -m ftc.controller`` (or ``ftc.mpc``) process,
and importing torch and the controllers is 1-2 s of each: the 660 runs of the
every-method benchmark suite spent about 16 min of CPU on it, more than any
method but ppo-robust and identified-mpc (docs/benchmarks.md). The fork server is one
process per orchestrator that imports them once and forks a child per run.
The child is the process the command would have started: its own session
(process group = pid, so stopping the group stops what it starts), the
niceness added, stdin from /dev/null, stdout and stderr into the run's log,
``sys.argv`` and ``__main__`` as ``python -m MODULE ARGS`` sets them, and its
exit status (``sys.exit`` codes, 1 on an uncaught exception, -N when killed by
signal N) reported back. Nothing has run in the server but imports (no
thread, no torch operation, no LCM instance), so the fork starts from the
same state a fresh process reaches after its imports: results are
bit-identical (tests/python/test_fork_server.py).

Protocol (lines on the server's stdin and stdout): the orchestrator sends a
JSON request ``{"id", "module", "args", "log", "nice"}``, optionally with
``"err"`` (stderr to its own file), ``"cwd"`` and ``"env"`` (the child's
working directory and whole environment, as ``subprocess.run`` takes them,
read by what the child does, not by the imports it was forked with); the
server answers
``started ID PID`` (or ``failed ID MESSAGE``) and, when a child ends,
``exited PID STATUS``. It exits when its stdin closes; its children then get
SIGKILL (a parent-death signal, as subprocess runs had from the orchestrator).
"""

from __future__ import annotations

import importlib
import json
import os
import runpy
import select
import signal
import subprocess
import sys
import threading
import traceback
from pathlib import Path
from typing import Sequence

from ftc.common.lifetime import die_with_parent


class ForkServerGone(RuntimeError):
    """The fork server exited (or never started): no run can be started by it."""


class ForkedProcess:
    """What the orchestrator uses of a :class:`subprocess.Popen`, for a child of
    the fork server (``pid``, ``returncode``, ``poll``, ``wait``)."""

    def __init__(self, server: "ForkServer", pid: int, args: list[str]) -> None:
        self.server, self.pid, self.args = server, pid, args
        self.returncode: int | None = None

    def poll(self) -> int | None:
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        with self.server.changed:
            if not self.server.changed.wait_for(lambda: self.returncode is not None, timeout):
                raise subprocess.TimeoutExpired(self.args, timeout)
        return self.returncode


class ForkServer:
    """The orchestrator's side: starts the server (from the thread that will
    outlive the runs: the children die with it) and forks runs from it."""

    def __init__(self, modules: Sequence[str], start_timeout: float = 120.0) -> None:
        self.modules = list(modules)
        self.process = subprocess.Popen(
            [sys.executable, "-c", "import sys; from ftc.experiments.fork_server import serve; "
             "sys.exit(serve(sys.argv[1:]))", *self.modules],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1,
            preexec_fn=die_with_parent())
        self.changed = threading.Condition()
        self._started: dict[int, int | str] = {}  # request id -> pid, or the error
        self._children: dict[int, ForkedProcess] = {}
        self._exits: dict[int, int] = {}  # statuses of children not yet claimed
        self._next_id = 0
        self.gone: str | None = None
        self._send_lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True,
                                        name="fork-server-reader")
        self._ready = threading.Event()
        self._reader.start()
        if not self._ready.wait(start_timeout) or self.gone:
            self.close()
            raise ForkServerGone(f"the fork server did not start ({self.gone or 'timed out'})")

    def _read(self) -> None:
        for line in self.process.stdout:
            word, *rest = line.split(None, 2)
            with self.changed:
                if word == "ready":
                    self._ready.set()
                elif word == "started":
                    self._started[int(rest[0])] = int(rest[1])
                elif word == "failed":
                    self._started[int(rest[0])] = rest[1].strip() if len(rest) > 1 else "?"
                elif word == "exited":
                    pid, status = int(rest[0]), int(rest[1])
                    if pid in self._children:
                        self._children.pop(pid).returncode = status
                    else:  # the exit came before the start was claimed
                        self._exits[pid] = status
                self.changed.notify_all()
        with self.changed:  # stdout closed: the server is gone, so are its children
            self.gone = f"exited with code {self.process.wait()}"
            for child in self._children.values():
                child.returncode = -signal.SIGKILL
            self._children.clear()
            self._ready.set()
            self.changed.notify_all()

    def spawn(self, module: str, args: Sequence[str], log: Path, nice: int = 0,
              err: Path | None = None, cwd: Path | None = None,
              env: dict[str, str] | None = None) -> ForkedProcess:
        """Fork ``python -m module args`` with stdout and stderr appended to
        ``log`` (stderr to ``err`` when given), in ``cwd`` with environment
        ``env`` when given (else the server's)."""
        with self.changed:
            if self.gone:
                raise ForkServerGone(f"the fork server {self.gone}")
            request_id, self._next_id = self._next_id, self._next_id + 1
        request = {"id": request_id, "module": module, "args": list(args),
                   "log": str(Path(log).resolve()), "nice": nice}
        if err is not None:
            request["err"] = str(Path(err).resolve())
        if cwd is not None:
            request["cwd"] = str(Path(cwd).resolve())
        if env is not None:
            request["env"] = dict(env)
        try:
            with self._send_lock:
                self.process.stdin.write(json.dumps(request) + "\n")
                self.process.stdin.flush()
        except (BrokenPipeError, ValueError, OSError):
            raise ForkServerGone("the fork server's stdin is closed") from None
        with self.changed:
            self.changed.wait_for(lambda: request_id in self._started or self.gone)
            started = self._started.pop(request_id, None)
            if started is None:
                raise ForkServerGone(f"the fork server {self.gone}")
            if isinstance(started, str):
                raise OSError(f"cannot fork {module}: {started}")
            child = ForkedProcess(self, started, ["python", "-m", module, *args])
            if started in self._exits:
                child.returncode = self._exits.pop(started)
            else:
                self._children[started] = child
            return child

    def close(self) -> None:
        """Close the server's stdin (it exits; children still running get SIGKILL)."""
        try:
            self.process.stdin.close()
        except OSError:
            pass
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


# ---------------------------------------------------------------------------
# The server
# ---------------------------------------------------------------------------

def _child(request: dict, inherited: Sequence[int], tie_to_server, in_session: int) -> int:
    """In the forked child: become ``python -m module args``; returns its exit status.
    A byte on ``in_session`` tells the server its session (and process group) exists."""
    os.setsid()
    os.write(in_session, b"s")
    os.close(in_session)
    tie_to_server()  # SIGKILL when the server goes
    signal.set_wakeup_fd(-1)
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a fresh python
    for fd in inherited:
        os.close(fd)
    # the run's files first (absolute paths), so that what fails after lands in them
    null = os.open(os.devnull, os.O_RDONLY)
    log = os.open(request["log"], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    err = (os.open(request["err"], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
           if "err" in request else log)
    for fd, target in ((null, 0), (log, 1), (err, 2)):
        if fd != target:
            os.dup2(fd, target)
    for fd in {null, log, err} - {0, 1, 2}:
        os.close(fd)
    try:
        if request["nice"]:
            os.nice(request["nice"])
        if "env" in request:
            os.environ.clear()
            os.environ.update(request["env"])
        if "cwd" in request:
            os.chdir(request["cwd"])
    except OSError as e:  # as python -m would never have started: one line, status 1
        os.write(2, f"fork server: cannot start {request['module']}: {e}\n".encode())
        return 1
    sys.stdin = open(0, closefd=False)
    sys.argv = [request["module"], *request["args"]]
    try:
        runpy.run_module(request["module"], run_name="__main__", alter_sys=True)
    except SystemExit as e:
        if e.code is None or isinstance(e.code, int):
            return e.code or 0
        print(e.code, file=sys.stderr)  # sys.exit("message"): printed, status 1
        return 1
    except BaseException:  # noqa: BLE001 - uncaught: the traceback and status 1, as python does
        traceback.print_exc()
        return 1
    return 0


def _exit(code: int) -> None:
    """End the child as the interpreter would, less tearing down its modules:
    non-daemon threads joined, atexit handlers run, stdout and stderr flushed,
    then _exit. The teardown is what it skips: freeing every object of torch's
    import touches (and so copies) every page the child shares with the
    server, 0.9 s of a 1.0 s closed-valves run of 2 x 128 steps (measured)."""
    try:
        threading._shutdown()  # what Py_FinalizeEx does first (CPython 3.8+)
        import atexit
        atexit._run_exitfuncs()
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
    finally:
        os._exit(code)


def _reap(out) -> None:
    while True:
        try:
            pid, status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return
        out.write(f"exited {pid} {os.waitstatus_to_exitcode(status)}\n")
        out.flush()


def serve(modules: Sequence[str]) -> int:
    """The server's loop (a forked child ends in :func:`_exit`)."""
    for module in modules:  # its imports stay loaded; it is forgotten so that runpy
        importlib.import_module(module)  # runs it afresh as __main__, as python -m does
        del sys.modules[module]
    tie_to_server = die_with_parent()  # made here: it checks the parent is this process
    # Ctrl-C reaches the orchestrator's process group, this server included: the
    # orchestrator stops the runs (their own sessions) and then closes the server
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_r, False)
    os.set_blocking(wake_w, False)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    signal.set_wakeup_fd(wake_w)
    out = sys.stdout
    out.write("ready\n")
    out.flush()
    stdin = sys.stdin.buffer.raw  # unbuffered: select() sees every line
    pending = b""
    while True:
        try:
            readable, _, _ = select.select([stdin, wake_r], [], [])
        except InterruptedError:
            continue
        if wake_r in readable:
            try:
                os.read(wake_r, 4096)
            except BlockingIOError:
                pass
            _reap(out)
        if stdin in readable:
            chunk = os.read(stdin.fileno(), 65536)
            if not chunk:
                return 0
            pending += chunk
            while b"\n" in pending:
                line, pending = pending.split(b"\n", 1)
                request = json.loads(line)
                out.flush()
                session_r, session_w = os.pipe()
                try:
                    pid = os.fork()
                except OSError as e:
                    os.close(session_r)
                    os.close(session_w)
                    out.write(f"failed {request['id']} {e}\n")
                    out.flush()
                    continue
                if pid == 0:
                    os.close(session_r)
                    code = 1
                    try:
                        code = _child(request, (wake_r, wake_w, 0), tie_to_server, session_w)
                    finally:  # never back into the server's loop, whatever happened
                        _exit(code)
                os.close(session_w)
                # reported once its process group exists (killpg on the pid must find it,
                # as after Popen(start_new_session=True)); EOF: it died before that
                os.read(session_r, 1)
                os.close(session_r)
                out.write(f"started {request['id']} {pid}\n")
                out.flush()
        _reap(out)

