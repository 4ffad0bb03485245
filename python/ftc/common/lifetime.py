"""Tying a child process's life to the thread that started it (Linux
``PR_SET_PDEATHSIG``), so a plant or a run does not outlive a parent that was
killed or terminated without running its clean-up."""

from __future__ import annotations

import ctypes
import os
import signal
from typing import Callable

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent(then: Callable[[], None] | None = None) -> Callable[[], None]:
    """A ``preexec_fn``: the child gets SIGKILL when the thread that started it
    ends (PR_SET_PDEATHSIG is per thread, not per process), or exits at once if
    that already happened; then runs ``then``."""
    parent = os.getpid()

    def preexec() -> None:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        if os.getppid() != parent:  # the parent died before prctl took effect
            os._exit(1)
        if then is not None:
            then()

    return preexec
