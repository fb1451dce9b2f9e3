"""The resource registrar: its actor, its resource-server and client actors, and its handle.

Message flow (thesis 4.2, figures 4.3-4.5), all through pykka mailboxes:

* `call`: caller thread -> client actor -> provider registrar actor. A dedup hit is answered
  by the provider actor at once; a miss goes to the server actor, which runs `load` on a
  worker thread and answers the registrar actor, which answers every waiter.
* `unload`: consumer registrar actor -> provider registrar actor; the last consumer id
  releases the resource's dependencies, then the server actor runs `unload`.
* `send_status`: provider registrar actor -> each consumer registrar actor (status
  callbacks on worker threads) and, for dependencies, on up to those resources'
  consumers. The acknowledgements travel back without entering a mailbox: each one is
  counted where it arrives (`SharedJoin`), and the last one answers the sender.

Registrar actors never wait: each question they ask another actor carries a token, and
the answer arrives as a message that resumes the work (`Tokens`, `Join`). User callbacks
run on worker threads (`Workers`), so a slow or hung callback never blocks a mailbox.
"""

from __future__ import annotations

import collections
import contextlib
import contextvars
import dataclasses
import functools
import logging
import queue
import threading
import time
import traceback
import uuid
from collections.abc import Callable
from typing import Any, ClassVar

import cloudpickle
import pykka

from rr_actors._catalog import Catalog, ClientRecord, Resource, ResourceState
from rr_actors._core.actor import Actor, OneShotFuture, refuse
from rr_actors._core.directory import DIRECTORY, LocalPeer, Reply
from rr_actors._core.replies import (
    Answer,
    CallbackReply,
    FutureReply,
    Join,
    SharedJoin,
    Tokens,
    wait,
)
from rr_actors._core.timers import Cancellable
from rr_actors._core.workers import Workers
from rr_actors._registrar.messages import (
    Abandon,
    ConsumerDown,
    Fetch,
    Load,
    ResponseUpdated,
    Revoke,
    StatusNotice,
    Unload,
)
from rr_actors._registrar.protocol import LoadCallback, UnloadCallback
from rr_actors._store import Saver, gc_paused, open_store
from rr_actors._types import Query, Status, StatusCallback, StatusUpdate
from rr_actors.config import RegistrarConfig, check_seconds
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    DependencyCycleError,
    DuplicateNameError,
    ErrorFrame,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    ResourceLoadError,
    RrError,
    UnknownQueryError,
    UnknownServerError,
)

__all__ = ["MAX_DEPENDENCY_DEPTH", "ResourceRegistrar"]

logger = logging.getLogger("rr_actors")

MAX_DEPENDENCY_DEPTH = 64
"""A load chain deeper than this is reported as a `DependencyCycleError` (runaway recursion)."""


@dataclasses.dataclass(frozen=True)
class LoadContext:
    """What is being loaded on the current thread (read by `call` to record dependencies)."""

    registrar: str
    resource_id: str
    chain: tuple[str, ...]


_LOADING: contextvars.ContextVar[LoadContext | None] = contextvars.ContextVar(
    "rr_actors_loading", default=None
)


# -- internal messages (never leave the process) ---------------------------------------


@dataclasses.dataclass(frozen=True)
class _RunLoad:
    resource_id: str
    request: Any
    chain: tuple[str, ...]
    reply: Reply


@dataclasses.dataclass(frozen=True)
class _RunUnload:
    request: Any
    response: Any
    reply: Reply


@dataclasses.dataclass(frozen=True)
class _FetchVia:
    server: str
    reply: Reply


@dataclasses.dataclass(frozen=True)
class _Pending:
    """A durable call about to go out: write its record as pending, then answer `reply`."""

    record: ClientRecord
    attempt: OneShotFuture[Any]
    reply: Reply


@dataclasses.dataclass(frozen=True)
class _ClientLoaded:
    record: ClientRecord  # its query holds the response
    on_status: StatusCallback | None
    attempt: OneShotFuture[Any]  # the caller's future
    answer_after_commit: bool = False  # the registrar answers the caller, after the commit


@dataclasses.dataclass(frozen=True)
class _CallFailed:
    """A call ended without an answer to record: it failed, or its caller withdrew it."""

    query_id: str
    attempt: OneShotFuture[Any]
    withdrawn: bool = False  # given up by its caller, who told the provider an Abandon first


@dataclasses.dataclass(frozen=True)
class _Request:
    """A request from the handle: run `op(actor)` in the actor thread, answer `reply`."""

    op: Callable[[RegistrarActor, Reply], None]
    reply: Reply


@dataclasses.dataclass(frozen=True)
class _Flush:
    pass


@dataclasses.dataclass(frozen=True)
class _Crash:
    pass


class _ClientReply:
    """The answer to a consumer's load: hand it to the caller, who records it.

    The caller's thread wakes with the value and tells the consumer's registrar the
    client record itself (`ResourceRegistrar.call`): the answering thread (a
    connection's reader, or the provider's actor) wakes one thread, not two, and the
    caller's later `unload` follows the record in the mailbox. A notice about the query
    that reaches the registrar before the record waits for it (`_DueAnswers`).

    Whoever settles the caller's one-shot future first owns the answer: this reply, by
    setting it, or the caller, by claiming it when it stops waiting (a timeout, a
    `KeyboardInterrupt`). A caller that claimed it withdrew the call and sent the
    provider an `Abandon` after the `Load`, so an answer that comes later is dropped here.
    With `commit_first` (a durable consumer) the record was written as pending before
    the load was sent; the registrar commits the answer and then sets the future (or,
    finding it claimed, drops the record).
    """

    __slots__ = ("commit_first", "future", "on_status", "record", "registrar")

    def __init__(
        self,
        registrar: pykka.ActorRef[Any],
        record: ClientRecord,
        on_status: StatusCallback | None,
        future: OneShotFuture[Any],
        *,
        commit_first: bool,
    ) -> None:
        self.registrar = registrar
        self.record = record
        self.on_status = on_status
        self.future = future
        self.commit_first = commit_first

    def set_result(self, value: Any) -> None:
        if not self.commit_first:
            with contextlib.suppress(queue.Full):  # (claimed: the caller withdrew the call)
                self.future.set(value)
            return  # the caller records it
        query = self.record.query.with_response(value)
        record = ClientRecord(query, self.record.parent, loaded=True)
        try:
            self.registrar.tell(
                _ClientLoaded(record, self.on_status, self.future, self.commit_first)
            )
        except pykka.ActorDeadError:  # the consumer stopped meanwhile: give the id back
            with contextlib.suppress(RrError):
                DIRECTORY.lookup(query.serving_rr).tell(Abandon(query.id, query.origin_rr))
            FutureReply(self.future).set_error(
                RegistrarStoppedError(f"registrar {query.origin_rr!r} stopped during the call")
            )

    def set_error(self, error: BaseException) -> None:
        with contextlib.suppress(pykka.ActorDeadError):
            self.registrar.tell(_CallFailed(self.record.query.id, self.future))
        FutureReply(self.future).set_error(error)


class _DueAnswers:
    """The query ids whose answer a consumer has not recorded yet, with their attempt.

    Shared by the registrar's callers and its actor: a caller adds its query id before
    its `Load` leaves; the actor removes it once it handled that attempt's answer
    (`_ClientLoaded`) or failure (`_CallFailed`). Across processes the provider's notices
    about a query (status, response update, revoke) travel on the provider's connection
    to this registrar's listener, while the answer comes back on this process's
    connection to the provider, read by another thread: a notice can overtake the answer
    it is about. The actor holds such a notice until the query id is no longer due. The
    lock makes "remove it if it is still this attempt's" atomic against a retry that
    reuses the query id.
    """

    __slots__ = ("_attempts", "_lock")

    def __init__(self) -> None:
        self._attempts: dict[str, OneShotFuture[Any]] = {}
        self._lock = threading.Lock()

    def __contains__(self, query_id: str) -> bool:
        return query_id in self._attempts

    def expect(self, query_id: str, attempt: OneShotFuture[Any]) -> None:
        """A call `attempt` with `query_id` is about to be sent (any thread)."""
        with self._lock:
            self._attempts[query_id] = attempt

    def settle(self, query_id: str, attempt: OneShotFuture[Any]) -> bool:
        """`attempt`'s answer or failure was handled; whether it was the one due."""
        with self._lock:
            if self._attempts.get(query_id) is attempt:
                del self._attempts[query_id]
                return True
        return False


