"""`SerialExecutor`: order, a producer that never waits, inline when idle, closing."""

from __future__ import annotations

import logging
import threading

import pytest

from rr_actors._core.serial import SerialExecutor, Task


@pytest.fixture
def executors() -> object:
    made: list[SerialExecutor] = []

    def make(name: str = "rr-test-serial", **kwargs: object) -> SerialExecutor:
        executor = SerialExecutor(name, **kwargs)  # type: ignore[arg-type]
        made.append(executor)
        return executor

    yield make
    for executor in made:
        executor.close(timeout=0)
        assert executor.join(5)


def hang(started: threading.Event, release: threading.Event) -> Task:
    def task() -> None:
        started.set()
        assert release.wait(10)

    return task


def test_tasks_run_one_at_a_time_in_the_order_submitted(executors) -> None:
    executor = executors()
    seen: list[int] = []
    running = []

    def task(i: int) -> Task:
        def run() -> None:
            running.append(i)
            assert len(running) == 1
            seen.append(i)
            running.pop()

        return run

    for i in range(500):
        assert executor.submit(task(i))
    assert executor.flush(timeout=5)
    assert list(range(500)) == seen


def test_tasks_run_on_the_executor_thread_named_as_given(executors) -> None:
    executor = executors("rr-test-named")
    names: list[str] = []
    executor.submit(lambda: names.append(threading.current_thread().name))
    executor.submit(lambda: names.append(threading.current_thread().name))
    assert executor.flush(timeout=5)
    assert ["rr-test-named", "rr-test-named"] == names
    assert executor.call(lambda: threading.current_thread().daemon)


def test_a_producer_never_waits_while_a_task_hangs(executors) -> None:
    executor = executors()
    started, release = threading.Event(), threading.Event()
    executor.submit(hang(started, release))
    assert started.wait(5)
    seen: list[int] = []
    for i in range(1000):  # (a submit that waited for the hanging task would never return)
        assert executor.submit(lambda i=i: seen.append(i))
    assert 1000 == executor.pending
    release.set()
    assert executor.flush(timeout=5)
    assert list(range(1000)) == seen


def test_a_task_that_raises_is_logged_and_the_next_one_runs(executors, caplog) -> None:
    executor = executors("rr-test-raises")
    seen: list[str] = []

    def fail() -> None:
        raise ValueError("boom")

    with caplog.at_level(logging.ERROR, logger="rr_actors"):
        executor.submit(fail)
        executor.submit(lambda: seen.append("after"))
        assert executor.flush(timeout=5)
    assert ["after"] == seen
    [record] = [r for r in caplog.records if r.exc_info is not None]
    assert "rr-test-raises" in record.getMessage()
    assert isinstance(record.exc_info[1], ValueError)


def test_inline_runs_on_the_submitting_thread_when_idle(executors) -> None:
    executor = executors()
    where: list[str] = []
    assert executor.submit(
        lambda: where.append("queued"),
        inline=lambda: where.append(threading.current_thread().name),  # type: ignore[func-returns-value]
    )
    assert [threading.current_thread().name] == where


def test_inline_is_not_used_while_a_task_runs_and_order_is_kept(executors) -> None:
    executor = executors("rr-test-busy")
    started, release = threading.Event(), threading.Event()
    executor.submit(hang(started, release))
    assert started.wait(5)
    seen: list[tuple[str, str]] = []
    executor.submit(
        lambda: seen.append(("queued", threading.current_thread().name)),
        inline=lambda: seen.append(("inline", "")),  # type: ignore[func-returns-value]
    )
    executor.submit(lambda: seen.append(("next", threading.current_thread().name)))
    assert [] == seen
    release.set()
    assert executor.flush(timeout=5)
    assert [("queued", "rr-test-busy"), ("next", "rr-test-busy")] == seen


def test_the_rest_of_an_inline_run_goes_before_tasks_submitted_meanwhile(executors) -> None:
    executor = executors("rr-test-rest")
    seen: list[str] = []
    others: list[threading.Thread] = []

    def inline() -> Task:
        # a submit from another thread now waits for the lock this step runs under
        other = threading.Thread(target=lambda: executor.submit(lambda: seen.append("meanwhile")))
        other.start()
        others.append(other)
        seen.append("inline")
        return lambda: seen.append(f"rest on {threading.current_thread().name}")

    executor.submit(lambda: None, inline=inline)
    others[0].join(5)
    assert executor.flush(timeout=5)
    assert ["inline", "rest on rr-test-rest", "meanwhile"] == seen


def test_what_inline_raises_reaches_its_caller_and_the_executor_goes_on(executors) -> None:
    executor = executors()

    def inline() -> Task | None:
        raise OSError("broken")

    with pytest.raises(OSError, match="broken"):
        executor.submit(lambda: None, inline=inline)
    assert 5 == executor.call(lambda: 5)


