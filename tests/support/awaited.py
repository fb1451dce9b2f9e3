"""Registrar handles whose blocking methods go through their awaitable twins.

The registrar tests' API dimension (`registrar_api`, tests/conftest.py): the same test
bodies, unchanged, run against the async surface. `awaited(handle)` gives the handle a
subclass whose `call` awaits `acall(...)` on an event loop and blocks the test's thread
for it, `unload` awaits `aunload(...)`, and so on; and whose callbacks are coroutine
functions: a `load`, `unload` or `on_status` given to `register_server` runs as a
coroutine on the registrar's loop, a client status callback given to `call` or
`set_status_callback` as a coroutine on the loop the call was awaited from. Each of
those coroutines runs the test's plain callback on a thread of `POOL` (the callback may
block on a gate, or call a registrar: the loop never waits for it), in the coroutine's
context (a call made inside a load still records its dependency). So a rule's test
checks the rule through the async surface, coroutine callbacks included.

Where the twin is awaited is where an application awaits it, in the registrar's own
process, so what is awaited is the registrar's `Here` driven on a loop:

```
 "thread-async":  handle.call(...) ──► on_loop(handle.acall(...))   this process's loop
 "process-async": handle.call(...) ──► handle.run(fn) ──► in the registrar's manager
     process: on_loop(registrar.acall(...)), on that process's loop; the registrar a
     ResourceRegistrar there, awaiting its providers in other manager processes (the
     path of an application's consumer registrar), their answers waking that loop
```

The "process-async" handle reaches the registrar's process over the carrier
(`RemoteRegistrar.run`, carrying the caller's load context, as `There` does), and is
stopped the same way (`astop` there, then its process ends). One loop thread per
process (`on_loop`). A handle pickles as its awaited self (its callbacks, that captured
it, do the same in a manager process).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import contextvars
import functools
import threading
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

import rr_actors as rr
from rr_actors._process.remote import FORWARD_MARGIN
from rr_actors._registrar.messages import LOADING, LoadContext
from rr_actors.testing import RemoteRegistrar

__all__ = ["LOOP_THREAD", "awaited", "on_loop"]

T = TypeVar("T")

POOL = concurrent.futures.ThreadPoolExecutor(max_workers=64, thread_name_prefix="awaited")
"""Where the coroutine callbacks run the tests' plain callbacks (they may block)."""

LOOP_THREAD = "awaited-loop"
"""The name of the thread that runs a process's test loop (`on_loop`)."""

_LOOP: list[asyncio.AbstractEventLoop] = []
_LOOP_LOCK = threading.Lock()


def _loop() -> asyncio.AbstractEventLoop:
    with _LOOP_LOCK:
        if not _LOOP:
            loop = asyncio.new_event_loop()
            threading.Thread(target=loop.run_forever, name=LOOP_THREAD, daemon=True).start()
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

    def _await(self, twin: str, *args: Any, **kw: Any) -> Any:
        """Await `registrar.<twin>(*args, **kw)` where the registrar is; block for it."""
        raise NotImplementedError

    def register_server(self, name: str, **kw: Any) -> None:
        for key in ("load", "unload", "on_status"):
            if key in kw:
                kw[key] = _coroutine(kw[key])
        self._await("aregister_server", name, **kw)

    def unregister_server(self, *args: Any, **kw: Any) -> None:
        self._await("aunregister_server", *args, **kw)

    def call(self, *args: Any, on_status: Any = None, **kw: Any) -> rr.Query:
        query: rr.Query = self._await("acall", *args, on_status=_coroutine(on_status), **kw)
        return query

    def unload(self, *args: Any, **kw: Any) -> None:
        self._await("aunload", *args, **kw)

    def send_status(self, *args: Any, **kw: Any) -> rr.StatusDelivery:
        delivery: rr.StatusDelivery = self._await("asend_status", *args, **kw)
        return delivery

    def server_queries(self, *args: Any, **kw: Any) -> list[rr.Query]:
        result: list[rr.Query] = self._await("aserver_queries", *args, **kw)
        return result

    def fetch_queries(self, *args: Any, **kw: Any) -> list[rr.Query]:
        result: list[rr.Query] = self._await("afetch_queries", *args, **kw)
        return result

    def client_queries(self, *args: Any, **kw: Any) -> list[rr.Query]:
        result: list[rr.Query] = self._await("aclient_queries", *args, **kw)
        return result

    def set_status_callback(self, query_id: str, callback: Any, **kw: Any) -> None:
        self._await("aset_status_callback", query_id, _coroutine(callback), **kw)

    def update_response(self, *args: Any, **kw: Any) -> None:
        self._await("aupdate_response", *args, **kw)

    def save_catalog(self, *args: Any, **kw: Any) -> None:
        self._await("asave_catalog", *args, **kw)

    def settle_in_doubt(self, *args: Any, **kw: Any) -> None:
        self._await("asettle_in_doubt", *args, **kw)

    def stop(self, *args: Any, **kw: Any) -> None:
        self._await("astop", *args, **kw)


