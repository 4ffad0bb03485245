"""The processes of a run other than its controller: the recorder of its LCM
traffic; the bookkeeping (pid and start time of every process group a run
starts) that lets --resume stop what a killed orchestrator left running; and
what makes the children die with the orchestrator (a parent-death signal on
each, and a guardian process that kills their process groups, the plants
the controllers started included, once the orchestrator is gone); the lock
that keeps two orchestrators out of one run directory.

Every process is started in its own session, so its process group id is its
pid and stopping the group stops the plant a controller started too.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from ftc.common.atomic import atomic_write_json
from ftc.common.build_info import recorder_binary
from ftc.common.errors import EXIT_STORAGE, RunError, StorageError
from ftc.common.lifetime import die_with_parent
from ftc.common.replacing import Replacement
from ftc.common.run_lock import InUse, RunLock, check_free, proc_start_time
from ftc.experiments.fork_server import ForkedProcess, ForkServer, ForkServerGone

LOCK_NAME = "orchestrator.lock"


class RunFailed(RunError):
    """One run failed (the others go on); the message says why."""


OutInUse = InUse  # the run directory belongs to an orchestrator that is still running


# The guardian: reads "+gPGID" / "+pPID" lines (a process group, a single
# process) and "-..." to forget one while the orchestrator lives; at end of
# input (the orchestrator has exited or was killed) it kills what is still
# listed. Standard library only, so it starts in a few milliseconds.
_GUARDIAN = r"""
import os, signal, sys
signal.signal(signal.SIGINT, signal.SIG_IGN)
listed = set()
for line in sys.stdin:
    line = line.strip()
    if line[:1] == "+":
        listed.add(line[1:])
    elif line[:1] == "-":
        listed.discard(line[1:])
for entry in listed:
    try:
        (os.killpg if entry[0] == "g" else os.kill)(int(entry[1:]), signal.SIGKILL)
    except (OSError, ValueError):
        pass