def test_close_lets_queued_tasks_run_within_its_bound(executors) -> None:
    executor = executors()
    seen: list[int] = []
    for i in range(100):
        executor.submit(lambda i=i: seen.append(i))
    assert executor.close(timeout=5)
    assert list(range(100)) == seen
    assert not executor.submit(lambda: seen.append(-1))
    assert executor.closed


def test_close_drops_what_did_not_run_within_its_bound(executors) -> None:
    dropped: list[Task] = []
    executor = executors(on_drop=dropped.append)
    started, release = threading.Event(), threading.Event()
    executor.submit(hang(started, release))
    assert started.wait(5)
    late = [lambda: None, lambda: None]
    for task in late:
        executor.submit(task)
    assert not executor.close(timeout=0.05)
    assert late == dropped
    assert not executor.flush(timeout=0)
    release.set()
    assert executor.join(5)  # the thread ends after the task it ran


def test_finish_runs_what_is_queued_then_ends_without_waiting(executors) -> None:
    ended = threading.Event()
    executor = executors(on_end=ended.set)
    started, release = threading.Event(), threading.Event()
    executor.submit(hang(started, release))
    assert started.wait(5)
    seen: list[str] = []
    executor.submit(lambda: seen.append("queued"))
    executor.finish()  # returns although a task hangs
    assert not executor.submit(lambda: seen.append("late"))
    release.set()
    assert ended.wait(5)
    assert ["queued"] == seen


def test_on_end_runs_once_on_the_executor_thread(executors) -> None:
    where: list[str] = []
    executor = executors(
        "rr-test-end", on_end=lambda: where.append(threading.current_thread().name)
    )
    executor.submit(lambda: None)
    assert executor.close(timeout=5)
    executor.close(timeout=5)
    assert ["rr-test-end"] == where


def test_an_executor_that_never_ran_a_task_ends_on_the_closing_thread(executors) -> None:
    where: list[str] = []
    executor = executors(on_end=lambda: where.append(threading.current_thread().name))
    assert executor.close(timeout=0)
    assert [threading.current_thread().name] == where


def test_a_transient_executors_thread_ends_once_idle_and_the_next_task_starts_another(
    executors,
) -> None:
    ended: list[str] = []
    executor = executors(
        "rr-test-transient",
        transient=True,
        on_end=lambda: ended.append(threading.current_thread().name),
    )
    threads: list[threading.Thread] = []
    seen: list[int] = []
    started, release = threading.Event(), threading.Event()
    for burst in range(3):
        started.clear()
        release.clear()
        executor.submit(hang(started, release))
        for i in range(50):  # (queued behind the hung task: run in order on its thread)
            executor.submit(lambda i=i: seen.append(i))
        assert started.wait(10)
        threads.append(_executor_thread(executor))
        release.set()
        threads[-1].join(10)
        assert not threads[-1].is_alive(), f"burst {burst}: the thread outlived its queue"
        assert list(range(50)) * (burst + 1) == seen
    assert 3 == len({id(t) for t in threads})
    assert executor.close(timeout=5)
    assert [threading.current_thread().name] == ended  # (no thread left: the closing one)


def _executor_thread(executor: SerialExecutor) -> threading.Thread:
    (thread,) = [t for t in threading.enumerate() if t.name == executor.name]
    return thread


def test_on_idle_runs_when_a_burst_was_handled(executors) -> None:
    batches: list[list[int]] = []
    batch: list[int] = []

    def ship() -> None:
        batches.append(batch[:])
        batch.clear()

    executor = executors(on_idle=ship)
    started, release = threading.Event(), threading.Event()
    executor.submit(hang(started, release))
    assert started.wait(5)
    for i in range(10):
        executor.submit(lambda i=i: batch.append(i))
    release.set()
    assert executor.flush(timeout=5)
    assert executor.call(lambda: batches[-1] if batches else None) == list(range(10))


def test_flush_and_call_on_its_own_thread_raise(executors) -> None:
    executor = executors()
    errors: list[BaseException] = []

    def inside() -> None:
        for wait in (lambda: executor.flush(timeout=1), lambda: executor.call(lambda: 1)):
            try:
                wait()
            except RuntimeError as exc:
                errors.append(exc)

    executor.submit(inside)
    assert executor.flush(timeout=5)
    assert 2 == len(errors)


def test_call_hands_over_the_result_or_the_exception(executors) -> None:
    executor = executors()
    assert "ok" == executor.call(lambda: "ok")

    def fail() -> None:
        raise KeyError("k")

    with pytest.raises(KeyError):
        executor.call(fail)
    executor.close(timeout=5)
    with pytest.raises(RuntimeError, match="closed"):
        executor.call(lambda: 1)


def test_every_runs_its_task_again_and_again_between_tasks(executors) -> None:
    ticks: list[str] = []
    three = threading.Event()

    def tick() -> None:
        ticks.append(threading.current_thread().name)
        if len(ticks) >= 3:
            three.set()

    executors("rr-test-tick", every=(0.01, tick))
    assert three.wait(10)
    assert {"rr-test-tick"} == set(ticks)