def _check_picklable(value: Any, what: str) -> None:
    """Raise `ConfigError` if `value` cannot be stored in a catalog backup."""
    try:
        cloudpickle.dumps(value)
    except Exception as exc:
        raise ConfigError(
            f"{what} cannot be pickled, so the catalog cannot store it: {exc}"
        ) from exc


def _load_error(registrar: str, server: str, exc: BaseException) -> RrError:
    """Turn what a `load` callback raised into the error its callers get."""
    inner: BaseException | None = exc
    while inner is not None and not isinstance(inner, ResourceLoadError | DependencyCycleError):
        inner = inner.__cause__
    if isinstance(inner, DependencyCycleError):
        return inner
    frame = ErrorFrame(
        registrar=registrar,
        server=server,
        exc_type=type(exc).__qualname__,
        message=str(exc),
        traceback="".join(traceback.format_exception(exc)),
    )
    stack = inner.stack if isinstance(inner, ResourceLoadError) else ()
    return ResourceLoadError((*stack, frame))


# -- the actors ------------------------------------------------------------------------


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
        if isinstance(message, _RunLoad):
            self.workers.submit(lambda: self._load(message))
        elif isinstance(message, _RunUnload):
            self.workers.submit(lambda: self._unload(message))

    def _load(self, message: _RunLoad) -> None:
        token = _LOADING.set(LoadContext(self.registrar, message.resource_id, message.chain))
        try:
            response = self.load(message.request)
            if self.persisted:
                _check_picklable(response, "the response")
        except BaseException as exc:  # noqa: BLE001 - any exception fails the load (rule 4)
            message.reply.set_error(_load_error(self.registrar, self.name, exc))
        else:
            message.reply.set_result(response)
        finally:
            _LOADING.reset(token)

    def _unload(self, message: _RunUnload) -> None:
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
        if isinstance(message, _FetchVia):
            try:
                DIRECTORY.lookup(self.target_rr).tell(
                    Fetch(message.server, self.origin_rr, message.reply)
                )
            except RrError as exc:
                message.reply.set_error(exc)


class _OpenReply:
    """A handle request's reply, known to its actor until answered (a crash fails it).

    Answered on the actor thread, or, for `send_status`, on the thread of the last
    acknowledgement: so `open_requests` is only ever changed by single `set` operations
    (add, discard) and read as a copy (`list(...)`), each atomic.
    """

    __slots__ = ("open", "reply")

    def __init__(self, reply: Reply, open_requests: set[_OpenReply]) -> None:
        self.reply = reply
        self.open = open_requests
        open_requests.add(self)

    def set_result(self, value: Any) -> None:
        self.open.discard(self)
        self.reply.set_result(value)

    def set_error(self, error: BaseException) -> None:
        self.open.discard(self)
        self.reply.set_error(error)


def _log_failure(what: str, then: Callable[[], None], _: Any, error: BaseException | None) -> None:
    """A continuation that logs a failed answer, then runs `then()`."""
    if error is not None:
        logger.warning("%s failed: %s", what, error)
    then()


def _consumers_by_origin(resource: Resource) -> dict[str, tuple[str, ...]]:
    """A resource's consumer ids, grouped by the registrar that holds them."""
    by_origin: dict[str, list[str]] = {}
    for query_id, origin in resource.consumers.items():
        by_origin.setdefault(origin, []).append(query_id)
    return {origin: tuple(ids) for origin, ids in by_origin.items()}


@dataclasses.dataclass
class _Server:
    name: str
    ref: pykka.ActorRef[ServerActor]
    on_status: StatusCallback | None
    closing: bool = False


@dataclasses.dataclass
class _Waiter:
    query_id: str
    origin_rr: str
    reply: Reply


