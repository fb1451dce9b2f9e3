"""Tests of `rr_actors/_core/workers.py`: the bounded pool that runs user callbacks.

Its queue (issue 53): an urgent job (an unload) goes before the jobs queued before it,
and a queued job that is cancelled (a load whose callers all gave up) never runs.
"""

from __future__ import annotations

import threading

from rr_actors._core.workers import Workers


def held_pool() -> tuple[Workers, threading.Event, list[str], threading.Event]:
    """A pool of one worker, held by a job until the returned gate is set."""
    pool = Workers("test-workers", max_workers=1, idle_timeout=1.0)
    gate, started, ran = threading.Event(), threading.Event(), []

    def hold() -> None:
        started.set()
        assert gate.wait(10)

    pool.submit(hold)
    assert started.wait(10)
    return pool, gate, ran, threading.Event()


def test_an_urgent_job_runs_before_the_jobs_queued_before_it() -> None:
    pool, gate, ran, done = held_pool()
    pool.submit(lambda: ran.append("load 1"))
    pool.submit(lambda: ran.append("load 2"))
    pool.submit(lambda: ran.append("unload"), urgent=True)
    pool.submit(done.set)
    assert 4 == pool.queued

    gate.set()

    assert done.wait(10)
    assert ["unload", "load 1", "load 2"] == ran


def test_a_cancelled_queued_job_never_runs_and_a_running_one_is_not_cancelled() -> None:
    pool, gate, ran, done = held_pool()
    cancelled = pool.submit(lambda: ran.append("withdrawn"))
    pool.submit(lambda: ran.append("kept"))
    pool.submit(done.set)

    assert cancelled.cancel()
    assert not cancelled.cancel()  # (once)
    gate.set()

    assert done.wait(10)
    assert ["kept"] == ran
    running, release = threading.Event(), threading.Event()
    job = pool.submit(lambda: (running.set(), release.wait(10)))
    assert running.wait(10)
    assert not job.cancel()  # it runs on
    release.set()