"""


class Guardian:
    """Kills the process groups of the runs (controller, its plant, recorder) when
    the orchestrator ends in any way, SIGKILL included: the parent-death signal
    reaches only a direct child, not the plant a controller started."""

    def __init__(self) -> None:
        self.process = subprocess.Popen([sys.executable, "-S", "-c", _GUARDIAN],
                                        stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                        stderr=subprocess.DEVNULL, text=True,
                                        start_new_session=True)

    def _send(self, line: str) -> None:
        try:
            self.process.stdin.write(line + "\n")
            self.process.stdin.flush()
        except (OSError, ValueError):
            pass

    def watch(self, pgid: int) -> None:
        """Kill process group ``pgid`` when the orchestrator dies."""
        self._send(f"+g{pgid}")

    def release(self, pgid: int) -> None:
        self._send(f"-g{pgid}")

    def watch_process(self, pid: int) -> None:
        """Kill process ``pid`` (not a group leader) when the orchestrator dies."""
        self._send(f"+p{pid}")

    def release_process(self, pid: int) -> None:
        self._send(f"-p{pid}")

    def close(self) -> None:
        try:
            self.process.stdin.close()
        except OSError:
            pass
        self.process.wait()


def record_process(run_dir: Path, name: str, proc: subprocess.Popen) -> None:
    """Note a started process group (pid and start time) so --resume can stop a
    leftover of a killed orchestrator, and nothing else."""
    path = run_dir / "processes.json"
    try:
        procs = json.loads(path.read_text())
    except (OSError, ValueError):
        procs = {}
    procs[name] = {"pid": proc.pid, "start": proc_start_time(proc.pid)}
    atomic_write_json(path, procs)


def stop_leftover_processes(run_dir: Path) -> None:
    """Stop process groups a killed earlier orchestrator left running for this run."""
    try:
        procs = json.loads((run_dir / "processes.json").read_text())
    except (OSError, ValueError):
        return
    for info in procs.values():
        pid, start = info.get("pid"), info.get("start")
        # The start time tells a leftover from an unrelated process that reuses the pid.
        if pid and start and proc_start_time(pid) == start:
            try:
                os.killpg(pid, signal.SIGKILL)  # its own session: pgid == pid
            except OSError:
                pass


@dataclass
class RunHandle:
    """A run in progress: its processes, so the orchestrator can stop them.

    key: the run's key (experiment/tNN/method/sS); directory: its run directory
    started: wall-clock start, s since the epoch (0 until its processes start)
    fork_server: where its controller is forked from (None: a fresh python)
    """

    key: str
    directory: Path
    started: float = 0.0
    processes: list[subprocess.Popen] = field(default_factory=list)
    cancelled: bool = False
    guardian: Guardian | None = None
    fork_server: "ForkServer | None" = None

    def launch(self, cmd: list[str], log: Path, nice: int) -> "subprocess.Popen | ForkedProcess":
        """Start ``cmd`` (``python -m MODULE ARGS``) in its own session, niced by
        ``nice``, stdout and stderr into ``log`` (truncated): forked from the fork
        server if there is one (a fresh python if it has gone)."""
        with open(log, "wb") as out:
            if self.fork_server is not None and cmd[1:2] == ["-m"]:
                try:
                    return self.fork_server.spawn(cmd[2], cmd[3:], log, nice)
                except ForkServerGone:
                    pass
            # The controller (and the plant it starts) run at a lower priority
            # than the recorder, so a busy machine slows the run down instead of
            # making the recorder drop messages (lcm-logger's subscription queue
            # is bounded and it missed states under load at equal priority).
            return subprocess.Popen(["nice", "-n", str(nice), *cmd], stdin=subprocess.DEVNULL,
                                    stdout=out, stderr=subprocess.STDOUT,
                                    start_new_session=True, preexec_fn=die_with_parent())

    def watch(self, proc: subprocess.Popen) -> None:
        """Have the guardian kill ``proc``'s process group if the orchestrator dies."""
        if self.guardian is not None:
            self.guardian.watch(proc.pid)

    def release(self) -> None:
        """The run's processes have ended: the guardian forgets their groups."""
        if self.guardian is not None:
            for p in self.processes:
                self.guardian.release(p.pid)

    def stop(self) -> None:
        self.cancelled = True
        for p in self.processes:
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except OSError:
                    pass