class RegistrarActor(Actor):
    """The registrar actor: the only writer of its catalog.

    It never blocks: what it needs from another actor arrives later as a message.
    """

    def __init__(
        self,
        config: RegistrarConfig,
        catalog: Catalog,
        saver: Saver,
        peer: LocalPeer,
        died: threading.Event,
        due: _DueAnswers,
        ended: threading.Event,
        *,
        setting_up: bool = False,
    ) -> None:
        super().__init__()
        self.config = config
        self.name = config.name
        self.catalog = catalog
        self.saver = saver
        self.peer = peer
        self.workers = Workers(config.name)
        self.tokens = Tokens()
        self.servers: dict[str, _Server] = {}
        self.clients: dict[tuple[str, str], pykka.ActorRef[ClientActor]] = {}
        self.status_callbacks: dict[str, StatusCallback] = {}
        self.loads: dict[str, list[_Waiter]] = {}  # resource id -> callers waiting for it
        self.loading_ids: dict[str, str] = {}  # waiting query id -> resource id
        self.abandoned: set[str] = set()  # provider side: callers that gave up on a load
        # consumer side: the futures of durable calls in flight (answered by this actor
        # after its commit)
        self.pending_attempts: dict[str, OneShotFuture[Any]] = {}
        self.unload_waiters: dict[str, list[Reply]] = {}
        self.after_unload: dict[str, list[Load]] = {}
        self.parked_unloads: dict[str, list[Callable[[], None]]] = {}
        self.seen_events: collections.OrderedDict[tuple[str, str], None] = collections.OrderedDict()
        self.stopping = False
        self.setting_up = setting_up  # loads for servers setup has not registered wait
        self.held_loads: list[Load] = []
        self.setup_done = False  # start(setup=) finished: servers it did not register are gone
        self.open_requests: set[_OpenReply] = set()  # handle requests not answered yet
        self.died = died  # set once a crash was fully handled (see testing.crash)
        self.ended = ended  # set once the actor's thread handed on its last message
        self.due = due  # consumer side: calls whose answer is on its way
        self.parked_notices: dict[str, list[StatusNotice | Revoke | ResponseUpdated]] = {}
        self.flush_timer: Cancellable | None = None

    # -- life cycle -------------------------------------------------------------------

    def on_start(self) -> None:
        self.peer.ref = self.actor_ref
        self._settle_in_doubt()
        self._arm_flush_timer()

    def _settle_in_doubt(self) -> None:
        """Drop restored resources whose load or unload a crash cut short (rule 16).

        They were reported to the manager as `in_doubt`; what they held as dependencies
        is released, so nothing they started at other servers leaks. A top-level call that
        was in flight is given up at its provider (its caller died with the last run), and
        so is a dependency whose resource is gone (a sub-call that outlived its load).
        """
        for resource in list(self.catalog.resources.values()):
            if resource.state is not ResourceState.LOADED:
                self.catalog.begin_unload(resource.id)
                self._release_dependencies(
                    resource.id, functools.partial(self._remove_resource, resource)
                )
        for record in list(self.catalog.clients.values()):
            orphan = record.parent is not None and record.parent not in self.catalog.resources
            if orphan or (record.parent is None and not record.loaded):
                query = record.query
                with contextlib.suppress(RrError):
                    DIRECTORY.lookup(query.serving_rr).tell(Abandon(query.id, self.name))
                self.catalog.remove_client(query.id)
        self._commit()

    def on_receive(self, message: Any) -> None:
        handler = self._handlers.get(type(message))
        if handler is None:
            logger.warning("registrar %s ignored an unknown message %r", self.name, message)
            return
        try:
            handler(self, message)
        except RrError as exc:  # e.g. a restored value that cannot be decoded any more
            reply = getattr(message, "reply", None)
            if reply is not None:
                reply.set_error(exc)  # that request fails; the registrar keeps serving
            else:
                logger.exception("registrar %s: %s failed", self.name, type(message).__name__)
        except Exception as exc:
            reply = getattr(message, "reply", None)
            if reply is not None:  # a bug: the actor dies, but its caller hears of it now
                reply.set_error(RegistrarUnavailableError(f"registrar {self.name!r} died: {exc!r}"))
            raise

    def on_failure(self, *_: object) -> None:
        self._die()

    def _die(self) -> None:
        """A crash: fail every waiting caller, release this consumer's ids elsewhere."""
        DIRECTORY.unregister(self.peer, "died")
        self._fail_waiting(RegistrarUnavailableError(f"registrar {self.name!r} died"))
        self._stop_children()
        if self.flush_timer is not None:
            self.flush_timer.cancel()
        self.saver.close(erase=False, flush=False)  # a crash writes nothing more
        if self.name not in DIRECTORY.restart_expected:
            for peer in DIRECTORY.local_peers():
                with contextlib.suppress(RrError):
                    peer.tell(ConsumerDown(self.name))
        self.died.set()

    def _fail_waiting(self, error: RrError) -> None:
        """Answer everyone still waiting on this actor with `error` (it stops or died)."""
        for waiters in self.loads.values():
            for waiter in waiters:
                waiter.reply.set_error(error)
        for replies in self.unload_waiters.values():
            for reply in replies:
                reply.set_error(error)
        for loads in [*self.after_unload.values(), self.held_loads]:
            for load in loads:
                load.reply.set_error(error)
        for attempt in self.pending_attempts.values():
            FutureReply(attempt).set_error(error)
        for request in list(self.open_requests):
            request.set_error(error)
        self._fail_parked(error)
        while not self.actor_inbox.empty():
            self._refuse(self.actor_inbox.get(), error)

    def _actor_loop_teardown(self) -> None:
        super()._actor_loop_teardown()  # what was left went to `on_late`
        self.ended.set()

    def on_late(self, envelope: Any) -> None:
        """A message that arrived after this actor's loop ended (any thread)."""
        self._refuse(envelope, DIRECTORY.gone_error(self.name))

    def _refuse(self, envelope: Any, error: Exception) -> None:
        """Answer a message this actor will not handle (it stops or died); any thread."""
        refuse(envelope)  # a pykka ask, e.g. the handle's `ref.stop()`: it must hear
        message = envelope.message
        pending = getattr(message, "reply", None)
        if pending is not None:
            pending.set_error(error)
        if isinstance(message, _ClientLoaded):  # its id would leak at the provider
            query = message.record.query
            with contextlib.suppress(RrError):
                DIRECTORY.lookup(query.serving_rr).tell(Abandon(query.id, self.name))
            FutureReply(message.attempt).set_error(error)

    def _fail_parked(self, error: RrError) -> None:
        """Answer the notices still waiting for an answer that will not be handled now."""
        for notices in self.parked_notices.values():
            for notice in notices:
                if not isinstance(notice, Revoke):  # (a revoke wants no answer)
                    notice.reply.set_error(error)
        self.parked_notices.clear()

    def _stop_children(self) -> None:
        for server in self.servers.values():
            server.ref.stop(block=True, timeout=5.0)
        for client in self.clients.values():
            client.stop(block=True, timeout=5.0)

    # -- persistence ------------------------------------------------------------------

    def _commit(self) -> None:
        if self.saver.store is None:  # nothing persists this catalog
            return
        changes = self.catalog.drain_changes()
        if changes:
            self.saver.changed(changes)

    def _arm_flush_timer(self) -> None:
        interval = self.saver.flush_interval
        if interval is None:
            return
        ref = self.actor_ref

        def tick() -> None:
            with contextlib.suppress(pykka.ActorDeadError):
                ref.tell(_Flush())

        self.flush_timer = self.saver.schedule(tick)

    def _on_flush(self, _: _Flush) -> None:
        if self.stopping:
            return
        self.saver.flush()
        self._arm_flush_timer()

    # -- asking others without waiting ------------------------------------------------

    def _send(self, target: str, make: Callable[[Reply], Any], then: Callable[..., None]) -> None:
        """Send `make(reply)` to registrar `target`; `then(value, error)` runs on the answer."""
        reply = self.tokens.reply(self.actor_ref, then)
        try:
            DIRECTORY.lookup(target).tell(make(reply))
        except RrError as exc:
            reply.set_error(exc)

    def _on_answer(self, message: Answer) -> None:
        self.tokens.answer(message.token, message.value, message.error)

    # -- provider side: load ----------------------------------------------------------

    def _load_refusal(self, message: Load) -> RrError | None:
        """Why this registrar cannot take `message` at all, if it cannot."""
        server = self.servers.get(message.server)
        if server is None or server.closing:
            return UnknownServerError(f"no resource server '{self.name}/{message.server}'")
        if self.stopping:
            return RegistrarStoppedError(f"registrar {self.name!r} is stopping")
        if len(message.chain) >= MAX_DEPENDENCY_DEPTH:
            return DependencyCycleError(
                f"load chain deeper than {MAX_DEPENDENCY_DEPTH} at '{self.name}/"
                f"{message.server}': runaway recursion"
            )
        return None

    def _on_load(self, message: Load) -> None:
        if self.setting_up and message.server not in self.servers:
            self.held_loads.append(message)  # served once setup has registered its servers
            return
        refusal = self._load_refusal(message)
        if refusal is not None:
            message.reply.set_error(refusal)
            return
        self.abandoned.discard(message.query_id)  # a retry: its caller is back
        if self.catalog.has_consumer(message.query_id):  # a retry of an answered call
            message.reply.set_result(self.catalog.resource_of(message.query_id).response)
            return
        resource = self.catalog.find(message.server, message.request)
        if resource is not None and resource.state is ResourceState.LOADED:  # the hot path
            self.catalog.add_consumer(resource.id, message.query_id, message.origin_rr)
            self._commit()
            message.reply.set_result(resource.response)
            return
        waiter = _Waiter(message.query_id, message.origin_rr, message.reply)
        rid = self.loading_ids.get(message.query_id)
        if rid is not None:  # a retry while its load runs
            self.loads[rid].append(waiter)
            return
        if resource is None:
            self._start_load(self.servers[message.server], message, waiter)
        elif resource.state is ResourceState.LOADING:
            if resource.id in message.chain:
                message.reply.set_error(
                    DependencyCycleError(
                        f"'{self.name}/{message.server}' is asked for {message.request!r} "
                        f"while loading it further up the same chain"
                    )
                )
                return
            self.loads[resource.id].append(waiter)
            self.loading_ids[message.query_id] = resource.id
        else:  # unloading: load it afresh once the unload finished
            self.after_unload.setdefault(resource.id, []).append(message)

    def _start_load(self, server: _Server, message: Load, waiter: _Waiter) -> None:
        if self.saver.store is not None:  # the backup must be able to hold the request
            try:
                _check_picklable(message.request, f"the request to '{self.name}/{server.name}'")
            except ConfigError as exc:
                message.reply.set_error(exc)
                return
        rid = str(uuid.uuid4())
        self.catalog.begin_load(rid, message.server, message.request)
        self._commit()
        self.loads[rid] = [waiter]
        self.loading_ids[message.query_id] = rid
        reply = self.tokens.reply(
            self.actor_ref, lambda value, error: self._load_done(rid, value, error)
        )
        server.ref.tell(_RunLoad(rid, message.request, (*message.chain, rid), reply))

    def _load_done(self, rid: str, response: Any, error: BaseException | None) -> None:
        waiters = self.loads.pop(rid)
        for waiter in waiters:
            self.loading_ids.pop(waiter.query_id, None)
        resource = self.catalog.resources[rid]
        if error is not None:
            self.catalog.begin_unload(rid)
            self._commit()

            def failed() -> None:
                self._remove_resource(resource)
                for waiter in waiters:
                    self.abandoned.discard(waiter.query_id)
                    waiter.reply.set_error(error)

            self._release_dependencies(rid, failed)
            return
        self.catalog.finish_load(rid, response)
        live = []
        for waiter in waiters:
            if waiter.query_id in self.abandoned:  # its caller gave up: answer, hold nothing
                self.abandoned.discard(waiter.query_id)
                waiter.reply.set_error(CallTimeoutError(f"call {waiter.query_id} was given up"))
            elif not self.catalog.has_consumer(waiter.query_id):
                self.catalog.add_consumer(rid, waiter.query_id, waiter.origin_rr)
                live.append(waiter)
            else:
                live.append(waiter)
        self._commit()
        server = self.servers.get(resource.server)
        if server is None or server.closing:
            for waiter in live:
                if self.catalog.has_consumer(waiter.query_id):  # a retry may be listed twice
                    self.catalog.release(waiter.query_id)
                waiter.reply.set_error(
                    UnknownServerError(f"resource server '{self.name}/{resource.server}' closed")
                )
            live = []
        for waiter in live:
            waiter.reply.set_result(response)
        if not resource.consumers:  # every caller gave up (or the server closed)
            self._unload_resource(resource, None)

    # -- provider side: unload --------------------------------------------------------

    def _on_unload(self, message: Unload) -> None:
        self._release(message.query_id, message.reply)

    def _on_abandon(self, message: Abandon) -> None:
        self._release(message.query_id, None)

    def _release(self, query_id: str, reply: Reply | None) -> None:
        parked = self._unpark(query_id)
        if parked is not None:  # it waited behind an unload or for setup: it never loads
            parked.reply.set_error(CallTimeoutError(f"call {query_id} was given up"))
            if reply is not None:
                reply.set_result(None)
            return
        if query_id in self.loading_ids:  # its caller gave up while it loads
            self.abandoned.add(query_id)
            if reply is not None:
                reply.set_result(None)
            return
        try:
            resource = self.catalog.release(query_id)
        except UnknownQueryError as exc:
            if reply is not None:
                reply.set_error(exc)
            return
        if resource.consumers or resource.state is not ResourceState.LOADED:
            self._commit()
            if reply is not None:
                reply.set_result(None)
            return
        self._unload_resource(resource, reply)

    def _unpark(self, query_id: str) -> Load | None:
        """Take the load of `query_id` out of the held or parked loads, if it is there."""
        for loads in [self.held_loads, *self.after_unload.values()]:
            for load in loads:
                if load.query_id == query_id:
                    loads.remove(load)
                    return load
        return None

    def _unload_resource(self, resource: Resource, reply: Reply | None) -> None:
        """The last consumer left: release the dependencies, then run `unload` (rule 7)."""
        self.catalog.begin_unload(resource.id)
        self._commit()
        self.unload_waiters[resource.id] = [] if reply is None else [reply]

        def run_unload() -> None:
            server = self.servers.get(resource.server)
            if server is None and self.setup_done:  # setup did not bring the server back
                unloaded(None, None)
                return
            if server is None:  # restored, and no one has registered the server yet
                self.parked_unloads.setdefault(resource.server, []).append(run_unload)
                return
            done = self.tokens.reply(self.actor_ref, unloaded)
            server.ref.tell(_RunUnload(resource.request, resource.response, done))

        def unloaded(_: Any, error: BaseException | None) -> None:
            if error is not None:
                logger.error(
                    "unload callback of '%s/%s' raised; the resource is released anyway",
                    self.name,
                    resource.server,
                    exc_info=error,
                )
            self._remove_resource(resource)
            for waiting in self.unload_waiters.pop(resource.id):
                waiting.set_result(None)

        self._release_dependencies(resource.id, run_unload)

    def _remove_resource(self, resource: Resource) -> None:
        self.catalog.remove_resource(resource.id)
        self._commit()
        for load in self.after_unload.pop(resource.id, ()):
            self._on_load(load)
        server = self.servers.get(resource.server)
        if server is not None and server.closing and not self.catalog.resources_of(server.name):
            del self.servers[server.name]
            server.ref.stop(block=False)

    def _release_dependencies(self, rid: str, then: Callable[[], None]) -> None:
        join = Join(then)
        for record in self.catalog.dependencies(rid):
            self._release_client(record, join.add())
        join.seal()

    def _release_client(self, record: ClientRecord, then: Callable[[], None]) -> None:
        """Unload one query this registrar holds; the record goes whatever the answer."""
        query = record.query

        def answered(_: Any, error: BaseException | None) -> None:
            if error is not None and not isinstance(error, UnknownQueryError):
                logger.warning("releasing %s at %s failed: %s", query.id, query.serving_rr, error)
            if query.id in self.catalog.clients:
                self.catalog.remove_client(query.id)
                self.status_callbacks.pop(query.id, None)
                self._commit()
            then()

        self._send(query.serving_rr, lambda reply: Unload(query.id, self.name, reply), answered)

    def _on_consumer_down(self, message: ConsumerDown) -> None:
        for query_id in self.catalog.consumers_from(message.origin_rr):
            self._release(query_id, None)

    # -- provider side: status, fetch, revoke -----------------------------------------

    def _notify(
        self,
        resource: Resource,
        update: StatusUpdate,
        event: str,
        own_query_id: str | None,
        then: Callable[[], None],
    ) -> None:
        """Run this server's `on_status` once and pass the status on to every consumer.

        `then()` runs once every callback and consumer on the way acknowledged, on the
        thread of the last acknowledgement (a reader thread, a worker, another registrar's
        actor, or this one): it must not touch this actor's state, and must come back
        through the mailbox (`self.tokens.reply`) if it has to.
        """
        key = (event, resource.id)
        if key in self.seen_events:
            then()
            return
        self.seen_events[key] = None
        if len(self.seen_events) > 4096:
            self.seen_events.popitem(last=False)
        join = SharedJoin(then)  # acknowledgements: no trip back through this mailbox
        server = self.servers.get(resource.server)
        query_id = own_query_id or next(iter(resource.consumers), resource.id)
        if server is not None and server.on_status is not None:
            query = Query(
                query_id,
                resource.server,
                self.name,
                resource.consumers.get(query_id, self.name),
                resource.request,
                resource.response,
            )
            self._run_status(
                server.on_status, query, dataclasses.replace(update, query_id=query_id), join
            )
        for origin, ids in _consumers_by_origin(resource).items():
            reply = CallbackReply(join.add())  # answered on the answering thread
            try:
                DIRECTORY.lookup(origin).tell(
                    StatusNotice(ids, update.status, update.message, update.source, event, reply)
                )
            except RrError as exc:
                reply.set_error(exc)
        join.seal()

    def _run_status(
        self, callback: StatusCallback, query: Query, update: StatusUpdate, join: SharedJoin
    ) -> None:
        """Run a status callback on a worker thread; its part of `join` is done after it."""
        done = join.add()

        def run() -> None:
            try:
                callback(query, update)
            except Exception:
                logger.exception("status callback for %s raised", query.id)
            finally:
                done()

        try:
            self.workers.submit(run)
        except RuntimeError:  # no thread could start: skip the callback, keep serving
            logger.exception("no worker thread for the status callback of %s", query.id)
            done()

    def _on_status_notice(self, message: StatusNotice) -> None:
        """Consumer side: run the client callbacks, climb to the dependent resources."""
        if self._parked(message):
            return
        join = SharedJoin(lambda: message.reply.set_result(None))
        for query_id in message.query_ids:
            record = self.catalog.clients.get(query_id)
            if record is None:
                continue
            update = StatusUpdate(query_id, message.status, message.message, message.source)
            callback = self.status_callbacks.get(query_id)
            if callback is not None:
                self._run_status(callback, record.query, update, join)
            if record.parent is not None and record.parent in self.catalog.resources:
                parent = self.catalog.resources[record.parent]
                self._notify(parent, update, message.event, None, join.add())
        join.seal()

    def _on_fetch(self, message: Fetch) -> None:
        if message.server not in self.servers:
            message.reply.set_error(
                UnknownServerError(f"no resource server '{self.name}/{message.server}'")
            )
            return
        message.reply.set_result(
            [
                query
                for query in self.catalog.server_queries(message.server, self.name)
                if query.origin_rr == message.origin_rr
            ]
        )

    def _on_revoke(self, message: Revoke) -> None:
        if self._parked(message):
            return
        for query_id in message.query_ids:
            if query_id in self.catalog.clients:
                self.catalog.remove_client(query_id)
                self.status_callbacks.pop(query_id, None)
        self._commit()

    def _on_response_updated(self, message: ResponseUpdated) -> None:
        if self._parked(message):
            return
        for query_id in message.query_ids:
            self.catalog.client_loaded(query_id, message.response)
        self._commit()
        message.reply.set_result(None)

    def _parked(self, notice: StatusNotice | Revoke | ResponseUpdated) -> bool:
        """Hold `notice` if the answer to one of its queries is still on its way.

        It is handled again (`_answered`) once that answer or the call's failure was.
        """
        for query_id in notice.query_ids:
            if query_id in self.due:
                self.parked_notices.setdefault(query_id, []).append(notice)
                return True
        return False

    def _answered(self, query_id: str, attempt: OneShotFuture[Any]) -> None:
        """`attempt`'s answer or failure was handled: handle what waited for it."""
        if not self.due.settle(query_id, attempt):
            return
        waiting = self.parked_notices.pop(query_id, [])
        while waiting:
            notice = waiting.pop(0)
            try:
                self.on_receive(notice)
            except BaseException:  # the actor dies: `_fail_parked` answers the rest
                if waiting:
                    self.parked_notices[query_id] = waiting
                raise

    # -- consumer side ----------------------------------------------------------------

    def _client(self, target_rr: str, server: str) -> pykka.ActorRef[ClientActor]:
        key = (target_rr, server)
        client = self.clients.get(key)
        if client is None:
            client = ClientActor.start(self.actor_ref, self.name, target_rr, server)
            self.clients[key] = client
        return client

    def _on_pending(self, message: _Pending) -> None:
        self.pending_attempts[message.record.query.id] = message.attempt
        if message.record.query.id not in self.catalog.clients:  # (else a retry of one it holds)
            record = message.record
            if self._owner_gone(record):  # a late sub-call: kept as a call of its own, so a
                record = ClientRecord(record.query, None)  # crash meanwhile gives it back
            self.catalog.add_client(record)
            self._commit()
        message.reply.set_result(None)  # durable: the Load may leave now (rule 16)

    def _on_client_loaded(self, message: _ClientLoaded) -> None:
        try:
            self._record_answer(message)
        finally:  # (also when recording failed: what waits for it must not wait for good)
            self._answered(message.record.query.id, message.attempt)

    def _record_answer(self, message: _ClientLoaded) -> None:
        query = message.record.query
        ours = self.pending_attempts.get(query.id) is message.attempt  # (not a same-id retry's)
        if ours:
            del self.pending_attempts[query.id]
        # A durable call's answer is kept only while its caller still waits: the actor takes
        # the caller's future before it commits, so a caller whose time runs out meanwhile
        # reads the answer instead. A caller that took it first withdrew the call (told the
        # provider an Abandon after its Load): its answer is not kept.
        withdrawn = message.answer_after_commit and not message.attempt.reserve()
        try:
            if withdrawn or (self.stopping and message.record.parent is None):
                self._drop_answer(message, withdrawn=withdrawn, ours=ours)
                return
            if self._owner_gone(message.record):
                self._give_back_late_dependency(message)
                return
            if message.answer_after_commit and self._unstorable(message):
                return
            if query.id in self.catalog.clients:  # written as pending before the load was sent
                self.catalog.client_loaded(query.id, query.response)
            else:
                self.catalog.add_client(message.record)
            if message.on_status is not None:
                self.status_callbacks[query.id] = message.on_status
            self._commit()
            if message.answer_after_commit:
                message.attempt.fulfil(query.response)
        except BaseException as exc:  # a reserved future must be settled on every path
            if message.answer_after_commit and not withdrawn and not message.attempt.done:
                message.attempt.fulfil(exc_info=(type(exc), exc, exc.__traceback__))
            raise

    def _drop_answer(self, message: _ClientLoaded, *, withdrawn: bool, ours: bool) -> None:
        """An answer not kept: its caller withdrew the call, or this registrar stops.

        `ours`: `message` is the attempt that wrote the pending record (not a same-id retry).
        """
        query = message.record.query
        if not withdrawn or self.stopping:  # give the id back (when stopping, the Abandon
            with contextlib.suppress(RrError):  # op_stop sent may have preceded the Load)
                DIRECTORY.lookup(query.serving_rr).tell(Abandon(query.id, self.name))
        record = self.catalog.clients.get(query.id)
        if withdrawn and not self.stopping:
            record = None  # its caller's _CallFailed removes it, after its Abandon
        if ours and record is not None and not record.loaded:  # its pending record
            self.catalog.remove_client(query.id)
            self._commit()
        if message.answer_after_commit and not withdrawn:
            error = RegistrarStoppedError(f"registrar {self.name!r} stopped during the call")
            message.attempt.fulfil(exc_info=(type(error), error, None))

    def _unstorable(self, message: _ClientLoaded) -> bool:
        """A durable call's response this catalog cannot store: give it back, fail the call.

        (A caller that records its own answer checks the response itself, see `call`.)
        """
        query = message.record.query
        try:
            _check_picklable(query.response, f"the response of '{query.serving_rr}/{query.server}'")
        except ConfigError as exc:
            with contextlib.suppress(RrError):
                DIRECTORY.lookup(query.serving_rr).tell(Abandon(query.id, self.name))
            if query.id in self.catalog.clients and not self.catalog.clients[query.id].loaded:
                self.catalog.remove_client(query.id)  # its pending record
                self._commit()
            message.attempt.fulfil(exc_info=(type(exc), exc, None))
            return True
        return False

    def _owner_gone(self, record: ClientRecord) -> bool:
        """Whether `record` is a dependency of a resource that failed or is unloading.

        Its load returned (or raised) while a sub-call it started was still in flight:
        the resource's dependencies were released already, so this one would never be.
        """
        if record.parent is None:
            return False
        owner = self.catalog.resources.get(record.parent)
        return owner is None or owner.state is ResourceState.UNLOADING

    def _give_back_late_dependency(self, message: _ClientLoaded) -> None:
        """Release a dependency that arrived after its resource's own release (rule 4).

        The call itself succeeded (its caller has the response, or gets it now), but the
        id is given back at once: nothing could ever release it otherwise.
        """
        query = message.record.query
        logger.warning(
            "registrar %s: call %s to '%s/%s' returned after the load that made it had "
            "failed or was unloading; releasing it",
            self.name,
            query.id,
            query.serving_rr,
            query.server,
        )
        with contextlib.suppress(RrError):
            DIRECTORY.lookup(query.serving_rr).tell(Abandon(query.id, self.name))
        if query.id in self.catalog.clients:  # a durable consumer's pending record
            self.catalog.remove_client(query.id)
            self._commit()
        if message.answer_after_commit:  # (reserved by `_record_answer`)
            message.attempt.fulfil(query.response)

    def _on_call_failed(self, message: _CallFailed) -> None:
        current = self.pending_attempts.get(message.query_id)
        if current is message.attempt:
            del self.pending_attempts[message.query_id]
        record = self.catalog.clients.get(message.query_id)
        try:
            if current is not None and current is not message.attempt:
                pass  # a stale failure of an earlier attempt: the record is a retry's
            elif record is not None and record.loaded and not message.withdrawn:
                pass  # a failed retry of an id this registrar holds: it still holds it
            elif record is not None:
                self.catalog.remove_client(message.query_id)
                self.status_callbacks.pop(message.query_id, None)
                self._commit()
        finally:
            self._answered(message.query_id, message.attempt)

    def _on_request(self, message: _Request) -> None:
        reply = _OpenReply(message.reply, self.open_requests)
        try:
            message.op(self, reply)
        except RrError as exc:
            reply.set_error(exc)

    def _on_crash(self, _: _Crash) -> None:
        raise RuntimeError(f"registrar {self.name!r} was made to crash (rr_actors.testing)")

    _handlers: ClassVar[dict[type, Callable[[RegistrarActor, Any], None]]] = {
        Answer: _on_answer,
        Load: _on_load,
        Unload: _on_unload,
        Abandon: _on_abandon,
        Fetch: _on_fetch,
        StatusNotice: _on_status_notice,
        Revoke: _on_revoke,
        ResponseUpdated: _on_response_updated,
        ConsumerDown: _on_consumer_down,
        _Pending: _on_pending,
        _ClientLoaded: _on_client_loaded,
        _CallFailed: _on_call_failed,
        _Request: _on_request,
        _Flush: _on_flush,
        _Crash: _on_crash,
    }

    # -- operations the handle asks for (run in the actor thread) ---------------------

    def op_register(
        self,
        name: str,
        load: LoadCallback,
        unload: UnloadCallback,
        on_status: StatusCallback | None,
        reply: Reply,
    ) -> None:
        if name in self.servers:
            raise DuplicateNameError(f"resource server '{self.name}/{name}' already exists")
        ref = ServerActor.start(
            self.name,
            name,
            load,
            unload,
            self.workers,
            persisted=self.saver.store is not None,
        )
        self.servers[name] = _Server(name, ref, on_status)
        for run_unload in self.parked_unloads.pop(name, ()):
            run_unload()
        reply.set_result(None)

    def op_ready(self, reply: Reply) -> None:
        """Setup is done: serve the loads that waited for it (unknown servers now fail)."""
        self.setting_up = False
        self.setup_done = True
        held, self.held_loads = self.held_loads, []
        for load in held:
            self._on_load(load)
        for server, unloads in list(self.parked_unloads.items()):
            if server not in self.servers:  # setup did not bring it back: release anyway
                logger.warning(
                    "registrar %s: server %r was not registered by setup; its restored "
                    "resources are released without their unload callback",
                    self.name,
                    server,
                )
                del self.parked_unloads[server]
                for run_unload in unloads:
                    run_unload()
        reply.set_result(None)

    def op_unregister(self, name: str, timeout: float, reply: Reply) -> None:
        server = self._server(name)
        server.closing = True
        resources = [r for r in self.catalog.resources_of(name) if r.state is ResourceState.LOADED]

        def finish() -> None:
            if not self.catalog.resources_of(name) and name in self.servers:
                del self.servers[name]
                server.ref.stop(block=False)
            reply.set_result(None)

        join = Join(finish)
        for resource in resources:
            self._close_resource(resource, join.add())
        join.seal()

    def _close_resource(self, resource: Resource, then: Callable[[], None]) -> None:
        """Send FATAL to a resource's consumers, revoke their ids, unload it."""
        query_id = next(iter(resource.consumers))
        update = StatusUpdate(
            query_id,
            Status.FATAL,
            "resource server was unregistered",
            f"{self.name}/{resource.server}",
        )

        def revoke_and_unload() -> None:
            done = self.tokens.reply(self.actor_ref, lambda *_: then())
            if resource.state is not ResourceState.LOADED:  # its consumers left meanwhile
                if resource.id in self.unload_waiters:
                    self.unload_waiters[resource.id].append(done)
                else:
                    done.set_result(None)
                return
            for origin, ids in _consumers_by_origin(resource).items():
                with contextlib.suppress(RrError):
                    DIRECTORY.lookup(origin).tell(Revoke(ids))
            for qid in list(resource.consumers):
                self.catalog.release(qid)
            self._unload_resource(resource, done)

        # the FATAL's acknowledgements may complete on any thread: come back to this one
        back = self.tokens.reply(self.actor_ref, lambda *_: revoke_and_unload())
        self._notify(resource, update, str(uuid.uuid4()), query_id, lambda: back.set_result(None))

    def op_send_status(self, query_id: str, status: Status, message: str, reply: Reply) -> None:
        resource = self.catalog.resource_of(query_id)
        update = StatusUpdate(query_id, status, message, f"{self.name}/{resource.server}")
        self._notify(resource, update, str(uuid.uuid4()), query_id, lambda: reply.set_result(None))

    def op_unload(self, query_id: str, reply: Reply) -> None:
        record = self.catalog.clients.get(query_id)
        if record is None or not record.loaded:
            raise UnknownQueryError(f"unknown or released query id {query_id!r}")
        query = record.query

        def answered(_: Any, error: BaseException | None) -> None:
            if error is not None and not isinstance(error, UnknownQueryError):
                reply.set_error(error)  # e.g. the provider is unavailable: keep the record
                return
            if error is not None:
                logger.warning("provider %s no longer knew %s", query.serving_rr, query.id)
            if query_id in self.catalog.clients:
                self.catalog.remove_client(query_id)
                self.status_callbacks.pop(query_id, None)
                self._commit()
            reply.set_result(None)

        self._send(query.serving_rr, lambda r: Unload(query_id, self.name, r), answered)

    def op_update_response(self, query_id: str, response: Any, reply: Reply) -> None:
        resource = self.catalog.resource_of(query_id)
        self.catalog.set_response(resource.id, response)
        self._commit()
        join = Join(lambda: reply.set_result(None))
        for origin, ids in _consumers_by_origin(resource).items():
            self._send(
                origin,
                functools.partial(ResponseUpdated, ids, response),
                functools.partial(
                    _log_failure, f"telling {origin} about a new response", join.add()
                ),
            )
        join.seal()

    def op_set_status_callback(self, query_id: str, callback: StatusCallback, reply: Reply) -> None:
        if query_id not in self.catalog.clients:
            raise UnknownQueryError(f"unknown or released query id {query_id!r}")
        self.status_callbacks[query_id] = callback
        reply.set_result(None)

    def op_server_queries(self, server: str, reply: Reply) -> None:
        self._server(server)
        reply.set_result(self.catalog.server_queries(server, self.name))

    def op_client_queries(self, reply: Reply) -> None:
        reply.set_result([r.query for r in self.catalog.clients.values() if r.loaded])

    def op_client(self, target_rr: str, server: str, reply: Reply) -> None:
        reply.set_result(self._client(target_rr, server))

    def op_save(self, reply: Reply) -> None:
        self._commit()
        self.saver.flush()
        reply.set_result(None)

    def op_snapshot(self, reply: Reply) -> None:
        try:
            self.catalog.check_invariants()
        except AssertionError as exc:  # the test's error, not the registrar's death
            reply.set_error(exc)
            return
        reply.set_result(
            CatalogView(
                resources=tuple(
                    dataclasses.replace(r, consumers=dict(r.consumers))
                    for r in self.catalog.read_all().values()
                ),
                clients=tuple(dataclasses.replace(c) for c in self.catalog.clients.values()),
            )
        )

    def op_stop(self, reply: Reply) -> None:
        """Unload what this registrar holds as a consumer (newest first), then stop (rule 12)."""
        self.stopping = True
        stopped = RegistrarStoppedError(f"registrar {self.name!r} stopped during the call")
        for record in list(self.catalog.clients.values()):
            attempt = self.pending_attempts.pop(record.query.id, None)
            if record.parent is None and not record.loaded and attempt is not None:
                # a durable call in flight: give it up (the Abandon first, then the record,
                # so a crash in between leaves nothing at the provider), tell its caller
                with contextlib.suppress(RrError):
                    DIRECTORY.lookup(record.query.serving_rr).tell(
                        Abandon(record.query.id, self.name)
                    )
                self._on_call_failed(_CallFailed(record.query.id, attempt, withdrawn=True))
                FutureReply(attempt).set_error(stopped)
        tops = [r for r in reversed(self.catalog.clients.values()) if r.parent is None and r.loaded]

        def next_one() -> None:
            if tops:
                self._release_client(tops.pop(0), next_one)
                return
            self._commit()
            if self.flush_timer is not None:
                self.flush_timer.cancel()
            self.saver.close(erase=self.config.erase_on_destruct)
            DIRECTORY.unregister(self.peer, "stopped")
            self._stop_children()
            reply.set_result(None)
            self._fail_waiting(RegistrarStoppedError(f"registrar {self.name!r} was stopped"))
            self._stop()  # at once: what arrives from now on goes to `on_late`

        next_one()

    def _server(self, name: str) -> _Server:
        server = self.servers.get(name)
        if server is None or server.closing:
            raise UnknownServerError(f"no resource server '{self.name}/{name}'")
        return server


