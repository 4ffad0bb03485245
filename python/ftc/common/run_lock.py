"""One writer per result: the lock every tool takes on what it writes.

A lock is a file (``DIR/run.lock`` for a run directory, ``DIR/orchestrator.lock``
for an experiment, ``.NAME.lock`` beside a single output file) holding its
holder's pid, process start time, host, tool and start date, and an ``flock``
on it while the holder lives. The kernel drops an flock with its holder's last
descriptor, so a killed holder leaves a *stale* lock: the next writer takes it
over and says so. A live holder makes every other writer stop with one line
naming it (:class:`InUse`, exit 2).

On a file system without flock the pid and its start time tell a live holder
from a dead one (a reused pid has another start time); a holder on another
host cannot be checked from here and counts as live.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import socket
import sys
import time
from pathlib import Path
from typing import TextIO

from ftc.common.errors import StorageError, UsageError


class InUse(UsageError):
    """Another live process holds the lock of what this one would write."""


def proc_start_time(pid: int) -> str | None:
    """The start time of process ``pid`` (clock ticks since boot), or None if it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def read_lock(path: Path | str) -> dict:
    """The holder recorded in a lock file ({} when missing or unreadable)."""
    try:
        doc = json.loads(Path(path).read_text() or "{}")
        return doc if isinstance(doc, dict) else {}
    except (OSError, ValueError):
        return {}


def holder_alive(holder: dict) -> bool:
    """Whether the recorded holder may still run: its pid with the same start
    time on this host, or any holder on another host (unknowable from here)."""
    if holder.get("host") not in (None, socket.gethostname()):
        return True
    pid, start = holder.get("pid"), holder.get("start")
    return bool(isinstance(pid, int) and start and proc_start_time(pid) == start)


def describe(holder: dict) -> str:
    """'ftc.controller, pid 123 on host h, started 2026-...' (what is known)."""
    parts = [holder["tool"]] if holder.get("tool") else ["writer"]
    who = f"pid {holder['pid']}" if holder.get("pid") else "of unknown pid"
    if holder.get("host"):
        who += f" on {holder['host']}"
    parts.append(who)
    if holder.get("started"):
        parts.append(f"started {holder['started']}")
    return ", ".join(parts)


def in_use_message(target: Path, lock: Path, holder: dict) -> str:
    if holder.get("host") not in (None, socket.gethostname()):
        return (f"{target} is in use by {describe(holder)} (lock {lock}), which cannot be "
                "checked from this host: wait for it, or remove the lock if it is gone")
    return (f"{target} is in use by a running {describe(holder)} (lock {lock}): wait for it "
            "to finish or stop it first")


class RunLock:
    """The lock on ``target`` (a directory, or a file with ``beside=True``),
    taken by ``tool``. ``took_over``: the stale holder it replaced, if any."""

    def __init__(self, target: Path | str, tool: str, name: str = "run.lock",
                 beside: bool = False) -> None:
        self.target = Path(target)
        self.tool = tool
        self.path = (self.target.parent / f".{self.target.name}.lock" if beside
                     else self.target / name)
        self._fd: int | None = None
        self.took_over: dict | None = None

    def acquire(self) -> "RunLock":
        """Take the lock (creating the directory it lives in); raises InUse
        naming a live holder, StorageError when the lock cannot be written."""
        for _ in range(100):  # a holder releasing meanwhile unlinks the file: open anew
            fd = self._open_and_flock()
            if _still_linked(fd, self.path):
                break
            os.close(fd)
        else:
            raise StorageError(f"cannot lock {self.path}: it keeps being removed")
        holder = read_lock(self.path)
        if holder and holder.get("pid") != os.getpid() and holder_alive(holder):
            os.close(fd)  # a file system without flock: the record tells
            raise InUse(in_use_message(self.target, self.path, holder))
        self.took_over = holder or None
        me = json.dumps({"pid": os.getpid(), "start": proc_start_time(os.getpid()),
                         "host": socket.gethostname(), "tool": self.tool,
                         "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}).encode()
        try:
            os.ftruncate(fd, 0)
            if os.pwrite(fd, me, 0) != len(me):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        except OSError as e:
            os.close(fd)
            self.path.unlink(missing_ok=True)
            raise StorageError(f"cannot write {self.path}: {e.strerror or e}") from None
        self._fd = fd
        return self

    def _open_and_flock(self) -> int:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)  # less the umask
        except OSError as e:
            raise StorageError(f"cannot write {self.path}: {e.strerror or e}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            os.close(fd)
            if e.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                raise StorageError(f"cannot lock {self.path}: {e.strerror or e}") from None
            raise InUse(in_use_message(self.target, self.path, read_lock(self.path))) from None
        return fd

    def announce_takeover(self, stream: TextIO | None = None) -> None:
        """One line on ``stream`` (stderr) when a stale lock was taken over."""
        if self.took_over:
            print(f"{self.tool}: note: taking over the stale lock {self.path} of "
                  f"{describe(self.took_over)} (no longer running)",
                  file=stream or sys.stderr, flush=True)

    def release(self) -> None:
        if self._fd is not None:
            self.path.unlink(missing_ok=True)  # still holding it: no one sees a gap
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def _still_linked(fd: int, path: Path) -> bool:
    """Whether the locked descriptor is still the file at ``path`` (a holder
    that released meanwhile unlinked it: a lock on the old file locks nothing)."""
    try:
        mine, there = os.fstat(fd), os.stat(path)
    except OSError:
        return False
    return (mine.st_dev, mine.st_ino) == (there.st_dev, there.st_ino)


def refuse_existing(out: Path, overwrite: bool) -> None:
    """An output file that exists is replaced only with --overwrite (UsageError)."""
    if out.exists() and not overwrite:
        raise UsageError(f"--out {out}: exists (--overwrite replaces it)")


def check_free(target: Path | str, name: str = "run.lock", beside: bool = False) -> None:
    """Raise InUse if a live process holds the lock of ``target`` (creates nothing)."""
    probe = RunLock(target, "", name, beside)
    if not probe.path.is_file():
        return
    try:
        fd = os.open(probe.path, os.O_RDONLY)
    except OSError:
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        raise InUse(in_use_message(probe.target, probe.path, read_lock(probe.path))) from None
    finally:
        os.close(fd)
    holder = read_lock(probe.path)
    if holder and holder.get("pid") != os.getpid() and holder_alive(holder):
        raise InUse(in_use_message(probe.target, probe.path, holder))