def _raise_priority() -> None:
    """Run the recorder ahead of the runs it records: lcm-logger dispatches from
    a bounded subscription queue, so a recorder starved of CPU on a busy machine
    drops messages (measured: 2-49 plant states per run at load 8 on 2 cores).
    Raising priority needs privileges; without them the niceness of the runs
    (ExperimentConfig.nice) still favours the recorder."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, -10)
    except OSError:
        pass


def with_recv_buffer(url: str) -> str:
    """url with the largest UDP receive buffer the kernel allows (up to 64 MiB;
    scripts/setup.sh raises net.core.rmem_max to that where it may)."""
    if not url.startswith("udpm://") or "recv_buf_size" in url:
        return url
    try:
        limit = int(Path("/proc/sys/net/core/rmem_max").read_text())
    except (OSError, ValueError):
        limit = 1 << 21
    size = max(1 << 18, min(limit, 1 << 26))
    return url + ("&" if "?" in url else "?") + f"recv_buf_size={size}"


class LcmLogger:
    """The recorder (build/lcm_recorder, lcm-logger's format) of one run's channels
    on its private URL.

    Started before the plant and confirmed ready by seeing a probe message of
    ours in its file; stopped after the run with an end marker seen in the file
    (so every message the plant sent before it is on disk) and SIGINT.
    """

    def __init__(self, url: str, prefix: str, path: Path, stderr_path: Path,
                 timeout: float = 10.0,
                 on_start: Callable[[subprocess.Popen], None] | None = None) -> None:
        import lcm

        self.url, self.prefix, self.path, self.timeout = url, prefix, path, timeout
        self._lc = lcm.LCM(url)
        self._stderr = open(stderr_path, "wb")
        # A large receive buffer: in lockstep the plant and controller exchange
        # thousands of messages a second, and a logger descheduled for a few
        # tens of ms on a busy machine would otherwise lose some (measured: 5 of
        # 400 with the default 208 KiB, two runs on two cores).
        self.process = subprocess.Popen(
            [str(recorder_binary()), "--flush-interval", "100",
             "--channel", f"{prefix}.*", "--lcm-url", with_recv_buffer(url), str(path)],
            stdin=subprocess.DEVNULL, stdout=self._stderr, stderr=self._stderr,
            start_new_session=True, preexec_fn=die_with_parent(_raise_priority))
        if on_start is not None:
            on_start(self.process)
        self._wait_for(f"{prefix}LOGGER_START")

    def _wait_for(self, channel: str) -> None:
        needle = channel.encode()
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                if self.process.returncode == EXIT_STORAGE:
                    raise StorageError(f"cannot write {self.path}: the recorder's write "
                                       "failed (disk full?)")
                raise RunFailed(f"recorder exited with code {self.process.returncode} "
                                f"(see {self._stderr.name})")
            self._lc.publish(channel, b"probe")
            # Waiting on an observable event (our probe reaching the file), not a
            # fixed delay; the poll period only bounds the cost of checking.
            self._lc.handle_timeout(20)
            try:
                with open(self.path, "rb") as f:
                    f.seek(max(0, self.path.stat().st_size - 4096))
                    if needle in f.read():
                        return
            except OSError:
                pass
        raise RunFailed(f"recorder on {self.url} did not record {channel} within "
                        f"{self.timeout:.0f} s")

    def stop(self) -> None:
        try:
            if self.process.poll() is None:
                self._wait_for(f"{self.prefix}LOGGER_END")
        finally:
            if self.process.poll() is None:
                self.process.send_signal(signal.SIGINT)
                try:
                    self.process.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    self.process.kill()
                    self.process.wait()
            self._stderr.close()


class OrchestratorLock(RunLock):
    """OUT/orchestrator.lock while an orchestrator runs on OUT (a
    :class:`ftc.common.run_lock.RunLock`: a live holder refuses with OutInUse,
    a stale one is taken over).

    While it is held no one else writes under OUT, so temporary files (``*.tmp``)
    there are leftovers of atomic writes cut short (a killed orchestrator, or a
    run stopped mid-write by SIGTERM when the disk filled): they are removed
    when the lock is taken and again when it is released, after every run
    has stopped."""

    def __init__(self, out: Path, tool: str = "ftc.experiments") -> None:
        super().__init__(out, tool, LOCK_NAME)

    def acquire(self) -> "OrchestratorLock":
        super().acquire()
        self.remove_temporaries()
        return self

    def remove_temporaries(self) -> None:
        for tmp in self.path.parent.rglob("*.tmp"):
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass

    def release(self) -> None:
        if self._fd is not None:
            self.remove_temporaries()
        super().release()


def a_run_finished(out: Path) -> bool:
    return any(Path(out).glob("runs/**/result.json"))


class OrchestratorReplacement:
    """--overwrite of an orchestrator's directory (:mod:`ftc.common.replacing`):
    what is in OUT moved aside once the lock is held; deleted once the new
    experiment has finished a run (checked when it ends, and by whoever next
    holds OUT if it was killed), moved back if it ends before any."""

    def __init__(self, out: Path, overwrite: bool) -> None:
        self.out = Path(out)
        self.overwrite = overwrite
        self.replacement = Replacement(self.out, os.listdir, a_run_finished)
        self.restored = False

    def __enter__(self) -> "OrchestratorReplacement":
        if self.overwrite:
            self.replacement.stash_old()
        else:
            self.replacement.settle()
        return self

    def __exit__(self, *exc: object) -> None:
        if a_run_finished(self.out):
            self.replacement.commit()
        elif self.overwrite:
            self.replacement.restore()
            self.restored = True


def check_out_free(out: Path) -> None:
    """Raise OutInUse if a live orchestrator holds OUT's lock (creates nothing)."""
    check_free(out, LOCK_NAME)