class AwaitedResourceRegistrar(_Awaited, rr.ResourceRegistrar):
    """A `ResourceRegistrar` driven through its awaitable twins, on this process's loop."""

    def _await(self, twin: str, *args: Any, **kw: Any) -> Any:
        return on_loop(getattr(self, twin)(*args, **kw))


class AwaitedRemoteRegistrar(_Awaited, RemoteRegistrar):
    """A `RemoteRegistrar` whose methods await the registrar's twins in its own process,
    on that process's loop (module docstring); pickles as one."""

    def _await(self, twin: str, *args: Any, **kw: Any) -> Any:
        there = functools.partial(_awaited_there, twin, args, kw, LOADING.get())
        return self.run(there, timeout=_limit(kw.get("timeout"), self.config))

    def stop(self, *args: Any, **kw: Any) -> None:
        """`astop` awaited in the registrar's process; then the owner's stop of that
        process (which ends by itself once its registrar stopped): a no-op if it has."""
        with contextlib.suppress(rr.RegistrarStoppedError, rr.RegistrarUnavailableError):
            super().stop(*args, **kw)  # (stopped already; or it ended before it answered)
        RemoteRegistrar.stop(self, *args, **kw)

    def __reduce__(self) -> tuple[Any, ...]:
        rebuild, args = super().__reduce__()[:2]
        return (_rebuilt_awaited, (rebuild, args))


def _limit(timeout: object, config: rr.RegistrarConfig) -> float:
    """How long to wait for a twin awaited in another process: its own `timeout` (the
    registrar's `call_timeout` without a valid one), and `FORWARD_MARGIN`."""
    limit = config.call_timeout
    if isinstance(timeout, int | float) and not isinstance(timeout, bool) and timeout > 0:
        limit = float(timeout)
    return limit + FORWARD_MARGIN


def _awaited_there(
    twin: str,
    args: tuple[Any, ...],
    kw: dict[str, Any],
    context: LoadContext | None,
    registrar: rr.ResourceRegistrar,
) -> Any:
    """In the registrar's process (`RemoteRegistrar.run`): await `registrar.<twin>(...)`
    on this process's test loop, in the load context of the caller (a call made inside
    a load elsewhere carries its chain, as `There` carries it)."""
    scope = contextvars.copy_context()
    if context is not None:
        scope.run(LOADING.set, context)
    return scope.run(lambda: on_loop(getattr(registrar, twin)(*args, **kw)))


def _rebuilt_awaited(rebuild: Callable[..., RemoteRegistrar], args: tuple[Any, ...]) -> Any:
    return awaited(rebuild(*args))


def awaited(handle: Any) -> Any:
    """`handle`, its blocking methods now through its awaitable twins (the same object)."""
    if isinstance(handle, RemoteRegistrar):
        handle.__class__ = AwaitedRemoteRegistrar
    else:
        handle.__class__ = AwaitedResourceRegistrar
    return handle
