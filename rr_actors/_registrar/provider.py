"""The provider side of a registrar actor: load, share, unload (thesis 4.2, rules 1-8).

```
 Load ──► on_load ── equal request loaded? ──yes──► add consumer, answer (a dedup hit)
                 │
                 ├── loading? ──► wait for it (one load per resource, rule 3)
                 └── new ──► start_load ──RunLoad──► server ──► load_done ──► answer waiters
 Unload/Abandon ──► release ── last consumer? ──► unload_resource:
                      release the resource's dependencies (consumer side), then RunUnload
```

A resource belongs to its server; its consumers are query ids (one per call, rule 2).
Callers that wait for a load, and loads parked behind an unload of the same resource,
are this role's state.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import time
import uuid
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rr_actors import events
from rr_actors._catalog import NO_DIGEST, Resource, ResourceState, describe, request_digest
from rr_actors._catalog.digest import requests_equal
from rr_actors._core.directory import DIRECTORY, Reply
from rr_actors._core.replies import Join
from rr_actors._registrar.endpoints import ServerActor
from rr_actors._registrar.loading import MAX_DEPENDENCY_DEPTH, check_picklable
from rr_actors._registrar.matching import Matching, first_equal, prepare
from rr_actors._registrar.messages import (
    Abandon,
    ConsumerDown,
    Fetch,
    Load,
    Reconcile,
    ReconcileAsk,
    ResponseUpdated,
    Revoke,
    RunLoad,
    RunUnload,
    Unload,
)
from rr_actors._registrar.protocol import LoadCallback, UnloadCallback
from rr_actors._registrar.state import Phase, Server, Shared, Waiter
from rr_actors._types import Status, StatusCallback, StatusUpdate
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    DependencyCycleError,
    DuplicateNameError,
    DuplicateQueryIdError,
    RegistrarStoppedError,
    ResourceLoadError,
    RrError,
    UnknownQueryError,
    UnknownServerError,
)

if TYPE_CHECKING:
    from rr_actors._registrar.consumer import Consumer
    from rr_actors._registrar.status import StatusRelay

__all__ = ["Provider", "consumers_by_origin"]

logger = logging.getLogger("rr_actors")


def consumers_by_origin(resource: Resource) -> dict[str, tuple[str, ...]]:
    """A resource's consumer ids, grouped by the registrar that holds them."""
    by_origin: dict[str, list[str]] = {}
    for query_id, origin in resource.consumers.items():
        by_origin.setdefault(origin, []).append(query_id)
    return {origin: tuple(ids) for origin, ids in by_origin.items()}


def _log_failure(what: str, then: Callable[[], None], _: Any, error: BaseException | None) -> None:
    """A continuation that logs a failed answer, then runs `then()`."""
    if error is not None:
        logger.warning("%s failed: %s", what, error)
    then()


