"""Tests of `rr_actors/_core/workers.py`: the bounded pool that runs user callbacks.

Its queue (issue 53): an urgent job (an unload) goes before the jobs queued before it,
a queued job that is cancelled (a load whose callers all gave up) never runs, and the
lanes (consumers) take turns, held jobs (coroutine loads) too.
"""

from __future__ import annotations

import queue
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


def test_the_lanes_take_turns_and_each_is_first_come_first_served() -> None:
    """A lane that queued three jobs first does not hold back another's one: the
    workers take one job of each lane with jobs in turn (round robin), in order within
    a lane (first come, first served alone put "b 1" after "a 3")."""
    pool, gate, ran, done = held_pool()
    for n in (1, 2, 3):
        pool.submit(lambda n=n: ran.append(f"a {n}"), lane="a")
    pool.submit(lambda: ran.append("b 1"), lane="b")
    pool.submit(lambda: ran.append("a 4"), lane="a")
    pool.submit(lambda: ran.append("c 1"), lane="c")
    pool.submit(done.set, lane="a")  # (the last of lane a: it runs last)
    gate.set()

    assert done.wait(10)
    assert ["a 1", "b 1", "c 1", "a 2", "a 3", "a 4"] == ran


def test_a_held_job_keeps_its_place_until_released_and_held_jobs_take_turns_too() -> None:
    """A held job (a coroutine load: its task starts it on a loop and returns) keeps its
    worker's place until `release()` (the coroutine ended): the next job starts only
    then; held jobs wait in lanes that take turns, as the others do."""
    pool = Workers("test-workers", max_workers=1, idle_timeout=1.0)
    log: list[str] = []
    seen: queue.SimpleQueue[str] = queue.SimpleQueue()

    def job(name: str, lane: str = "", held: bool = True) -> None:
        pool.submit(lambda: (log.append(name), seen.put(name)), lane=lane, held=held)

    job("held")
    for n in (1, 2, 3):
        job(f"a {n}", "a")
    job("b 1", "b")
    job("c 1", "c", held=False)  # (a plain job: its place is free once it returned)
    for step, names in enumerate([["held"], ["a 1"], ["b 1"], ["c 1", "a 2"], ["a 3"]]):
        if step:
            log.append("release")
            pool.release()
        assert names == [seen.get(timeout=10) for _ in names]
    pool.release()

    assert [
        *("held", "release", "a 1", "release", "b 1"),
        *("release", "c 1", "a 2", "release", "a 3"),
    ] == log


def test_waiting_counts_a_keys_jobs_still_queued_not_those_begun_cancelled_or_never_queued() -> (
    None
):
    """A server's loads still queued ahead (issue 53's refusal as a load arrives): a job
    given a worker at once never counts, a cancelled (withdrawn) one stops counting at
    once, not when a worker skips it, and one counts until a worker begins it."""
    pool = Workers("test-workers", max_workers=1, idle_timeout=1.0)
    gate, started, ran = threading.Event(), threading.Event(), []

    def hold() -> None:
        started.set()
        assert gate.wait(10)

    pool.submit(hold, key="k")  # (a new worker takes it: never queued)
    assert started.wait(10)
    assert 0 == pool.waiting("k")
    jobs = [pool.submit(lambda n=n: ran.append(n), lane="c", key="k") for n in range(3)]
    pool.submit(lambda: ran.append("other"), lane="c", key="other")
    assert (3, 1, 0) == (pool.waiting("k"), pool.waiting("other"), pool.waiting("x"))
    assert jobs[1].cancel()
    assert (2, 4) == (pool.waiting("k"), pool.queued)  # (skipped later, counted no more)
    done = threading.Event()
    pool.submit(done.set)
    gate.set()
    assert done.wait(10)
    assert [0, 2, "other"] == ran
    assert (0, 0) == (pool.waiting("k"), pool.waiting("other"))


def test_waiting_read_without_the_lock_never_sees_a_key_emptied_while_a_job_leaves() -> None:
    """Review: `waiting` is read on a server actor's thread without the pool's lock while
    workers begin jobs; as one left the queue the key's count was popped then put back,
    and a read between the two saw 0 with jobs still queued. Each read sees the old count
    or the new one (forced: the read happens inside the update, where a thread could)."""
    pool = Workers("test-workers", max_workers=1, idle_timeout=1.0)
    gate, started, seen = threading.Event(), threading.Event(), []

    class Watched(dict):  # type: ignore[type-arg]
        def pop(self, *args: object) -> object:
            value = super().pop(*args)
            seen.append(pool.waiting("k"))  # (as a reader between pop and put back)
            return value

        def __setitem__(self, key: object, value: object) -> None:
            super().__setitem__(key, value)
            seen.append(pool.waiting("k"))

        def __delitem__(self, key: object) -> None:
            super().__delitem__(key)
            seen.append(pool.waiting("k"))

    def hold() -> None:
        started.set()
        assert gate.wait(10)

    pool.submit(hold)
    assert started.wait(10)
    pool._waiting = Watched()
    jobs = [pool.submit(lambda: None, lane="c", key="k") for _ in range(3)]
    seen.clear()
    assert jobs[0].cancel()
    assert [2] == seen  # (before: [0, 2], a key emptied between its pop and its put back)
    gate.set()