@dataclasses.dataclass(frozen=True)
class CatalogView:
    """An immutable copy of a registrar's catalog rows (for inspection and tests)."""

    resources: tuple[Resource, ...]
    clients: tuple[ClientRecord, ...]


# -- the handle --------------------------------------------------------------------------


class RegistrarFacts:
    """What a registrar handle knows without asking its actor (shared by every handle)."""

    _config: RegistrarConfig
    _restored: bool
    _in_doubt: tuple[Query, ...]

    @property
    def name(self) -> str:
        """The registrar's name."""
        return self._config.name

    @property
    def config(self) -> RegistrarConfig:
        """The configuration it was started with."""
        return self._config

    @property
    def restored(self) -> bool:
        """Whether the catalog was restored from an existing backup at start."""
        return self._restored

    @property
    def in_doubt(self) -> tuple[Query, ...]:
        """Loads (or unloads) a crash cut short in the last run, found at restore (rule 16).

        Each is a `Query` whose `id` is the resource id, whose `request` is what the load
        was for and whose `response` is `None` for a load that never finished. They are
        no longer in the catalog and their dependencies were released; the manager
        decides whether something its callback started must be cleaned up.
        """
        return self._in_doubt


class ResourceRegistrar(RegistrarFacts):
    """A manager's resource registrar (thesis 4.3.1, `RrBase`).

    Start one with [`ResourceRegistrar.start`][rr_actors.ResourceRegistrar.start]. Its
    methods may be called from any thread, including from inside callbacks; each sends a
    message to the registrar actor and waits for the answer at most `timeout` seconds
    (default: the config's `call_timeout`).
    """

    def __init__(
        self,
        ref: pykka.ActorRef[RegistrarActor],
        config: RegistrarConfig,
        *,
        restored: bool,
        in_doubt: tuple[Query, ...],
    ) -> None:
        self._ref = ref
        self._config = config
        self._restored = restored
        self._in_doubt = in_doubt
        self._clients: dict[tuple[str, str], pykka.ActorRef[ClientActor]] = {}
        self._died = threading.Event()  # set when a crash of the actor was fully handled
        self._ended = threading.Event()  # set when the actor handed on its last message
        self._due = _DueAnswers()  # shared with the actor (see `start`)
        self._commit_first = config.save_on_modify and config.backup_path is not None

    @classmethod
    def start(
        cls,
        config: RegistrarConfig | str,
        *,
        setup: Callable[[ResourceRegistrar], object] | None = None,
    ) -> ResourceRegistrar:
        """Start a registrar, restoring its catalog first if its backup exists.

        Args:
            config: a `RegistrarConfig`, or just a name (all other fields default).
            setup: `setup(registrar)`, run on the calling thread after the catalog was
                restored and before the registrar serves other registrars: loads that
                arrive meanwhile for servers it has not registered yet wait for it (a
                manager's start-up, DESIGN "Public API"). If it raises, the registrar is
                stopped and the error propagates.

        Returns:
            The handle of the running registrar.

        Raises:
            DuplicateNameError: a registrar with this name is already running here.
            CatalogCorruptError: the backup exists but cannot be read (it is left as is).
            ConfigError: the configuration, or its backup path, is invalid.
        """
        if isinstance(config, str):
            config = RegistrarConfig(name=config)
        elif not isinstance(config, RegistrarConfig):
            raise ConfigError(f"config must be a RegistrarConfig or a name, got {config!r}")
        peer = LocalPeer(config.name, None)
        DIRECTORY.register(peer)
        store = None
        try:
            store = open_store(config)
            with gc_paused():  # building many rows allocates no cycles: skip the rescans
                restored = store.restore() if store is not None else None
                catalog = (
                    Catalog.restore(restored.resources, restored.clients, restored.unread)
                    if restored is not None
                    else None
                )
            if catalog is None:
                catalog = Catalog(track_changes=store is not None)
            saver = Saver(store, config)
            in_doubt = tuple(
                Query(r.id, r.server, config.name, config.name, r.request, r.response)
                for r in catalog.resources.values()
                if r.state is not ResourceState.LOADED
            )
            died, ended, due = threading.Event(), threading.Event(), _DueAnswers()
            ref = RegistrarActor.start(
                config, catalog, saver, peer, died, due, ended, setting_up=setup is not None
            )
        except BaseException:
            if store is not None:
                store.close(erase=False)
            DIRECTORY.unregister(peer, "stopped")
            raise
        handle = cls(ref, config, restored=restored is not None, in_doubt=in_doubt)
        handle._died = died
        handle._ended = ended
        handle._due = due
        if setup is not None:
            try:
                setup(handle)
            except BaseException:
                handle.stop()
                raise
            handle._ask(lambda actor, reply: actor.op_ready(reply), None, "ready")
        return handle

    # -- properties -------------------------------------------------------------------

    def is_alive(self) -> bool:
        """Whether the registrar actor is running."""
        return self._ref.is_alive()

    # -- servers ----------------------------------------------------------------------

    def register_server(
        self,
        name: str,
        *,
        load: LoadCallback,
        unload: UnloadCallback,
        on_status: StatusCallback | None = None,
        timeout: float | None = None,
    ) -> None:
        """Register a resource server `"<registrar>/<name>"`.

        Args:
            name: server name, unique on this registrar.
            load: `load(request) -> response`; runs on a worker thread of this process.
            unload: `unload(request, response) -> None`; runs on a worker thread, after the
                resource's dependencies were released.
            on_status: `on_status(query, update)`, run once on a worker thread when a status
                about one of this server's resources is sent or passes through.
            timeout: seconds to wait for the registrar.

        Raises:
            ConfigError: a callback is not callable or the name is invalid.
            DuplicateNameError: a server with this name exists on this registrar.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        if not isinstance(name, str) or not name or "/" in name:
            raise ConfigError(f"server name must be a non-empty string without '/', got {name!r}")
        for arg, fn in (("load", load), ("unload", unload), ("on_status", on_status)):
            if fn is not None and not callable(fn):
                raise ConfigError(f"{arg} must be callable, got {fn!r}")
        self._ask(
            lambda actor, reply: actor.op_register(name, load, unload, on_status, reply),
            timeout,
            f"register_server({name!r})",
        )

    def unregister_server(self, name: str, *, timeout: float | None = None) -> None:
        """Remove a server: send `FATAL` to its consumers and unload all it serves (rule 12).

        Raises:
            UnknownServerError: no such server here.
            CallTimeoutError: not finished within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        limit = self._timeout(timeout)
        self._ask(
            lambda actor, reply: actor.op_unregister(name, limit, reply),
            limit,
            f"unregister_server({name!r})",
        )

    # -- consumer API -----------------------------------------------------------------

    def call(
        self,
        target_rr: str,
        server: str,
        request: Any,
        *,
        on_status: StatusCallback | None = None,
        timeout: float | None = None,
        query_id: str | None = None,
    ) -> Query:
        """Ask `target_rr/server` for the resource `request` describes (rules 1-6, 17).

        The provider runs `load(request)` unless an equal (`==`) request is loaded or
        loading there; either way this call becomes one more consumer with its own id.
        Called from inside a `load` callback of this registrar, the query is recorded as
        a dependency of the resource being loaded.

        Args:
            target_rr: name of the provider registrar (this one's own name works too).
            server: server name on it.
            request: any value; equal requests mean the same resource. Between
                registrars of one process it is passed, not copied (as pykka passes
                messages): do not change it after the call, or the provider's catalog
                holds the changed value and may no longer match equal requests to it.
            on_status: client status callback `on_status(query, update)`, run on a worker
                thread of this registrar's process.
            timeout: seconds to wait for the answer.
            query_id: the id to use (default: a fresh UUID4). Retrying with the same id is
                idempotent: it never loads twice nor adds a second consumer.

        Returns:
            The `Query`, with the provider's `response` (in one process, the very object
            `load` returned, shared by every consumer: treat it as read-only).

        Raises:
            ResourceLoadError: `load` raised here or further down; `stack` says where.
            DependencyCycleError: the load would wait for itself further up its chain.
            UnknownServerError: no such registrar or server.
            CallTimeoutError: no answer in time; the query id is released if it loads later.
            RegistrarUnavailableError: the provider died (it may have executed the load).
            RegistrarStoppedError: this registrar or the provider was stopped.
            ConfigError: `on_status` is not callable; or the request, or the response,
                cannot be pickled where it must be: across processes, or into this
                registrar's backup (its client record); the provider then holds nothing.
        """
        if on_status is not None and not callable(on_status):
            raise ConfigError(f"on_status must be callable, got {on_status!r}")
        limit = self._timeout(timeout)
        deadline = time.monotonic() + limit
        context = _LOADING.get()
        parent: str | None = None
        chain: tuple[str, ...] = ()
        if context is not None:
            chain = context.chain
            if context.registrar == self.name:
                parent = context.resource_id
        if self._config.backup_path is not None:  # its client record is stored
            _check_picklable(request, f"the request of a call to '{target_rr}/{server}'")
        query = Query(query_id or str(uuid.uuid4()), server, target_rr, self.name, request)
        self._client(target_rr, server, limit)  # the client endpoint exists from the first call
        future: OneShotFuture[Any] = OneShotFuture()
        record = ClientRecord(query, parent)
        reply = _ClientReply(self._ref, record, on_status, future, commit_first=self._commit_first)
        answered = query
        try:
            self._due.expect(query.id, future)  # a notice that overtakes the answer waits
            load = Load(query.id, server, request, self.name, chain, reply)
            sent = self._send(load, reply, deadline)
            # Settled by the answer (see _ClientReply), or claimed here when the time is up.
            left = max(0.0, deadline - time.monotonic())
            answer_came = (sent and future.wait(left)) or not future.claim()
            if answer_came:
                future.wait()  # whoever holds the claim is writing the answer: read it whole
            if answer_came and not future.failed:
                answered = query.with_response(future.get())
                if self._config.backup_path is not None and not self._commit_first:
                    _check_picklable(  # stored with its record at the next flush
                        answered.response, f"the response of '{target_rr}/{server}'"
                    )
                if not self._commit_first:  # a durable one the registrar recorded already
                    self._ref.tell(
                        _ClientLoaded(
                            ClientRecord(answered, parent, loaded=True), on_status, future
                        )
                    )
        except pykka.ActorDeadError:  # this registrar stopped meanwhile: give the id back
            with contextlib.suppress(RrError):
                DIRECTORY.lookup(target_rr).tell(Abandon(query.id, self.name))
            raise DIRECTORY.gone_error(self.name) from None
        except BaseException:  # the caller stops waiting (KeyboardInterrupt, ...)
            future.claim()
            self._withdraw(query, future)
            raise
        if not answer_came:
            self._withdraw(query, future)
            raise CallTimeoutError(f"call to '{target_rr}/{server}' timed out after {limit:g} s")
        if future.failed:
            future.get()  # raises what the call failed with
        return answered

    def _send(self, load: Load, reply: _ClientReply, deadline: float) -> bool:
        """Send a call's `load` from the caller's thread; whether it left before `deadline`.

        Along the client's route rather than through the client's mailbox: one thread
        hand-off less (a dedup hit went from 3.1x to 2.0x a raw pykka ask); mailbox order
        still holds, a later withdrawal reaches its actors after this. A durable call's
        record is committed as pending first (rule 16), so a crash of this process after
        the load left still knows the call; a record that cannot be written raises here.
        """
        if self._commit_first:
            committed = FutureReply()
            self._ref.tell(_Pending(reply.record, reply.future, committed))
            if not committed.future.wait(max(0.0, deadline - time.monotonic())):
                return False
            committed.future.get()
            if reply.future.done:  # failed meanwhile (this registrar stops): nothing to send
                return True
        try:
            DIRECTORY.lookup(reply.record.query.serving_rr).tell(load)
        except RrError as exc:
            reply.set_error(exc)
        return True

    def _withdraw(self, query: Query, future: OneShotFuture[Any]) -> None:
        """Take back a call whose caller stopped waiting: leave nothing behind (rule 17).

        The caller claimed `future`, so an answer that comes later is dropped (or, for a
        durable call, not kept). Told from the caller's thread, like the `Load`: the
        provider sees the `Abandon` after the `Load` and before any retry this caller makes
        with the same id. Not for a call that failed: its provider may hold a committed id
        that a retry with the same id must find (`Supervisor.call_with_retry`).
        """
        with contextlib.suppress(RrError):  # a provider that is gone holds nothing
            DIRECTORY.lookup(query.serving_rr).tell(Abandon(query.id, self.name))
        with contextlib.suppress(pykka.ActorDeadError):  # after: a crash in between keeps
            self._ref.tell(_CallFailed(query.id, future, withdrawn=True))  # the record

    def unload(self, query_id: str, *, timeout: float | None = None) -> None:
        """Release one consumer id obtained from `call` (rules 7-8).

        The provider's `unload` callback runs when the last consumer id of the resource is
        released, after that resource's own dependencies were released; this returns
        when that is done.

        Raises:
            UnknownQueryError: the id is unknown here or already released (nothing changes).
            CallTimeoutError: not finished within `timeout` seconds.
            RegistrarUnavailableError: the provider died; the id is kept, retry later.
            RegistrarStoppedError: this registrar was stopped.
        """
        self._ask(
            lambda actor, reply: actor.op_unload(query_id, reply), timeout, f"unload({query_id!r})"
        )

    def send_status(
        self, query_id: str, status: Status, message: str = "", *, timeout: float | None = None
    ) -> None:
        """Tell every consumer of the resource behind `query_id` about its status (rule 9).

        This server's `on_status` runs once; each consumer's status callback runs with its
        own query id; the status climbs every dependency path to the top consumers.
        Returns once every callback on the way has run.

        Args:
            query_id: any consumer id of a resource this registrar serves.
            status: the status code.
            message: free text.
            timeout: seconds to wait for delivery along the whole path.

        Raises:
            UnknownQueryError: `query_id` is not a consumer id of a resource served here.
            CallTimeoutError: not delivered everywhere within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        if not isinstance(status, Status):
            raise ConfigError(f"status must be an rr_actors.Status, got {status!r}")
        self._ask(
            lambda actor, reply: actor.op_send_status(query_id, status, message, reply),
            timeout,
            f"send_status({query_id!r})",
        )

    def server_queries(self, server: str, *, timeout: float | None = None) -> list[Query]:
        """Every consumer query of this registrar's `server`, each id once (rule 10).

        Raises:
            UnknownServerError: no such server here.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        result: list[Query] = self._ask(
            lambda actor, reply: actor.op_server_queries(server, reply),
            timeout,
            f"server_queries({server!r})",
        )
        return result

    def fetch_queries(
        self, target_rr: str, server: str, *, timeout: float | None = None
    ) -> list[Query]:
        """The queries this registrar holds at `target_rr/server`, as the provider has them.

        Used after a restart to learn what this registrar had asked for (thesis 4.2.5).

        Raises:
            UnknownServerError: no such registrar or server.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarUnavailableError: the provider died.
        """
        limit = self._timeout(timeout)
        reply = FutureReply()
        self._client(target_rr, server, limit).tell(_FetchVia(server, reply))
        result: list[Query] = wait(reply.future, limit, f"fetch_queries({target_rr!r})")
        return result

    def client_queries(self, *, timeout: float | None = None) -> list[Query]:
        """Every query this registrar holds at servers (its own included), oldest first.

        Raises:
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        result: list[Query] = self._ask(
            lambda actor, reply: actor.op_client_queries(reply), timeout, "client_queries()"
        )
        return result

    def set_status_callback(
        self, query_id: str, callback: StatusCallback, *, timeout: float | None = None
    ) -> None:
        """Attach (or replace) the client status callback of a query this registrar holds.

        Status callbacks are code, so they are not in the backup: re-attach them after a
        restart (rule 11).

        Raises:
            UnknownQueryError: this registrar holds no such query.
            ConfigError: `callback` is not callable.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        if not callable(callback):
            raise ConfigError(f"callback must be callable, got {callback!r}")
        self._ask(
            lambda actor, reply: actor.op_set_status_callback(query_id, callback, reply),
            timeout,
            f"set_status_callback({query_id!r})",
        )

    def update_response(
        self, query_id: str, response: Any, *, timeout: float | None = None
    ) -> None:
        """Replace the stored response of the resource behind `query_id` (asynchronous loads).

        Like TeMoto's catalog response update (thesis 4.3.2). Returns once every
        consumer's client record holds the new response too (a consumer that cannot be
        reached is logged and skipped).

        Args:
            query_id: any consumer id of a resource this registrar serves.
            response: the new response (it must pickle when the catalog has a backup).
            timeout: seconds to wait for the update to reach every consumer.

        Raises:
            UnknownQueryError: `query_id` is not a consumer id of a resource served here.
            CallTimeoutError: not delivered within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        self._ask(
            lambda actor, reply: actor.op_update_response(query_id, response, reply),
            timeout,
            f"update_response({query_id!r})",
        )

    def save_catalog(self, *, timeout: float | None = None) -> None:
        """Write every pending change of the catalog to the backup now (no-op without one).

        Raises:
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        self._ask(lambda actor, reply: actor.op_save(reply), timeout, "save_catalog()")

    def stop(self, *, timeout: float | None = None) -> None:
        """Stop the registrar (rule 12).

        Unloads everything it holds as a consumer (newest first), then stops its servers
        and clients. What its servers serve stays in the catalog for a restart. With
        `erase_on_destruct` the backup is removed. Stopping a stopped registrar is a no-op.

        Raises:
            CallTimeoutError: not finished within `timeout` seconds.
            RegistrarUnavailableError: the registrar died while it stopped.
        """
        if not self._ref.is_alive():
            return
        limit = self._timeout(timeout)
        deadline = time.monotonic() + limit
        try:
            self._ask(lambda actor, reply: actor.op_stop(reply), limit, "stop()")
        except RegistrarStoppedError:
            return
        # op_stop ended the actor; what reached its mailbox meanwhile (an answer to give
        # back, a notice to acknowledge) is handled once its thread has handed it on.
        if not self._ended.wait(max(0.0, deadline - time.monotonic())):
            raise CallTimeoutError(f"stop() of {self.name!r} timed out after {limit:g} s")

    def __enter__(self) -> ResourceRegistrar:
        return self

    def __exit__(self, *_: object) -> None:
        self.stop()

    def __repr__(self) -> str:
        state = "running" if self._ref.is_alive() else "stopped"
        return f"<ResourceRegistrar {self.name!r} {state}>"

    # -- plumbing ---------------------------------------------------------------------

    def _timeout(self, timeout: float | None) -> float:
        if timeout is None:
            return self._config.call_timeout
        check_seconds("timeout", timeout)
        return float(timeout)

    def _ask(
        self,
        op: Callable[[RegistrarActor, Reply], None],
        timeout: float | None,
        what: str,
    ) -> Any:
        limit = self._timeout(timeout)
        reply = FutureReply()
        try:
            self._ref.tell(_Request(op, reply))
        except pykka.ActorDeadError:
            raise DIRECTORY.gone_error(self.name) from None
        return wait(reply.future, limit, what)

    def _client(self, target_rr: str, server: str, timeout: float) -> pykka.ActorRef[ClientActor]:
        key = (target_rr, server)
        client = self._clients.get(key)
        if client is None or not client.is_alive():
            client = self._ask(
                lambda actor, reply: actor.op_client(target_rr, server, reply),
                timeout,
                "starting a client",
            )
            self._clients[key] = client
        return client
