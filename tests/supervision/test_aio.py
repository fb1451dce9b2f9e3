"""A supervisor from an event loop (`rr_actors._supervision.aio`): `async with`, the
awaited start, stop and wait for a restart, a consumer registrar made awaited, and a
call that waits out a provider's restart (`acall_with_retry`; its rules run against both
APIs in test_supervisor.py, through the `call_with_retry` fixture)."""

from __future__ import annotations

import asyncio
import threading
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._supervision import aio
from tests.support.heard import events_of
from tests.support.supervising import ManualTimer, crash, process, sigkill

pytestmark = pytest.mark.usefixtures("by_value")


async def _ticks_while(work: Any) -> tuple[Any, int]:
    """Await `work` while a ticker task counts its turns: the loop ran meanwhile."""
    ticks = 0
    stop = asyncio.Event()

    async def ticker() -> None:
        nonlocal ticks
        while not stop.is_set():
            ticks += 1
            await asyncio.sleep(0.001)

    ticking = asyncio.ensure_future(ticker())
    try:
        return await work, ticks
    finally:
        stop.set()
        await ticking


def test_a_tree_started_waited_on_and_stopped_from_a_loop_never_blocks_it(uid: str) -> None:
    name = f"erm-{uid}"
    sup = rr.Supervisor([process(name)], strategy="one_for_one", max_restarts=3, period=5.0)

    async def main() -> tuple[int, int, Any, rr.ChildInfo]:
        async with sup:
            app = await sup.aregistrar(f"app-{uid}")
            query = await app.acall(name, "echo", "r")
            await app.aunload(query.id)
            sigkill(sup, name)
            info, waiting_ticks = await _ticks_while(sup.await_restarted(name, timeout=20))
        _, stopping_ticks = await _ticks_while(sup.astop())  # (a second stop: a no-op)
        return waiting_ticks, stopping_ticks, query.response, info

    waiting_ticks, _, response, info = asyncio.run(main())

    assert "r" == response
    assert ("running", 1) == (info.state, info.restarts)
    assert waiting_ticks > 0  # the loop ran while the restart was awaited
    assert "stopped" == sup.child(name).state


def test_an_awaited_restart_wait_times_out_with_call_timeout_error(uid: str) -> None:
    name = f"erm-{uid}"
    sup = rr.Supervisor([process(name)])

    async def main() -> None:
        async with sup:
            with pytest.raises(rr.CallTimeoutError, match="not restarted within"):
                await sup.await_restarted(name, timeout=0.2)
            with pytest.raises(rr.UnknownServerError):
                await sup.await_restarted("nobody", timeout=1)

    asyncio.run(main())


def test_a_cancelled_astart_stops_what_it_started(uid: str) -> None:
    name = f"erm-{uid}"
    sup = rr.Supervisor([process(name)])
    seen: list[str] = []
    exited = threading.Event()

    def on_event(event: rr.events.Event) -> None:
        seen.append(type(event).__name__)
        if isinstance(event, rr.events.ChildExited):
            exited.set()

    async def main() -> None:
        task = asyncio.ensure_future(sup.astart())
        await asyncio.sleep(0)  # (it awaits its start, on a thread of its own, now)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    with sup.subscribe(on_event):
        asyncio.run(main())
        assert exited.wait(20)  # its start went on, then it was stopped

    assert ["ChildStarted", "ChildExited"] == [
        kind for kind in seen if kind in ("ChildStarted", "ChildExited")
    ]


