"""asyncio at the edge of the actors (`rr_actors._core.loops`): awaiting a one-shot
future settled by another thread, steps driven on a loop, coroutines run on a loop."""

from __future__ import annotations

import asyncio
import threading
from typing import Any

import pytest

from rr_actors._core.actor import OneShotFuture
from rr_actors._core.loops import (
    OnLoop,
    is_coroutine_function,
    on_process_loop,
    process_loop,
    run_steps_async,
    settled,
)
from rr_actors._core.replies import Steps


def test_a_future_settled_by_another_thread_wakes_the_awaiting_task_no_thread_waits() -> None:
    future: OneShotFuture[Any] = OneShotFuture()

    async def main() -> tuple[bool, int]:
        before = threading.active_count()
        waiting = asyncio.ensure_future(settled(future, 5.0))
        await asyncio.sleep(0)  # (it awaits now)
        during = threading.active_count()
        threading.Thread(target=future.set, args=(7,)).start()
        return await waiting, during - before

    done, threads_added = asyncio.run(main())

    assert (True, 0) == (done, threads_added)


def test_an_awaited_future_not_settled_in_time_reports_false() -> None:
    assert asyncio.run(settled(OneShotFuture(), 0.01)) is False


def _one_wait(future: OneShotFuture[Any], seen: list[str]) -> Steps[str]:
    try:
        settled_in_time = yield future, None
    except BaseException as exc:
        seen.append(type(exc).__name__)
        raise
    return f"settled: {settled_in_time}"


def test_steps_driven_on_a_loop_return_their_result() -> None:
    future: OneShotFuture[Any] = OneShotFuture()
    future.set(None)

    assert "settled: True" == asyncio.run(run_steps_async(_one_wait(future, [])))


def test_a_cancelled_task_throws_the_cancellation_into_its_steps_at_the_wait() -> None:
    seen: list[str] = []

    async def main() -> None:
        task = asyncio.ensure_future(run_steps_async(_one_wait(OneShotFuture(), seen)))
        await asyncio.sleep(0.01)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(main())

    assert ["CancelledError"] == seen


def test_coroutine_functions_are_told_apart_from_plain_ones() -> None:
    async def coroutine(_x: Any) -> None:
        return None

    class Awaitable:
        async def __call__(self) -> None:
            return None

    assert [True, True, False] == [
        is_coroutine_function(coroutine),
        is_coroutine_function(Awaitable()),
        is_coroutine_function(lambda _x: None),
    ]


def test_calls_of_one_key_run_in_order_one_at_a_time_other_keys_beside_them() -> None:
    log: list[str] = []
    gate = asyncio.Event()

    async def callback(name: str, wait: bool) -> None:
        log.append(f"start {name}")
        if wait:
            await gate.wait()
        log.append(f"end {name}")

    async def main() -> None:
        on_loop = OnLoop.bind(callback)
        ended = asyncio.Event()
        on_loop.submit("a1", True, key="a")
        on_loop.submit("a2", False, key="a", then=lambda _e: ended.set())
        on_loop.submit("b1", False, key="b", then=lambda _e: gate.set())
        await asyncio.wait_for(ended.wait(), 5)  # (a2 waits for a1, b1 runs beside it)

    asyncio.run(main())

    assert ["start a1", "start b1", "end b1", "end a1", "start a2", "end a2"] == log


def test_a_slow_call_is_not_overtaken_by_the_next_of_its_key() -> None:
    """Issue 51 finding 6: past 50 ms, the next call of a key ran beside the one before
    it (a status callback's id heard its statuses out of order). The slow call's work:
    a 0.2 s wait, past that bound (the order asserted holds whatever it takes)."""
    log: list[str] = []

    async def callback(name: str) -> None:
        log.append(f"start {name}")
        if name == "first":
            await asyncio.sleep(0.2)
        log.append(f"end {name}")

    async def main() -> None:
        ended = asyncio.Event()
        on_loop = OnLoop.bind(callback)
        on_loop.submit("first", key="k")
        on_loop.submit("second", key="k", then=lambda _e: ended.set())
        await asyncio.wait_for(ended.wait(), 5)

    asyncio.run(main())

    assert ["start first", "end first", "start second", "end second"] == log


def test_a_call_that_awaits_a_registrar_lets_the_next_of_its_key_start() -> None:
    """A status callback may await a `send_status` that reaches its own id: its next
    call starts beside it (no deadlock), as soon as it awaits (steps on the loop)."""
    log: list[str] = []
    reached = OneShotFuture[Any]()

    async def callback(name: str) -> None:
        log.append(f"start {name}")
        if name == "first":
            log.append(await run_steps_async(_one_wait(reached, [])))
        else:
            reached.set(None)

    async def main() -> None:
        ended = asyncio.Event()
        on_loop = OnLoop.bind(callback)
        on_loop.submit("first", key="k", then=lambda _e: ended.set())
        on_loop.submit("second", key="k")
        await asyncio.wait_for(ended.wait(), 5)

    asyncio.run(main())

    assert ["start first", "start second", "settled: True"] == log


def test_a_coroutine_callback_bound_outside_a_loop_runs_on_the_process_loop() -> None:
    ran = threading.Event()
    where: list[bool] = []

    async def callback() -> None:
        where.append(on_process_loop())
        ran.set()

    OnLoop.bind(callback).submit()

    assert ran.wait(5)
    assert [True] == where
    assert process_loop() is process_loop()


def test_a_call_submitted_to_a_closed_loop_is_told_so_at_once() -> None:
    loop = asyncio.new_event_loop()
    loop.close()
    errors: list[BaseException | None] = []

    async def callback() -> None:
        return None

    OnLoop(callback, loop).submit(then=errors.append)

    assert [RuntimeError] == [type(e) for e in errors]


def test_what_a_coroutine_callback_raises_is_logged_and_told_to_then(
    caplog: pytest.LogCaptureFixture,
) -> None:
    errors: list[BaseException | None] = []

    async def callback() -> None:
        raise ValueError("nope")

    async def main() -> None:
        ended = asyncio.Event()

        def then(error: BaseException | None) -> None:
            errors.append(error)
            ended.set()

        OnLoop.bind(callback).submit(then=then)
        await asyncio.wait_for(ended.wait(), 5)

    asyncio.run(main())

    assert [ValueError] == [type(e) for e in errors]
    assert "coroutine callback" in caplog.text
