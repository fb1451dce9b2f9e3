"""Registrar handles whose blocking methods go through their awaitable twins.

The registrar tests' API dimension (`registrar_api`, tests/conftest.py): the same test
bodies, unchanged, run against the async surface. `awaited(handle)` gives the handle a
subclass whose `call` is `await handle.acall(...)` on an event loop of this process (one
loop thread per process, `on_loop`), `unload` is `await aunload(...)`, and so on; and
whose callbacks are coroutine functions: a `load`, `unload` or `on_status` given to
`register_server` runs as a coroutine on the registrar's loop, a client status callback
given to `call` or `set_status_callback` as a coroutine on this loop. Each of those
coroutines runs the test's plain callback on a thread of `POOL` (the callback may block
on a gate, or call a registrar: the loop never waits for it), in the coroutine's context
(a call made inside a load still records its dependency). So a rule's test checks the
rule through the async surface, coroutine callbacks included.

A handle pickles as its awaited self (its callbacks, that captured it, do the same in a
manager process).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextvars
import functools
import threading
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

import rr_actors as rr
from rr_actors.testing import RemoteRegistrar

__all__ = ["awaited", "on_loop"]

T = TypeVar("T")

POOL = concurrent.futures.ThreadPoolExecutor(max_workers=64, thread_name_prefix="awaited")
"""Where the coroutine callbacks run the tests' plain callbacks (they may block)."""

_LOOP: list[asyncio.AbstractEventLoop] = []
_LOOP_LOCK = threading.Lock()


def _loop() -> asyncio.AbstractEventLoop:
    with _LOOP_LOCK:
        if not _LOOP:
            loop = asyncio.new_event_loop()
            threading.Thread(target=loop.run_forever, name="awaited-loop", daemon=True).start()
            _LOOP.append(loop)
        return _LOOP[0]


def on_loop(coroutine: Coroutine[Any, Any, T]) -> T:
    """Run `coroutine` on this process's test loop; block the calling thread for it."""
    return asyncio.run_coroutine_threadsafe(coroutine, _loop()).result()


async def _in_pool(fn: Callable[..., T], *args: Any) -> T:
    """`fn(*args)` on a thread of `POOL`, in this coroutine's context."""
    context = contextvars.copy_context()
    return await asyncio.get_running_loop().run_in_executor(POOL, context.run, fn, *args)


def _coroutine(fn: Callable[..., Any] | None) -> Callable[..., Any] | None:
    """A coroutine function that runs plain `fn` on `POOL` (`None` stays `None`)."""
    if not callable(fn) or asyncio.iscoroutinefunction(fn):
        return fn  # (`None`; or not callable: the registrar says so)
    return functools.partial(_in_pool, fn)


class _Awaited:
    """The blocking methods, each through its awaitable twin (module docstring)."""

    def register_server(self, name: str, **kw: Any) -> None:
        for key in ("load", "unload", "on_status"):
            if key in kw:
                kw[key] = _coroutine(kw[key])
        on_loop(self.aregister_server(name, **kw))  # type: ignore[attr-defined]

    def unregister_server(self, *args: Any, **kw: Any) -> None:
        on_loop(self.aunregister_server(*args, **kw))  # type: ignore[attr-defined]

    def call(self, *args: Any, on_status: Any = None, **kw: Any) -> rr.Query:
        query: rr.Query = on_loop(self.acall(*args, on_status=_coroutine(on_status), **kw))  # type: ignore[attr-defined]
        return query

    def unload(self, *args: Any, **kw: Any) -> None:
        on_loop(self.aunload(*args, **kw))  # type: ignore[attr-defined]

    def send_status(self, *args: Any, **kw: Any) -> None:
        on_loop(self.asend_status(*args, **kw))  # type: ignore[attr-defined]

    def server_queries(self, *args: Any, **kw: Any) -> list[rr.Query]:
        result: list[rr.Query] = on_loop(self.aserver_queries(*args, **kw))  # type: ignore[attr-defined]
        return result

    def fetch_queries(self, *args: Any, **kw: Any) -> list[rr.Query]:
        result: list[rr.Query] = on_loop(self.afetch_queries(*args, **kw))  # type: ignore[attr-defined]
        return result

    def client_queries(self, *args: Any, **kw: Any) -> list[rr.Query]:
        result: list[rr.Query] = on_loop(self.aclient_queries(*args, **kw))  # type: ignore[attr-defined]
        return result

    def set_status_callback(self, query_id: str, callback: Any, **kw: Any) -> None:
        on_loop(self.aset_status_callback(query_id, _coroutine(callback), **kw))  # type: ignore[attr-defined]

    def update_response(self, *args: Any, **kw: Any) -> None:
        on_loop(self.aupdate_response(*args, **kw))  # type: ignore[attr-defined]

    def save_catalog(self, *args: Any, **kw: Any) -> None:
        on_loop(self.asave_catalog(*args, **kw))  # type: ignore[attr-defined]

    def stop(self, *args: Any, **kw: Any) -> None:
        on_loop(self.astop(*args, **kw))  # type: ignore[attr-defined]


class AwaitedResourceRegistrar(_Awaited, rr.ResourceRegistrar):
    """A `ResourceRegistrar` driven through its awaitable twins."""


class AwaitedRemoteRegistrar(_Awaited, RemoteRegistrar):
    """A `RemoteRegistrar` driven through its awaitable twins; pickles as one."""

    def __reduce__(self) -> tuple[Any, ...]:
        rebuild, args = super().__reduce__()[:2]
        return (_rebuilt_awaited, (rebuild, args))


def _rebuilt_awaited(rebuild: Callable[..., RemoteRegistrar], args: tuple[Any, ...]) -> Any:
    return awaited(rebuild(*args))


def awaited(handle: Any) -> Any:
    """`handle`, its blocking methods now through its awaitable twins (the same object)."""
    if isinstance(handle, RemoteRegistrar):
        handle.__class__ = AwaitedRemoteRegistrar
    else:
        handle.__class__ = AwaitedResourceRegistrar
    return handle
