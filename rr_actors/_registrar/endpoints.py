"""A registrar's endpoint actors: its resource servers and its clients (thesis 4.3.3).

```
 registrar actor ──RunLoad/RunUnload──► ServerActor ──submit──► worker thread: load() / unload()
        ▲                                    │ (async def)                     │
        │                                    └──task──► the process's event loop:
        │                                               await load() / unload()
        └────────────────────── reply (a token back to the mailbox) ◄──┘
 handle ──FetchVia──► ClientActor ──Fetch──► provider registrar
```

A server's callbacks that are coroutine functions run as tasks of the process's own
event loop (`_core/loops.py`): a load that awaits a slow resource holds no thread, so
ten thousand of them cost ten thousand tasks, not threads. The rules are the blocking
ones': loads of one server run concurrently, a hung load fails its callers at their
`timeout` (rule 17), an unload is bounded by `unload_timeout` (past it, it is cancelled
rather than abandoned on its thread), and the tasks still running when the server stops
are cancelled (a load then fails, an unload is cut short, as a stop cuts one short).
"""

from __future__ import annotations

import asyncio
import inspect
from collections.abc import Awaitable, Coroutine
from typing import Any, cast

import pykka

from rr_actors._core.actor import Actor, refuse
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.loops import is_coroutine_function, process_loop
from rr_actors._core.workers import Workers
from rr_actors._registrar.loading import LOADING, LoadContext, check_picklable, load_error
from rr_actors._registrar.messages import Fetch, FetchVia, RunLoad, RunUnload
from rr_actors._types import LoadCallback, UnloadCallback
from rr_actors.errors import CallTimeoutError, RrError

__all__ = ["ClientActor", "Clients", "ServerActor"]


def _no_thread(exc: RuntimeError) -> RuntimeError:
    """What a callback that got no worker thread fails with (the OS refused a thread)."""
    error = RuntimeError(f"no worker thread could be started for the callback: {exc}")
    error.__cause__ = exc
    return error


class ServerActor(Actor):
    """A resource server: owns its callbacks and runs them on the registrar's workers.

    `load` and `unload` run on a worker thread of the registrar's process, never on an
    actor thread, so different requests to one server load concurrently.
    """

    def __init__(
        self,
        registrar: str,
        name: str,
        load: LoadCallback,
        unload: UnloadCallback,
        workers: Workers,
        *,
        persisted: bool = False,
    ) -> None:
        super().__init__()
        self.persisted = persisted  # responses must pickle: the catalog stores them
        self.registrar = registrar
        self.name = name
        self.load = load
        self.unload = unload
        self.workers = workers
        self.on_loop = is_coroutine_function(load), is_coroutine_function(unload)
        self.tasks: set[asyncio.Task[None]] = set()  # its coroutines running (loop thread)

    def on_receive(self, message: Any) -> None:
        if isinstance(message, RunLoad) and self.on_loop[0]:
            self._spawn(self._aload(message))
        elif isinstance(message, RunUnload) and self.on_loop[1]:
            self._spawn(self._aunload(message))
        elif isinstance(message, RunLoad):
            try:
                self.workers.submit(lambda: self._load(message))
            except RuntimeError as exc:  # no thread could start: this load fails, no other
                message.reply.set_error(load_error(self.registrar, self.name, _no_thread(exc)))
        elif isinstance(message, RunUnload):
            timeout = message.timeout

            def overdue() -> None:
                message.reply.set_error(
                    CallTimeoutError(
                        f"the unload callback of '{self.registrar}/{self.name}' did not "
                        f"return within {timeout:g} s"
                    )
                )

            try:
                self.workers.submit(
                    lambda: self._unload(message),
                    timeout=timeout,
                    on_overdue=None if timeout is None else overdue,
                )
            except RuntimeError as exc:
                message.reply.set_error(_no_thread(exc))

    def on_stop(self) -> None:
        """Cancel its coroutines still running (a load fails, an unload is cut short)."""
        if self.on_loop[0] or self.on_loop[1]:
            loop = process_loop()
            tasks = self.tasks
            try:
                loop.call_soon_threadsafe(lambda: [task.cancel() for task in list(tasks)])
            except RuntimeError:  # (the loop is closed: nothing runs there any more)
                return

    def _spawn(self, coroutine: Coroutine[Any, Any, None]) -> None:
        """Run `coroutine` as a task of the process's loop, kept until it ends."""
        tasks = self.tasks

        def start() -> None:
            task = asyncio.get_running_loop().create_task(coroutine)
            tasks.add(task)
            task.add_done_callback(tasks.discard)

        process_loop().call_soon_threadsafe(start)

    async def _aload(self, message: RunLoad) -> None:
        """A coroutine `load`, on the process's loop (its task's own context)."""
        LOADING.set(LoadContext(self.registrar, message.resource_id, message.chain))
        try:
            response = await self.load(message.request)
            if self.persisted:
                check_picklable(response, "the response")
        except BaseException as exc:  # noqa: BLE001 - any exception fails the load (rule 4)
            message.reply.set_error(load_error(self.registrar, self.name, exc))
        else:
            message.reply.set_result(response)

    async def _aunload(self, message: RunUnload) -> None:
        """A coroutine `unload`, on the process's loop, cancelled past `timeout`."""
        timeout = message.timeout
        bound = asyncio.timeout(timeout)
        try:
            async with bound:
                await cast("Awaitable[None]", self.unload(message.request, message.response))
        except TimeoutError as exc:
            if not bound.expired():  # (the callback's own TimeoutError)
                message.reply.set_error(exc)
                return
            message.reply.set_error(
                CallTimeoutError(
                    f"the unload callback of '{self.registrar}/{self.name}' did not "
                    f"return within {timeout:g} s"
                )
            )
        except BaseException as exc:  # noqa: BLE001 - logged by the registrar, never lost
            message.reply.set_error(exc)
        else:
            message.reply.set_result(None)

    def _load(self, message: RunLoad) -> None:
        token = LOADING.set(LoadContext(self.registrar, message.resource_id, message.chain))
        try:
            response = self.load(message.request)
            _refuse_awaitable(response)
            if self.persisted:
                check_picklable(response, "the response")
        except BaseException as exc:  # noqa: BLE001 - any exception fails the load (rule 4)
            message.reply.set_error(load_error(self.registrar, self.name, exc))
        else:
            message.reply.set_result(response)
        finally:
            LOADING.reset(token)

    def _unload(self, message: RunUnload) -> None:
        try:
            self.unload(message.request, message.response)
        except BaseException as exc:  # noqa: BLE001 - logged by the registrar, never lost
            message.reply.set_error(exc)
        else:
            message.reply.set_result(None)


