"""Process lifetimes: a child's tied to the thread that started it (Linux
``PR_SET_PDEATHSIG``), so a plant or a run does not outlive a parent that was
killed without running its clean-up; and stop signals turned into an
exception, so a tool that is told to stop does run its clean-up."""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import threading
from typing import Callable, Iterator

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent(then: Callable[[], None] | None = None) -> Callable[[], None]:
    """A ``preexec_fn``: the child gets SIGKILL when the thread that started it
    ends (PR_SET_PDEATHSIG is per thread, not per process), or exits at once if
    that already happened; then runs ``then``."""
    parent = os.getpid()
    # Looked up here, in the parent: a dlopen between fork and exec could wait
    # for ever on a loader lock another of the parent's threads held at the fork.
    prctl = ctypes.CDLL(None, use_errno=True).prctl

    def preexec() -> None:
        prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        if os.getppid() != parent:  # the parent died before prctl took effect
            os._exit(1)
        if then is not None:
            then()

    return preexec


def tie_to(parent: int) -> None:
    """A pool worker's ``initializer`` (``initargs=(os.getpid(),)``): the
    worker gets SIGKILL when the thread that started it ends, as
    :func:`die_with_parent` does for a child it starts, so a pool's workers do
    not go on computing for a parent killed by SIGTERM or SIGKILL; it exits at
    once if ``parent`` is already gone."""
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent:
        os._exit(1)


class Stopped(BaseException):
    """A stop signal (SIGINT, SIGTERM, SIGHUP) raised in the main thread, so every
    ``finally`` runs: the plant is shut down, an atomic write cut short removes
    its temporary file. A BaseException, as KeyboardInterrupt is, so no
    ``except Exception`` on the way swallows it."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


# SIGINT is here too, not left to Python's KeyboardInterrupt: a process started
# with SIGINT ignored (a background job of a non-interactive shell, as a CI
# runner may start the tests) keeps it ignored, and Python installs no handler,
# so a Ctrl-C or `kill -INT` would let the run go on to its end and exit 0.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def _stop(signum: int, frame: object) -> None:
    for s in STOP_SIGNALS:  # one stop: a second signal must not cut the clean-up short
        signal.signal(s, signal.SIG_IGN)
    raise Stopped(signum)


@contextlib.contextmanager
def stop_signals() -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP raise :class:`Stopped` in the block (main thread only;
    elsewhere a no-op); the previous handlers are restored after it."""
    handlers = {}
    if threading.current_thread() is threading.main_thread():
        handlers = {s: signal.signal(s, _stop) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)


def stopped_line(tool: str, e: BaseException, kept: str = "") -> tuple[str, int]:
    """The one line a tool prints when stopped by a signal (``e``: Stopped, or
    KeyboardInterrupt for SIGINT), and its exit code, 128 + the signal's
    number (130, 143, 129), as a shell reports it."""
    signum = e.signum if isinstance(e, Stopped) else signal.SIGINT
    return f"{tool}: stopped by {signal.Signals(signum).name}{kept}", 128 + signum
