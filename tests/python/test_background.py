"""ftc.control.run.background.OneJob: one job at a time on a worker thread,
taken between two steps, its error raised in the taker's thread."""

from __future__ import annotations

import threading

import pytest

from ftc.control.run.background import OneJob


def test_a_job_is_taken_once_done_or_by_waiting_and_only_one_runs():
    jobs, release = OneJob("test-job"), threading.Event()
    assert not jobs.running and jobs.take() is None and jobs.take(wait=True) is None
    jobs.submit(lambda: (release.wait(5), threading.current_thread().name)[1], interval=3)
    assert jobs.running
    assert jobs.take() is None  # not done: the loop acts on
    with pytest.raises(RuntimeError, match="already running"):
        jobs.submit(lambda: None)
    release.set()
    name, interval = jobs.take(wait=True)
    # it ran on the worker, not in the caller
    assert interval == 3 and name.startswith("test-job") and name != threading.current_thread().name
    assert not jobs.running and jobs.take(wait=True) is None
    jobs.close()
    jobs.submit(lambda: 7)  # a closed runner starts a new worker
    assert jobs.take(wait=True) == (7, None)
    jobs.close()


def test_a_jobs_error_is_raised_where_it_is_taken():
    jobs = OneJob("test-job")

    def fails():
        raise ValueError("the fit diverged")

    jobs.submit(fails, interval=1)
    with pytest.raises(ValueError, match="the fit diverged"):
        jobs.take(wait=True)
    assert not jobs.running  # taken, error and all
    jobs.close()