def _refuse_awaitable(response: Any) -> None:
    """A plain `load` that returned an awaitable (a callable object whose call makes a
    coroutine) fails: nobody would await it. It is closed (no "never awaited" warning).

    Raises:
        TypeError: `response` is awaitable.
    """
    if not inspect.isawaitable(response):
        return
    close = getattr(response, "close", None)
    if close is not None:
        close()
    raise TypeError(
        "load returned an awaitable: make it a coroutine function (async def) for the "
        "registrar to await it"
    )


class ClientActor(Actor):
    """A client: the consumer-side endpoint for one target server (thesis 4.3.3).

    Created (and cached) by its registrar the first time it calls the server. It relays
    fetches. A load (and the give-up of a timed-out one) is sent from the caller's thread
    along the client's route (see `ResourceRegistrar.call`); status callbacks run on the
    registrar's worker threads.
    """

    def __init__(
        self,
        registrar_ref: pykka.ActorRef[Any],
        origin_rr: str,
        target_rr: str,
        server: str,
    ) -> None:
        super().__init__()
        self.registrar_ref = registrar_ref
        self.origin_rr = origin_rr
        self.target_rr = target_rr
        self.server = server

    def on_late(self, envelope: Any) -> None:
        """A fetch that reached this client after it ended is answered, not dropped."""
        refuse(envelope)
        reply = getattr(envelope.message, "reply", None)
        if reply is not None:
            reply.set_error(DIRECTORY.gone_error(self.origin_rr))

    def on_receive(self, message: Any) -> None:
        if isinstance(message, FetchVia):
            try:
                DIRECTORY.lookup(self.target_rr).tell(
                    Fetch(message.server, self.origin_rr, message.reply)
                )
            except RrError as exc:
                message.reply.set_error(exc)


class Clients:
    """A registrar's client actors by `(target registrar, server)`: its one client cache.

    Its actor starts them (`start`, on the actor's thread) and stops them; its handle
    looks them up from any thread (`get`, one dict read), so that a call to a server it
    called before does not ask the actor first.
    """

    __slots__ = ("_refs",)

    def __init__(self) -> None:
        self._refs: dict[tuple[str, str], pykka.ActorRef[ClientActor]] = {}

    def get(self, target_rr: str, server: str) -> pykka.ActorRef[ClientActor] | None:
        """The client actor for `target_rr/server`, if one was started (any thread)."""
        return self._refs.get((target_rr, server))

    def start(
        self, registrar_ref: pykka.ActorRef[Any], origin_rr: str, target_rr: str, server: str
    ) -> pykka.ActorRef[ClientActor]:
        """The client actor for `target_rr/server`, started on first use (actor thread)."""
        key = (target_rr, server)
        client = self._refs.get(key)
        if client is None:
            client = ClientActor.start(registrar_ref, origin_rr, target_rr, server)
            self._refs[key] = client
        return client

    def stop_all(self) -> None:
        """Stop every client actor (the registrar stops or died; actor thread)."""
        for client in list(self._refs.values()):
            client.stop(block=True, timeout=5.0)
