"""The processes of a run other than its controller: the recorder of its LCM
traffic, and the bookkeeping (pid and start time of every process group a run
starts) that lets --resume stop what a killed orchestrator left running.

Every process is started in its own session, so its process group id is its
pid and stopping the group stops the plant a controller started too.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

from ftc import BUILD_DIR
from ftc.common.atomic import atomic_write_json
from ftc.common.errors import RunError


class RunFailed(RunError):
    """One run failed (the others go on); the message says why."""


def recorder_binary() -> Path:
    """build/lcm_recorder: records a run's traffic in lcm-logger's file format
    without lcm-logger's 30-message subscription queue, which dropped plant
    states whenever the recorder was briefly descheduled (measured: 2 to 752
    of ~5,000 per run on a loaded 2-core machine). See cpp/plant/apps/recorder.cpp."""
    path = BUILD_DIR / "lcm_recorder"
    if not path.is_file():
        raise FileNotFoundError(f"lcm_recorder not found at {path}; run scripts/setup.sh")
    return path


def _proc_start_time(pid: int) -> str | None:
    """The start time of process ``pid`` (clock ticks since boot), or None if it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def record_process(run_dir: Path, name: str, proc: subprocess.Popen) -> None:
    """Note a started process group (pid and start time) so --resume can stop a
    leftover of a killed orchestrator, and nothing else."""
    path = run_dir / "processes.json"
    try:
        procs = json.loads(path.read_text())
    except (OSError, ValueError):
        procs = {}
    procs[name] = {"pid": proc.pid, "start": _proc_start_time(proc.pid)}
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
        if pid and start and _proc_start_time(pid) == start:
            try:
                os.killpg(pid, signal.SIGKILL)  # its own session: pgid == pid
            except OSError:
                pass


@dataclass
class RunHandle:
    """A run in progress: its processes, so the orchestrator can stop them.

    key: the run's key (experiment/tNN/method/sS); directory: its run directory
    started: wall-clock start, s since the epoch (0 until its processes start)
    """

    key: str
    directory: Path
    started: float = 0.0
    processes: list[subprocess.Popen] = field(default_factory=list)
    cancelled: bool = False

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


def _with_recv_buffer(url: str) -> str:
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
                 timeout: float = 10.0) -> None:
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
             "--channel", f"{prefix}.*", "--lcm-url", _with_recv_buffer(url), str(path)],
            stdin=subprocess.DEVNULL, stdout=self._stderr, stderr=self._stderr,
            start_new_session=True, preexec_fn=_raise_priority)
        self._wait_for(f"{prefix}LOGGER_START")

    def _wait_for(self, channel: str) -> None:
        needle = channel.encode()
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
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