class Provider:
    """Serves this registrar's resources to consumers (its own calls included).

    Attributes:
        loads: resource id -> the callers waiting for its load.
        loading_ids: a waiting caller's query id -> the resource it waits for.
        abandoned: query ids whose callers gave up while their load ran.
        held_loads: loads for servers `setup` has not registered yet.
        after_unload: resource id -> loads of an equal request, parked until it unloaded.
        load_started: resource id -> when its load started (`time.monotonic()`).
        unload_waiters: resource id -> replies waiting for its unload to finish.
        parked_unloads: server name -> unloads of restored resources waiting for the
            server to be registered again.
        matching: loads whose match user code decides, off the actor thread.
    """

    def __init__(self, shared: Shared, consumer: Consumer, status: StatusRelay) -> None:
        self.s = shared
        self.consumer = consumer
        self.status = status
        self.loads: dict[str, list[Waiter]] = {}
        self.loading_ids: dict[str, str] = {}
        self.abandoned: set[str] = set()
        self.held_loads: list[Load] = []
        self.after_unload: dict[str, list[Load]] = {}
        self.load_started: dict[str, float] = {}
        self.unload_waiters: dict[str, list[Reply]] = {}
        self.parked_unloads: dict[str, list[Callable[[], None]]] = {}
        self.matching = Matching(shared, self.serve)

    # -- load -------------------------------------------------------------------------

    def refusal(self, message: Load) -> RrError | None:
        """Why this registrar cannot take `message` at all, if it cannot."""
        server = self.s.servers.get(message.server)
        if server is None or server.closing:
            return UnknownServerError(f"no resource server '{self.s.name}/{message.server}'")
        if self.s.stopping:
            return RegistrarStoppedError(f"registrar {self.s.name!r} is stopping")
        if len(message.chain) >= MAX_DEPENDENCY_DEPTH:
            return DependencyCycleError(
                f"load chain deeper than {MAX_DEPENDENCY_DEPTH} at '{self.s.name}/"
                f"{message.server}': runaway recursion"
            )
        return None

    def on_load(self, message: Load) -> None:
        if self.s.phase is Phase.SETTING_UP and message.server not in self.s.servers:
            self.held_loads.append(message)  # served once setup has registered its servers
            return
        if self.matching.busy(message.server):  # user code decides a match there now
            self.matching.queue(message)
            return
        self.serve(message)

    def serve(self, message: Load) -> None:
        """Serve a load: find what its query id and its request name, then act (rules 1-3).

        What only user code can decide (a request without a digest: its `__hash__`,
        pickling it, its `__eq__`) runs on a worker (`Matching`), and the load goes on
        from the step that waited for it.
        """
        refusal = self.refusal(message)
        if refusal is not None:
            message.reply.set_error(refusal)
            return
        self.abandoned.discard(message.query_id)  # a retry: its caller is back
        digest = request_digest(message.request)
        if digest is not None:  # a plain value: decided on this thread
            self.identify(message, None, digest)
            return
        pickled = None
        if self.s.saver.store is not None:  # the backup must be able to hold the request
            pickled = f"the request to '{self.s.name}/{message.server}'"

        def prepared(key: Any, error: BaseException | None) -> None:
            if self.resumed(message, error):
                self.identify(message, key, None)

        self.matching.run(
            message,
            "hashing the request",
            functools.partial(prepare, message.request, pickled=pickled),
            prepared,
        )

    def resumed(self, message: Load, error: BaseException | None) -> bool:
        """Back from a worker: whether the load goes on (else its caller was answered)."""
        if error is None:
            error = self.refusal(message)  # (the server may have closed meanwhile)
        if error is not None:
            message.reply.set_error(error)
            return False
        return True

    def identify(self, message: Load, key: Any, digest: int | None) -> None:
        """Check what the load's query id names already: a retry, or an id reused (rule 2).

        `key` is the request's `runtime_key` if it has no digest (else `None`); `digest`
        its digest, if it has one.
        """
        catalog = self.s.catalog
        known: Resource | None = None
        if catalog.has_consumer(message.query_id):  # a retry of an answered call?
            known = catalog.resource_of(message.query_id)
        elif message.query_id in self.loading_ids:  # a retry while its load runs?
            known = catalog.resources[self.loading_ids[message.query_id]]
        else:
            other = self.matching.named(message.query_id)  # (of another server)
            if other is not None and other is not message:
                message.reply.set_error(self.reused(message, other.server))
                return
        if known is None:
            self.look_up(message, key, digest)
        elif known.server != message.server:
            message.reply.set_error(self.reused(message, known.server))
        elif key is None and known.digest not in (None, NO_DIGEST):  # both plain
            self.retried(message, known, key, same=requests_equal(known.request, message.request))
        else:
            candidate = known

            def compared(index: int | None, error: BaseException | None) -> None:
                if self.resumed(message, error):
                    self.retried(message, candidate, key, same=index == 0)

            self.matching.run(
                message,
                "comparing the request with the one its query id was used for",
                functools.partial(first_equal, message.request, [known.request]),
                compared,
            )

    def reused(self, message: Load, server: str) -> DuplicateQueryIdError:
        return DuplicateQueryIdError(
            f"query id {message.query_id!r} was used already for another call (to "
            f"'{self.s.name}/{server}', with another request); an id is for one call and "
            "its retries"
        )

    def retried(self, message: Load, known: Resource, key: Any, *, same: bool) -> None:
        """A load with a query id known here: a retry of that call, or an id reused."""
        if not same:
            message.reply.set_error(self.reused(message, known.server))
        elif self.s.catalog.has_consumer(message.query_id):  # answered: the stored response
            message.reply.set_result(known.response)
        elif message.query_id in self.loading_ids:  # it waits for the load again
            waiter = Waiter(message.query_id, message.origin_rr, message.reply)
            self.loads[self.loading_ids[message.query_id]].append(waiter)
        else:  # (released while its comparison ran: a new call now)
            self.look_up(message, key, request_digest(message.request))

    def look_up(self, message: Load, key: Any, digest: int | None) -> None:
        """Find an equal request on the server (rule 1), user code off this thread."""
        found, undecided = self.s.catalog.lookup(
            message.server, message.request, key, digest=digest
        )
        if not undecided:
            self.matched(message, key, found)
            return

        def compared(index: int | None, error: BaseException | None) -> None:
            if self.resumed(message, error):
                self.matched(message, key, None if index is None else undecided[index])

        self.matching.run(
            message,
            "comparing the request with the ones served",
            functools.partial(first_equal, message.request, [r.request for r in undecided]),
            compared,
        )

    def matched(self, message: Load, key: Any, resource: Resource | None) -> None:
        """Act on what the request matched: share it, wait for it, or load it (rules 1-3, 6)."""
        refusal = self.s.unwritable()  # a full disk: serve what is stored, nothing new
        if refusal is not None:
            message.reply.set_error(refusal)
            return
        if resource is not None and resource.id not in self.s.catalog.resources:
            resource = None  # it left while user code compared: load afresh
        if resource is not None and resource.state is ResourceState.LOADED:  # the hot path
            self.share(resource, message)
            return
        waiter = Waiter(message.query_id, message.origin_rr, message.reply)
        if resource is None:
            self.start_load(self.s.servers[message.server], message, waiter, key)
        elif resource.state is ResourceState.UNLOADING:  # load it afresh once it is gone
            self.after_unload.setdefault(resource.id, []).append(message)
        elif resource.id in message.chain:
            message.reply.set_error(
                DependencyCycleError(
                    f"'{self.s.name}/{message.server}' is asked for "
                    f"{describe(message.request)} while loading it further up the same chain"
                )
            )
        else:  # loading: wait for it (one load per resource, rule 3)
            self.loads[resource.id].append(waiter)
            self.loading_ids[message.query_id] = resource.id

    def share(self, resource: Resource, message: Load) -> None:
        """A dedup hit: one more consumer of a loaded resource (rules 1-2)."""
        catalog = self.s.catalog
        catalog.add_consumer(resource.id, message.query_id, message.origin_rr)
        failed = self.s.commit()
        if failed is not None:  # not durable: the caller holds nothing
            catalog.release(message.query_id)
            self.s.commit()
            message.reply.set_error(failed)
            return
        message.reply.set_result(resource.response)
        if self.s.events.active:
            self.s.events.publish(
                events.ConsumerAdded(self.s.name, resource.id, message.query_id, message.origin_rr)
            )

    def start_load(self, server: Server, message: Load, waiter: Waiter, key: Any) -> None:
        """Load a request not loaded here (`key`: its `runtime_key` if it has no digest)."""
        if self.s.saver.store is not None and key is None:  # (else checked with the key)
            try:  # the backup must be able to hold the request (a plain one: no user code)
                check_picklable(message.request, f"the request to '{self.s.name}/{server.name}'")
            except ConfigError as exc:
                message.reply.set_error(exc)
                return
        rid = str(uuid.uuid4())
        self.s.catalog.begin_load(rid, message.server, message.request, key=key)
        failed = self.s.commit()
        if failed is not None:  # not durable: load nothing (rule 16 needs the record)
            self.s.catalog.remove_resource(rid)
            self.s.commit()
            message.reply.set_error(failed)
            return
        self.loads[rid] = [waiter]
        self.loading_ids[message.query_id] = rid
        self.load_started[rid] = time.monotonic()
        reply = self.s.come_back(lambda value, error: self.load_done(rid, value, error))
        server.ref.tell(RunLoad(rid, message.request, (*message.chain, rid), reply))

    def load_done(self, rid: str, response: Any, error: BaseException | None) -> None:
        catalog = self.s.catalog
        waiters = self.loads.pop(rid)
        for waiter in waiters:
            self.loading_ids.pop(waiter.query_id, None)
        resource = catalog.resources[rid]
        started = self.load_started.pop(rid)
        if self.s.events.active:
            self._published_load(resource, waiters[0].query_id, started, error)
        if error is not None:
            catalog.begin_unload(rid)
            self.s.commit()

            def failed() -> None:
                self.remove_resource(resource)
                for waiter in waiters:
                    self.abandoned.discard(waiter.query_id)
                    waiter.reply.set_error(error)

            self.consumer.release_dependencies(rid, failed)
            return
        catalog.finish_load(rid, response)
        live = self._add_consumers(rid, waiters)
        refusal: RrError | None = self.s.commit()  # not durable: unload it, fail the callers
        server = self.s.servers.get(resource.server)
        if refusal is None and (server is None or server.closing):
            refusal = UnknownServerError(
                f"resource server '{self.s.name}/{resource.server}' closed"
            )
        if refusal is not None:
            for waiter in live:
                if catalog.has_consumer(waiter.query_id):  # a retry may be listed twice
                    catalog.release(waiter.query_id)
                waiter.reply.set_error(refusal)
            live = []
        for waiter in live:
            waiter.reply.set_result(response)
        if not resource.consumers:  # every caller gave up (or the server closed)
            self.unload_resource(resource, None)

    def _add_consumers(self, rid: str, waiters: list[Waiter]) -> list[Waiter]:
        """Make the waiters of a finished load its consumers; the ones still waiting.

        A waiter whose caller gave up meanwhile is answered and holds nothing; a retry
        listed twice is added once.
        """
        catalog = self.s.catalog
        live = []
        for waiter in waiters:
            if waiter.query_id in self.abandoned:  # its caller gave up: answer, hold nothing
                self.abandoned.discard(waiter.query_id)
                waiter.reply.set_error(CallTimeoutError(f"call {waiter.query_id} was given up"))
                continue
            live.append(waiter)
            if not catalog.has_consumer(waiter.query_id):
                catalog.add_consumer(rid, waiter.query_id, waiter.origin_rr)
                if self.s.events.active:
                    self.s.events.publish(
                        events.ConsumerAdded(self.s.name, rid, waiter.query_id, waiter.origin_rr)
                    )
        return live

    def _published_load(
        self, resource: Resource, query_id: str, started: float, error: BaseException | None
    ) -> None:
        """Publish how a load ended (`ResourceLoaded` or `LoadFailed`)."""
        if error is None:
            load_s = time.monotonic() - started
            self.s.events.publish(
                events.ResourceLoaded(self.s.name, resource.server, resource.id, query_id, load_s)
            )
            return
        error_type, message = type(error).__qualname__, str(error)
        if isinstance(error, ResourceLoadError):  # this registrar's frame: what load raised
            error_type, message = error.stack[-1].exc_type, error.stack[-1].message
        self.s.events.publish(
            events.LoadFailed(
                self.s.name, resource.server, resource.id, query_id, error_type, message
            )
        )

    def serve_held(self) -> None:
        """Setup is done: serve the loads that waited for it (unknown servers now fail),
        and release restored resources of servers setup did not bring back."""
        held, self.held_loads = self.held_loads, []
        for load in held:
            self.on_load(load)
        for server, unloads in list(self.parked_unloads.items()):
            if server not in self.s.servers:  # setup did not bring it back: release anyway
                logger.warning(
                    "registrar %s: server %r was not registered by setup; its restored "
                    "resources are released without their unload callback",
                    self.s.name,
                    server,
                )
                del self.parked_unloads[server]
                for run_unload in unloads:
                    run_unload()

    # -- unload -----------------------------------------------------------------------

    def on_unload(self, message: Unload) -> None:
        self.release(message.query_id, message.reply)

    def on_abandon(self, message: Abandon) -> None:
        self.release(message.query_id, None)

    def on_consumer_down(self, message: ConsumerDown) -> None:
        for query_id in self.s.catalog.consumers_from(message.origin_rr):
            self.release(query_id, None)

    def release(self, query_id: str, reply: Reply | None) -> None:
        """Release consumer id `query_id` (rules 7-8); answer `reply` when it is done.

        While a durable registrar's backup cannot be written an `Unload` is refused
        (nothing changes; the consumer keeps the id and may try again); a give-up
        (`reply` is `None`) is carried out and written with the next write that succeeds.
        """
        unwritable = self.s.unwritable() if reply is not None else None
        if unwritable is not None:
            reply.set_error(unwritable)  # type: ignore[union-attr]
            return
        parked = self.unpark(query_id)
        if parked is not None:  # it waited behind an unload or for setup: it never loads
            parked.reply.set_error(CallTimeoutError(f"call {query_id} was given up"))
        # (or user code compares its request now: it is answered as given up when done)
        if parked is not None or self.matching.give_up(query_id):
            if reply is not None:
                reply.set_result(None)
            return
        if query_id in self.loading_ids:  # its caller gave up while it loads
            self.abandoned.add(query_id)
            if reply is not None:
                reply.set_result(None)
            return
        catalog = self.s.catalog
        try:
            resource = catalog.resource_of(query_id)
        except UnknownQueryError as exc:
            if reply is not None:
                reply.set_error(exc)
            return
        origin = resource.consumers[query_id]
        catalog.release(query_id)
        failed = self.s.commit()
        if failed is not None and reply is not None:  # not durable: nothing changes
            catalog.add_consumer(resource.id, query_id, origin)
            self.s.commit()
            reply.set_error(failed)
            return
        if self.s.events.active:
            self.s.events.publish(
                events.ConsumerReleased(self.s.name, resource.id, query_id, origin)
            )
        if resource.consumers or resource.state is not ResourceState.LOADED:
            if reply is not None:
                reply.set_result(None)
            return
        self.unload_resource(resource, reply)

    def unpark(self, query_id: str) -> Load | None:
        """Take the load of `query_id` out of the held, parked or queued loads, if there."""
        for loads in [self.held_loads, *self.after_unload.values()]:
            for load in loads:
                if load.query_id == query_id:
                    loads.remove(load)
                    return load
        return self.matching.take(query_id)

    def unload_resource(self, resource: Resource, reply: Reply | None) -> None:
        """The last consumer left: release the dependencies, then run `unload` (rule 7)."""
        self.s.probe("unload_resource", resource)
        self.s.catalog.begin_unload(resource.id)
        self.s.commit()
        self.unload_waiters[resource.id] = [] if reply is None else [reply]

        def run_unload() -> None:
            server = self.s.servers.get(resource.server)
            if server is None and self.s.servers_settled:  # setup did not bring it back
                unloaded(None, None)
                return
            if server is None:  # restored, and no one has registered the server yet
                self.parked_unloads.setdefault(resource.server, []).append(run_unload)
                return
            done = self.s.come_back(unloaded)
            timeout = self.s.config.unload_timeout
            server.ref.tell(RunUnload(resource.request, resource.response, done, timeout))

        def unloaded(_: Any, error: BaseException | None) -> None:
            overdue = isinstance(error, CallTimeoutError)
            if overdue:  # it hangs: the resource is dropped as failed, its callers told
                logger.error(
                    "registrar %s: %s; resource %s (request %s) is dropped as failed, and "
                    "whatever it still holds is the server's to clean up",
                    self.s.name,
                    error,
                    resource.id,
                    describe(resource.request),
                )
            elif error is not None:
                logger.error(
                    "unload callback of '%s/%s' raised; the resource is released anyway",
                    self.s.name,
                    resource.server,
                    exc_info=error,
                )
            self.remove_resource(resource)
            if self.s.events.active:
                self.s.events.publish(
                    events.ResourceUnloaded(self.s.name, resource.server, resource.id)
                )
            for waiting in self.unload_waiters.pop(resource.id):
                if overdue:
                    waiting.set_error(error)  # type: ignore[arg-type]
                else:
                    waiting.set_result(None)

        self.consumer.release_dependencies(resource.id, run_unload)

    def remove_resource(self, resource: Resource) -> None:
        """Forget a resource that is gone; serve the loads parked behind its unload."""
        self.s.catalog.remove_resource(resource.id)
        self.s.commit()
        for load in self.after_unload.pop(resource.id, ()):
            self.on_load(load)
        server = self.s.servers.get(resource.server)
        if server is not None and server.closing and not self.s.catalog.resources_of(server.name):
            del self.s.servers[server.name]
            server.ref.stop(block=False)

    def fail_waiting(self, error: RrError) -> None:
        """Answer every caller waiting on a load or an unload here with `error`."""
        for waiters in self.loads.values():
            for waiter in waiters:
                waiter.reply.set_error(error)
        for replies in self.unload_waiters.values():
            for reply in replies:
                reply.set_error(error)
        for loads in [*self.after_unload.values(), self.held_loads]:
            for load in loads:
                load.reply.set_error(error)
        self.matching.fail_waiting(error)

    # -- reconciling with consumers after a restart -----------------------------------

    def ask_to_reconcile(self) -> None:
        """This registrar serves (again): ask every registrar holding ids here to
        `Reconcile` (one that cannot be reached reconciles at its own start)."""
        for origin in sorted(self.s.catalog.consumer_origins()):
            with contextlib.suppress(RrError):
                DIRECTORY.lookup(origin).tell(ReconcileAsk(self.s.name))

    def on_reconcile(self, message: Reconcile) -> None:
        """Release the ids of `origin_rr` it no longer holds; name those held here unknown.

        An id whose load is still under way here (waiting, parked, matched) is neither.
        """
        catalog = self.s.catalog
        held = set(message.held)
        mine = catalog.consumer_ids_from(message.origin_rr)
        stale = sorted(mine - held)
        if stale:
            logger.warning(
                "registrar %s: %s no longer holds %d of its ids here (released while this "
                "registrar was down, or lost in its own restart): releasing them",
                self.s.name,
                message.origin_rr,
                len(stale),
            )
        for query_id in stale:
            if catalog.has_consumer(query_id):  # (still: a release above may have cascaded)
                self.release(query_id, None)
        under_way = {*self.loading_ids, *(load.query_id for load in self.matching.waiting())}
        under_way.update(load.query_id for load in self.held_loads)
        under_way.update(load.query_id for loads in self.after_unload.values() for load in loads)
        unknown = tuple(q for q in message.held if q not in mine and q not in under_way)
        message.reply.set_result(unknown)

    # -- fetch and servers ------------------------------------------------------------

    def on_fetch(self, message: Fetch) -> None:
        if message.server not in self.s.servers:
            message.reply.set_error(
                UnknownServerError(f"no resource server '{self.s.name}/{message.server}'")
            )
            return
        message.reply.set_result(
            [
                query
                for query in self.s.catalog.server_queries(message.server, self.s.name)
                if query.origin_rr == message.origin_rr
            ]
        )

    def server(self, name: str) -> Server:
        """The open server `name`.

        Raises:
            UnknownServerError: there is none (or it is closing).
        """
        server = self.s.servers.get(name)
        if server is None or server.closing:
            raise UnknownServerError(f"no resource server '{self.s.name}/{name}'")
        return server

    def op_register(
        self,
        name: str,
        load: LoadCallback,
        unload: UnloadCallback,
        on_status: StatusCallback | None,
        reply: Reply,
    ) -> None:
        if name in self.s.servers:
            raise DuplicateNameError(f"resource server '{self.s.name}/{name}' already exists")
        ref = ServerActor.start(
            self.s.name,
            name,
            load,
            unload,
            self.s.workers,
            persisted=self.s.saver.store is not None,
        )
        self.s.servers[name] = Server(name, ref, on_status)
        for run_unload in self.parked_unloads.pop(name, ()):
            run_unload()
        reply.set_result(None)

    def op_unregister(self, name: str, reply: Reply) -> None:
        server = self.server(name)
        server.closing = True
        resources = [
            r for r in self.s.catalog.resources_of(name) if r.state is ResourceState.LOADED
        ]

        def finish() -> None:
            if not self.s.catalog.resources_of(name) and name in self.s.servers:
                del self.s.servers[name]
                server.ref.stop(block=False)
            reply.set_result(None)

        join = Join(finish)
        for resource in resources:
            self.close_resource(resource, join.add())
        join.seal()

    def close_resource(self, resource: Resource, then: Callable[[], None]) -> None:
        """Send FATAL to a resource's consumers, revoke their ids, unload it (rule 12)."""
        self.s.probe("close_resource", resource)
        query_id = next(iter(resource.consumers))
        update = StatusUpdate(
            query_id,
            Status.FATAL,
            "resource server was unregistered",
            f"{self.s.name}/{resource.server}",
        )

        def revoke_and_unload() -> None:
            done = self.s.come_back(lambda *_: then())
            if resource.state is not ResourceState.LOADED:  # its consumers left meanwhile
                if resource.id in self.unload_waiters:
                    self.unload_waiters[resource.id].append(done)
                else:
                    done.set_result(None)
                return
            for origin, ids in consumers_by_origin(resource).items():
                with contextlib.suppress(RrError):
                    DIRECTORY.lookup(origin).tell(Revoke(ids))
            revoked = list(resource.consumers.items())
            for qid, _ in revoked:
                self.s.catalog.release(qid)
            if self.s.events.active:
                for qid, origin in revoked:
                    self.s.events.publish(
                        events.ConsumerReleased(self.s.name, resource.id, qid, origin)
                    )
            self.unload_resource(resource, done)

        if self.s.events.active:
            self.s.events.publish(
                events.StatusSent(self.s.name, query_id, update.status, update.message)
            )
        # the FATAL's acknowledgements may complete on any thread: come back to this one
        back = self.s.come_back(lambda *_: revoke_and_unload())
        self.status.notify(
            resource, update, str(uuid.uuid4()), query_id, lambda: back.set_result(None)
        )

    def op_update_response(self, query_id: str, response: Any, reply: Reply) -> None:
        resource = self.s.catalog.resource_of(query_id)
        self.s.catalog.set_response(resource.id, response)
        self.s.commit()
        join = Join(lambda: reply.set_result(None))
        for origin, ids in consumers_by_origin(resource).items():
            self.s.send(
                origin,
                functools.partial(ResponseUpdated, ids, response),
                functools.partial(
                    _log_failure, f"telling {origin} about a new response", join.add()
                ),
            )
        join.seal()

    def op_server_queries(self, server: str, reply: Reply) -> None:
        self.server(server)
        reply.set_result(self.s.catalog.server_queries(server, self.s.name))
