"""A supervisor from an event loop (`rr_actors._supervision.aio`): `async with`, the
awaited start, stop and wait for a restart, a consumer registrar made awaited."""

from __future__ import annotations

import asyncio
import threading
from typing import Any

import pytest

import rr_actors as rr
from tests.support.supervising import process, sigkill

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