def test_an_astart_cancelled_as_its_start_ends_stops_what_it_started(
    uid: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # (forced: the cancel lands once the start ended, before the awaited start returns:
    # the start's thread saw no cancel, so the cancelled await must stop the tree)
    name = f"erm-{uid}"
    sup = rr.Supervisor([process(name)])
    exited = threading.Event()
    run_steps_async = aio.run_steps_async

    async def ended_then_cancelled(steps: Any) -> Any:
        await run_steps_async(steps)
        raise asyncio.CancelledError

    def on_event(event: rr.events.Event) -> None:
        if isinstance(event, rr.events.ChildExited):
            exited.set()

    monkeypatch.setattr(aio, "run_steps_async", ended_then_cancelled)
    try:
        with sup.subscribe(on_event):
            with pytest.raises(asyncio.CancelledError):
                asyncio.run(sup.astart())
            assert exited.wait(20)  # stopped on a thread of its own
    finally:  # (its stop's thread ends first: a failure leaves no tree running)
        for thread in threading.enumerate():
            if thread.name == f"rr-stop-{sup.name}":
                thread.join(20)
        sup.stop()


def _counting_restart_waits(
    sup: rr.Supervisor, monkeypatch: pytest.MonkeyPatch, count: int
) -> asyncio.Event:
    """An event of the running loop, set once `count` waits for a restart have started
    (each started on the loop's thread, by an awaited retry)."""
    started = asyncio.Event()
    restart_wait = sup._restart_wait
    waits = iter(range(1, count + 1))

    def counted(*args: Any) -> Any:
        if next(waits, None) == count:
            started.set()
        return restart_wait(*args)

    monkeypatch.setattr(sup, "_restart_wait", counted)
    return started


def _writers_ended(registrar: str, timeout: float) -> bool:
    """Join this process's connection writer threads to `registrar` (one whose connect
    failed ends just after it failed the calls waiting on it); whether all ended."""
    writers = [t for t in threading.enumerate() if t.name == f"rr-write-{registrar}"]
    for writer in writers:
        writer.join(timeout)
    return not any(writer.is_alive() for writer in writers)


def test_awaited_retries_wait_out_a_killed_providers_restart_with_no_thread_each(
    uid: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The web service: requests over a manager process that was SIGKILLed, its
    # restart held by a backoff until the test fires it. Each call waits for the restart
    # as a task; the loop goes on and no thread is held per call.
    name = f"cams-{uid}"
    timer = ManualTimer()
    sup = rr.Supervisor([process(name)], backoff=rr.Backoff(initial=1.0), timer=timer)
    calls = 50

    async def main() -> tuple[int, int, int, list[rr.Query], rr.ChildInfo]:
        all_waiting = _counting_restart_waits(sup, monkeypatch, calls)
        async with sup:
            app = await sup.aregistrar(f"app-{uid}")
            sigkill(sup, name)
            assert await asyncio.to_thread(timer.wait_scheduled, 1)  # its restart is held
            before = threading.active_count()
            tasks = [
                asyncio.ensure_future(sup.acall_with_retry(app, name, "echo", n, timeout=60))
                for n in range(calls)
            ]
            await asyncio.wait_for(all_waiting.wait(), 30)
            assert await asyncio.to_thread(_writers_ended, name, 10)  # (the dead one's)
            during = threading.active_count()
            timer.fire()  # the restart: a manager process started, served, answering
            queries, ticks = await _ticks_while(asyncio.gather(*tasks))
            await asyncio.gather(*(app.aunload(query.id) for query in queries))
            return before, during, ticks, queries, sup.child(name)

    before, during, ticks, queries, info = asyncio.run(main())

    assert during - before <= 2  # at most the client actor of that server, at first use
    assert ticks > 0  # the loop ran while the calls waited for the restart
    assert list(range(calls)) == [query.response for query in queries]
    assert calls == len({query.id for query in queries})
    assert ("running", 1) == (info.state, info.restarts)


def test_an_awaited_retry_cancelled_while_its_provider_restarts_abandons_its_id_withdrawn(
    uid: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Withdrawn as a timed-out one is: the id is kept for the provider's next start, which
    releases it there if its restored catalog holds it; and its `CallWithdrawn`
    ("interrupted") is published, as a call cancelled in flight has: it had none (the
    outcome and kept rules read it)."""
    name = f"p-{uid}"
    timer = ManualTimer()
    sup = rr.Supervisor([rr.ManagerSpec(name)], backoff=rr.Backoff(initial=1.0), timer=timer)
    withdrawn, seen, on_event = events_of(rr.events.CallWithdrawn)

    async def main(app: rr.ResourceRegistrar) -> None:
        waiting = _counting_restart_waits(sup, monkeypatch, 1)
        task = asyncio.ensure_future(
            sup.acall_with_retry(app, name, "res", "camera", timeout=30, query_id="q-1")
        )
        await asyncio.wait_for(waiting.wait(), 10)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    with sup:
        app = sup.registrar(f"app-{uid}")
        with app.subscribe(on_event):
            crash(sup, name)
            assert timer.wait_scheduled(1)
            asyncio.run(main(app))

            assert seen.wait(10.0)
            assert {name: [("q-1", app.name)]} == sup._tree.abandon_later
    assert [("q-1", name, "interrupted")] == [
        (e.query_id, e.serving_rr, e.reason) for e in withdrawn
    ]
