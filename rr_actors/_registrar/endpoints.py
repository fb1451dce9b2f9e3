"""A registrar's endpoint actors: its resource servers and its clients (thesis 4.3.3).

```
 registrar actor ──RunLoad/RunUnload──► ServerActor ──submit──► worker thread: load() / unload()
        ▲                                                              │
        └────────────────────── reply (a token back to the mailbox) ◄──┘
 handle ──FetchVia──► ClientActor ──Fetch──► provider registrar
```
"""

from __future__ import annotations

from typing import Any

import pykka

from rr_actors._core.actor import Actor, refuse
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.workers import Workers
from rr_actors._registrar.loading import LOADING, LoadContext, check_picklable, load_error
from rr_actors._registrar.messages import Fetch, FetchVia, RunLoad, RunUnload
from rr_actors._registrar.protocol import LoadCallback, UnloadCallback
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

    def on_receive(self, message: Any) -> None:
        if isinstance(message, RunLoad):
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

    def _load(self, message: RunLoad) -> None:
        token = LOADING.set(LoadContext(self.registrar, message.resource_id, message.chain))
        try:
            response = self.load(message.request)
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
