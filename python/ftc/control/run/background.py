"""One learning job at a time on a worker thread, for the agents that learn
off a real-time plant's control loop (:class:`ftc.control.run.deferred.DeferredAgent`
and the adaptive policy's fine-tune): ``submit`` a job and the interval it
belongs to; ``take`` its result between two steps once it is done (or wait
for it), its error raised in the caller's thread; ``close`` stops the worker.
"""

from __future__ import annotations

import concurrent.futures
from typing import Any, Callable


class OneJob:
    """At most one job running on one worker thread named ``name``."""

    def __init__(self, name: str) -> None:
        self._name = name
        self._worker: concurrent.futures.ThreadPoolExecutor | None = None
        self._job: tuple[concurrent.futures.Future, int | None] | None = None

    @property
    def running(self) -> bool:
        """A job was submitted and not taken yet."""
        return self._job is not None

    def submit(self, job: Callable[[], Any], interval: int | None = None) -> None:
        if self._job is not None:
            raise RuntimeError(f"{self._name}: a job is already running")
        if self._worker is None:
            self._worker = concurrent.futures.ThreadPoolExecutor(1, self._name)
        self._job = (self._worker.submit(job), interval)

    def take(self, wait: bool = False) -> tuple[Any, int | None] | None:
        """(the job's result, its interval) if it is done, or after waiting for
        it with ``wait``; None if none runs or it is not done. A job's error is
        raised here."""
        if self._job is None or not (wait or self._job[0].done()):
            return None
        (future, interval), self._job = self._job, None
        return future.result(), interval

    def close(self) -> None:
        """Stop the worker (a job queued and not started is cancelled)."""
        if self._worker is not None:
            self._worker.shutdown(wait=True, cancel_futures=True)
            self._worker = None
