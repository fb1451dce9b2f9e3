"""The registrar handle's awaitable surface, written once for every handle.

Each blocking method of a handle runs its operation's *steps* (`_core/replies.py`: a
generator that yields `(future, deadline)` for each wait) on the calling thread; its
async twin here runs the very same steps on the running event loop, where each wait is
an await that the future's done callback wakes (`_core/loops.py`). One protocol, two
drivers: same arguments, results, errors and timeouts, and no thread per waiting call.

```
 await reg.acall(...) ──► self._call_steps(...) ──► run_steps_async: yield attempt, deadline
                                                       └─► await: the answering thread's
                                                          call_soon_threadsafe wakes it
 reg.call(...)        ──► self._call_steps(...) ──► run_steps: the thread blocks on it
 task cancelled ──► CancelledError thrown in at the yield: the call is withdrawn as a
                    timeout withdraws it (its id given back, nothing held), then raised
```

A handle provides the steps (`_<operation>_steps`), this mixin the public awaitables and
`watch`. The names follow the prefix Django gave its async ORM (`aget`, `asave`) and the
language its own (`anext`, `aclose`): `acall` is `call`, awaited.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

from rr_actors._core.loops import run_steps_async
from rr_actors._core.replies import Steps
from rr_actors._registrar.protocol import LoadCallback, UnloadCallback
from rr_actors._types import Query, Status, StatusCallback, StatusUpdate
from rr_actors.errors import ConfigError

__all__ = ["AsyncSurface", "StatusWatch"]


class AsyncSurface:
    """The awaitable twins of a registrar handle's blocking methods (module docstring).

    Every method may be awaited from any running event loop, any number at once; each
    has the semantics, errors and `timeout` of its blocking twin (see
    [`ResourceRegistrar`][rr_actors.ResourceRegistrar]), and holds no thread while it
    waits. Cancelling the awaiting task withdraws what it waits for as its timeout
    would: a cancelled `acall` gives its query id back (if its load completes later,
    the id is released; nothing is left held) and raises `asyncio.CancelledError`; a
    cancelled `aunload`, `asend_status`, ... stops waiting for what was already sent,
    exactly as one that timed out.
    """

    # -- the steps a handle provides (each is its blocking method's body) --------------

    def _register_server_steps(
        self,
        name: str,
        load: LoadCallback,
        unload: UnloadCallback,
        on_status: StatusCallback | None,
        timeout: float | None,
        label: Callable[[Any], str] | None,
    ) -> Steps[None]:
        raise NotImplementedError

    def _unregister_server_steps(self, name: str, timeout: float | None) -> Steps[None]:
        raise NotImplementedError

    def _call_steps(
        self,
        target_rr: str,
        server: str,
        request: Any,
        on_status: StatusCallback | None,
        timeout: float | None,
        query_id: str | None,
    ) -> Steps[Query]:
        raise NotImplementedError

    def _unload_steps(self, query_id: str, timeout: float | None) -> Steps[None]:
        raise NotImplementedError

    def _send_status_steps(
        self, query_id: str, status: Status, message: str, timeout: float | None
    ) -> Steps[None]:
        raise NotImplementedError

    def _server_queries_steps(self, server: str, timeout: float | None) -> Steps[list[Query]]:
        raise NotImplementedError

    def _fetch_queries_steps(
        self, target_rr: str, server: str, timeout: float | None
    ) -> Steps[list[Query]]:
        raise NotImplementedError

    def _client_queries_steps(self, timeout: float | None) -> Steps[list[Query]]:
        raise NotImplementedError

    def _set_status_callback_steps(
        self, query_id: str, callback: StatusCallback, timeout: float | None
    ) -> Steps[None]:
        raise NotImplementedError

    def _update_response_steps(
        self, query_id: str, response: Any, timeout: float | None
    ) -> Steps[None]:
        raise NotImplementedError

    def _save_catalog_steps(self, timeout: float | None) -> Steps[None]:
        raise NotImplementedError

    def _stop_steps(self, timeout: float | None) -> Steps[None]:
        raise NotImplementedError

    # -- the awaitables ----------------------------------------------------------------

    async def aregister_server(
        self,
        name: str,
        *,
        load: LoadCallback,
        unload: UnloadCallback,
        on_status: StatusCallback | None = None,
        timeout: float | None = None,
        label: Callable[[Any], str] | None = None,
    ) -> None:
        """`register_server`, awaited.

        `load`, `unload` and `on_status` may be coroutine functions (`async def`): they
        then run on the event loop of the registrar's process (one thread for all of
        them), a slow one awaiting without holding a thread; plain ones run on worker
        threads. Either kind may be registered through either twin.

        Raises:
            ConfigError: a callback is not callable (or `label` is a coroutine function),
                or the name is invalid.
            DuplicateNameError: a server with this name exists on this registrar.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        steps = self._register_server_steps(name, load, unload, on_status, timeout, label)
        await run_steps_async(steps)

    async def aunregister_server(self, name: str, *, timeout: float | None = None) -> None:
        """`unregister_server`, awaited (rule 12).

        Raises:
            UnknownServerError: no such server here.
            CallTimeoutError: not finished within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        await run_steps_async(self._unregister_server_steps(name, timeout))

    async def acall(
        self,
        target_rr: str,
        server: str,
        request: Any,
        *,
        on_status: StatusCallback | None = None,
        timeout: float | None = None,
        query_id: str | None = None,
    ) -> Query:
        """`call`, awaited (rules 1-6, 17): the provider's answer wakes the loop.

        Awaited inside a coroutine `load` of this registrar, the query is recorded as a
        dependency of the resource being loaded, as `call` inside a plain `load` is.
        `on_status` may be a coroutine function: it then runs on the loop this call was
        awaited from, one update at a time (see `StatusWatch` for an iterator instead).

        Raises:
            ResourceLoadError: `load` raised there or further down; `stack` says where.
            DependencyCycleError: the load would wait for itself further up its chain.
            UnknownServerError: no such registrar or server.
            CallTimeoutError: no answer in time; the query id is released if it loads
                later.
            RegistrarUnavailableError: the provider died (it may have executed the load).
            RegistrarStoppedError: this registrar or the provider was stopped.
            ConfigError: as for `call`.
            asyncio.CancelledError: the awaiting task was cancelled: the call was
                withdrawn as a timed-out one is (nothing is left held).
        """
        steps = self._call_steps(target_rr, server, request, on_status, timeout, query_id)
        return await run_steps_async(steps)

    async def aunload(self, query_id: str, *, timeout: float | None = None) -> None:
        """`unload`, awaited (rules 7-8).

        Raises:
            UnknownQueryError: the id is unknown here or already released.
            CallTimeoutError: not finished within `timeout` seconds.
            RegistrarUnavailableError: the provider died before it answered (see
                `unload`: the release is done all the same).
            RegistrarStoppedError: this registrar, or the provider, was stopped.
        """
        await run_steps_async(self._unload_steps(query_id, timeout))

    async def asend_status(
        self, query_id: str, status: Status, message: str = "", *, timeout: float | None = None
    ) -> None:
        """`send_status`, awaited (rule 9): done once every callback on the way has run
        (a coroutine one: once it returned).

        Raises:
            UnknownQueryError: `query_id` is not a consumer id of a resource served here.
            ConfigError: `status` is not a `Status`.
            MessageTooLargeError: over a consumer's `max_message_bytes` (see `send_status`).
            CallTimeoutError: not delivered everywhere within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        await run_steps_async(self._send_status_steps(query_id, status, message, timeout))

    async def aserver_queries(self, server: str, *, timeout: float | None = None) -> list[Query]:
        """`server_queries`, awaited (rule 10).

        Raises:
            UnknownServerError: no such server here.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        return await run_steps_async(self._server_queries_steps(server, timeout))

    async def afetch_queries(
        self, target_rr: str, server: str, *, timeout: float | None = None
    ) -> list[Query]:
        """`fetch_queries`, awaited (rule 10).

        Raises:
            UnknownServerError: no such registrar or server.
            ConfigError: `target_rr` or `server` is not a str.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarUnavailableError: the provider died.
        """
        return await run_steps_async(self._fetch_queries_steps(target_rr, server, timeout))

    async def aclient_queries(self, *, timeout: float | None = None) -> list[Query]:
        """`client_queries`, awaited.

        Raises:
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        return await run_steps_async(self._client_queries_steps(timeout))

    async def aset_status_callback(
        self, query_id: str, callback: StatusCallback, *, timeout: float | None = None
    ) -> None:
        """`set_status_callback`, awaited (rule 11); a coroutine `callback` runs on the
        loop this was awaited from.

        Raises:
            UnknownQueryError: this registrar holds no such query.
            ConfigError: `callback` is not callable.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        await run_steps_async(self._set_status_callback_steps(query_id, callback, timeout))

    async def aupdate_response(
        self, query_id: str, response: Any, *, timeout: float | None = None
    ) -> None:
        """`update_response`, awaited (rule 11).

        Raises:
            UnknownQueryError: `query_id` is not a consumer id of a resource served here.
            MessageTooLargeError: over a consumer's `max_message_bytes`.
            CallTimeoutError: not delivered within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        await run_steps_async(self._update_response_steps(query_id, response, timeout))

    async def asave_catalog(self, *, timeout: float | None = None) -> None:
        """`save_catalog`, awaited.

        Raises:
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        await run_steps_async(self._save_catalog_steps(timeout))

    async def astop(self, *, timeout: float | None = None) -> None:
        """`stop`, awaited (rule 12). Stopping a stopped registrar is a no-op.

        Raises:
            CallTimeoutError: not finished within `timeout` seconds.
            RegistrarUnavailableError: the registrar died while it stopped.
        """
        await run_steps_async(self._stop_steps(timeout))

    async def __aenter__(self) -> Any:
        return self

    async def __aexit__(self, *_: object) -> None:
        await self.astop()

    def watch(self, query_id: str, *, maxsize: int = 256) -> StatusWatch:
        """The status updates of query `query_id`, as an async iterator.

        ```python
        async for update in reg.watch(query.id):   # rr.StatusUpdate, in order
            print(update.status, update.message)
        ```

        Once opened (its first step, or `async with`) it is the query's status callback
        (it replaces the one the call was made with, as `aset_status_callback` does).
        Iteration ends after a `FATAL` (the resource is gone for good, rule 19) or once
        the watch is closed (`aclose()`, or leaving its `async with` block; a closed
        watch drops what comes). An `async for` that breaks leaves it open: use `async
        with` to close it. It does not end when the query is released: its reader
        decides when to stop. Updates are queued for it on the loop it was opened on;
        past `maxsize` the oldest is dropped (and counted in `dropped`), so a reader that
        falls behind never holds the registrar.

        Args:
            query_id: a query this registrar holds (from `call` or `acall`).
            maxsize: updates kept for a reader that falls behind.

        Returns:
            The watch: iterate it with `async for` from a coroutine on one loop.

        Raises:
            ConfigError: `maxsize` is not a positive int (at once); the first step of
                the iteration raises what `aset_status_callback` raises (an unknown id:
                `UnknownQueryError`).
        """
        if isinstance(maxsize, bool) or not isinstance(maxsize, int) or maxsize < 1:
            raise ConfigError(f"maxsize must be a positive int, got {maxsize!r}")
        return StatusWatch(self, query_id, maxsize)


class StatusWatch:
    """A query's status updates as an async iterator (`AsyncSurface.watch` makes one).

    Attributes:
        query_id: the query watched.
        dropped: updates dropped because the reader fell more than `maxsize` behind.
    """

    def __init__(self, registrar: AsyncSurface, query_id: str, maxsize: int) -> None:
        self._registrar = registrar
        self.query_id = query_id
        self._maxsize = maxsize
        self._updates: asyncio.Queue[StatusUpdate | None] | None = None  # None: closed
        self._closed = False
        self._ended = False
        self.dropped = 0

    def __repr__(self) -> str:
        return f"<StatusWatch {self.query_id!r}{' closed' if self._closed else ''}>"

    async def _receive(self, _query: Query, update: StatusUpdate) -> None:
        """The query's status callback, on the watch's loop."""
        updates = self._updates
        if updates is None or self._closed:
            return
        if updates.full():
            updates.get_nowait()
            self.dropped += 1
        updates.put_nowait(update)

    async def open(self, *, timeout: float | None = None) -> StatusWatch:
        """Become the query's status callback now (the first `__anext__` does it too).

        Raises:
            UnknownQueryError: the registrar holds no such query.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: the registrar was stopped.
            RegistrarUnavailableError: the registrar died.
        """
        if self._updates is None:
            self._updates = asyncio.Queue(self._maxsize)
            await self._registrar.aset_status_callback(
                self.query_id, self._receive, timeout=timeout
            )
        return self

    def __aiter__(self) -> StatusWatch:
        return self

    async def __anext__(self) -> StatusUpdate:
        if self._closed or self._ended:
            raise StopAsyncIteration
        await self.open()
        assert self._updates is not None
        update = await self._updates.get()
        if update is None:  # closed while this waited (`aclose`)
            raise StopAsyncIteration
        if update.status is Status.FATAL:
            self._ended = True
        return update

    async def aclose(self) -> None:
        """Stop collecting: updates that come later are dropped; iteration ends, also
        for a reader that waits for the next update (in another task of the loop)."""
        self._closed = True
        updates = self._updates
        if updates is not None:  # wake a reader waiting for the next update: it ends
            if updates.full():
                updates.get_nowait()  # (unread: a closed watch gives nothing more)
            updates.put_nowait(None)

    async def __aenter__(self) -> StatusWatch:
        return await self.open()

    async def __aexit__(self, *_: object) -> None:
        await self.aclose()
