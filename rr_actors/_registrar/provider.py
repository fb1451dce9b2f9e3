"""The provider side of a registrar actor: a resource's life, loaded once (rules 1-7).

```
 Load ──► on_load ── equal request loaded? ──yes──► add consumer, answer (a dedup hit)
                 │         (user code compares off the actor thread: matching.py)
                 ├── loading? ──► wait for it (one load per resource, rule 3)
                 ├── unloading? ──► parked until it is gone, then loaded afresh
                 └── new ──► start_load ──RunLoad──► server ──► load_done ──► answer waiters
 failed, or nobody waits any more ──► Teardown.unload_resource / remove_resource
 parked behind an unload ──► Teardown.when_gone ──► serve_parked ──► on_load afresh
```

A resource its provider reported `FATAL` (`Resource.failed`) is no equal request's
match, also one reported so while user code compared: the request is loaded afresh
beside it (rule 1; `status.py` marks it).

A resource belongs to its server; its consumers are query ids (one per call, rule 2).
Callers that wait for a load and loads parked behind an unload of the same resource
are this role's state; running an unload is `teardown.py`'s, releasing consumer ids
`unloading.py`'s (it calls `give_up` here), the servers themselves `servers.py`'s.
"""

from __future__ import annotations

import functools
import logging
import time
import uuid
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rr_actors import events
from rr_actors._catalog import NO_DIGEST, Resource, ResourceState, describe, request_digest
from rr_actors._catalog.digest import requests_equal
from rr_actors._core.directory import Reply
from rr_actors._registrar.display import show_request, show_response
from rr_actors._registrar.loading import MAX_DEPENDENCY_DEPTH, check_picklable
from rr_actors._registrar.matching import Matching, first_equal, prepare
from rr_actors._registrar.messages import Load, RunLoad
from rr_actors._registrar.state import Phase, Server, Shared, Waiter
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    DependencyCycleError,
    DuplicateQueryIdError,
    RegistrarStoppedError,
    ResourceLoadError,
    RrError,
    UnknownServerError,
    _known_names,
)

if TYPE_CHECKING:
    from rr_actors._registrar.releases import Releases
    from rr_actors._registrar.teardown import Teardown

__all__ = ["Provider"]

logger = logging.getLogger("rr_actors")


class Provider:
    """Serves this registrar's resources to consumers (its own calls included).

    Attributes:
        loads: resource id -> the callers waiting for its load.
        loading_ids: a waiting caller's query id -> the resource it waits for.
        abandoned: query ids whose callers gave up while their load ran.
        held_loads: loads for servers `setup` has not registered yet.
        after_unload: resource id -> loads of an equal request, parked until it unloaded.
        load_started: resource id -> when its load started (`time.monotonic()`).
        labelling: resource id -> its load's end, waiting for its label (`None`: the load
            still runs), of the loads whose server's `label` a worker makes.
        matching: loads whose match user code decides, off the actor thread.
    """

    def __init__(self, shared: Shared, releases: Releases, teardown: Teardown) -> None:
        self.registrar = shared
        self.releases = releases
        self.teardown = teardown
        self.loads: dict[str, list[Waiter]] = {}
        self.loading_ids: dict[str, str] = {}
        self.abandoned: set[str] = set()
        self.held_loads: list[Load] = []
        self.after_unload: dict[str, list[Load]] = {}
        self.load_started: dict[str, float] = {}
        self.labelling: dict[str, Callable[[], None] | None] = {}
        self.matching = Matching(shared, self.serve)

    # -- load -------------------------------------------------------------------------

    def refusal(self, message: Load) -> RrError | None:
        """Why this registrar cannot take `message` at all, if it cannot."""
        server = self.registrar.servers.get(message.server)
        if server is None or server.closing:
            return UnknownServerError(
                f"no resource server '{self.registrar.name}/{message.server}'"
                + _known_names(
                    message.server, (n for n, s in self.registrar.servers.items() if not s.closing)
                )
            )
        if self.registrar.stopping:
            return RegistrarStoppedError(f"registrar {self.registrar.name!r} is stopping")
        if len(message.chain) >= MAX_DEPENDENCY_DEPTH:
            return DependencyCycleError(
                f"load chain deeper than {MAX_DEPENDENCY_DEPTH} at '{self.registrar.name}/"
                f"{message.server}': runaway recursion"
            )
        return None

    def on_load(self, message: Load, _reply: Reply) -> None:
        """Serve `message` (its answer goes to `message.reply`, which its waiters keep)."""
        if (
            self.registrar.phase is Phase.SETTING_UP
            and message.server not in self.registrar.servers
        ):
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
        if self.registrar.saver.store is not None:  # the backup must be able to hold the request
            pickled = f"the request to '{self.registrar.name}/{message.server}'"

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
        catalog = self.registrar.catalog
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
            f"'{self.registrar.name}/{server}', with another request); an id is for one call and "
            "its retries"
        )

    def retried(self, message: Load, known: Resource, key: Any, *, same: bool) -> None:
        """A load with a query id known here: a retry of that call, or an id reused."""
        if not same:
            message.reply.set_error(self.reused(message, known.server))
        elif self.registrar.catalog.has_consumer(message.query_id):  # answered: the stored response
            message.reply.set_result(known.response)
        elif message.query_id in self.loading_ids:  # it waits for the load again
            waiter = Waiter(message.query_id, message.origin_rr, message.reply)
            self.loads[self.loading_ids[message.query_id]].append(waiter)
        else:  # (released while its comparison ran: a new call now)
            self.look_up(message, key, request_digest(message.request))

    def look_up(self, message: Load, key: Any, digest: int | None) -> None:
        """Find an equal request on the server (rule 1), user code off this thread."""
        found, undecided = self.registrar.catalog.lookup(
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
        refusal = self.registrar.unwritable()  # a full disk: serve what is stored, nothing new
        if refusal is not None:
            message.reply.set_error(refusal)
            return
        if resource is not None and resource.id not in self.registrar.catalog.resources:
            resource = None  # it left while user code compared: load afresh
        elif resource is not None and resource.failed:
            resource = None  # reported FATAL while user code compared: load afresh
        if resource is not None and resource.state is ResourceState.LOADED:  # the hot path
            self.share(resource, message)
            return
        waiter = Waiter(message.query_id, message.origin_rr, message.reply)
        if resource is None:
            self.start_load(self.registrar.servers[message.server], message, waiter, key)
        elif resource.state is ResourceState.UNLOADING:  # load it afresh once it is gone
            if resource.id not in self.after_unload:  # the first parked behind it
                self.teardown.when_gone(
                    resource.id, functools.partial(self.serve_parked, resource.id)
                )
            self.after_unload.setdefault(resource.id, []).append(message)
        elif resource.id in message.chain:
            message.reply.set_error(
                DependencyCycleError(
                    f"'{self.registrar.name}/{message.server}' is asked for "
                    f"{describe(message.request)} while loading it further up the same chain"
                )
            )
        else:  # loading: wait for it (one load per resource, rule 3)
            self.loads[resource.id].append(waiter)
            self.loading_ids[message.query_id] = resource.id

    def share(self, resource: Resource, message: Load) -> None:
        """A dedup hit: one more consumer of a loaded resource (rules 1-2)."""
        shared = self.registrar
        shared.catalog.add_consumer(resource.id, message.query_id, message.origin_rr)
        told = (
            (events.ConsumerAdded(shared.name, resource.id, message.query_id, message.origin_rr),)
            if shared.events.active
            else ()
        )
        failed = shared.commit(*told)  # (written with it, published before the answer)
        if failed is not None:  # not durable: the caller holds nothing
            shared.catalog.release(message.query_id)
            shared.commit()
            message.reply.set_error(failed)
            return
        message.reply.set_result(resource.response)

    def start_load(self, server: Server, message: Load, waiter: Waiter, key: Any) -> None:
        """Load a request not loaded here (`key`: its `runtime_key` if it has no digest)."""
        if self.registrar.saver.store is not None and key is None:  # (else checked with the key)
            try:  # the backup must be able to hold the request (a plain one: no user code)
                check_picklable(
                    message.request, f"the request to '{self.registrar.name}/{server.name}'"
                )
            except ConfigError as exc:
                message.reply.set_error(exc)
                return
        rid = str(uuid.uuid4())
        resource = self.registrar.catalog.begin_load(rid, message.server, message.request, key=key)
        if server.label is not None:  # its ResourceLoaded names the label: made meanwhile
            self.labelling[rid] = None
        show_request(self.registrar, resource, server.label, functools.partial(self.labelled, rid))
        failed = self.registrar.commit()
        if failed is not None:  # not durable: load nothing (rule 16 needs the record)
            self.labelling.pop(rid, None)
            self.registrar.catalog.remove_resource(rid)
            self.registrar.commit()
            message.reply.set_error(failed)
            return
        self.loads[rid] = [waiter]
        self.loading_ids[message.query_id] = rid
        self.load_started[rid] = time.monotonic()
        reply = self.registrar.come_back(lambda value, error: self.load_done(rid, value, error))
        server.ref.tell(RunLoad(rid, message.request, (*message.chain, rid), reply))

    def load_done(self, rid: str, response: Any, error: BaseException | None) -> None:
        """The load of `rid` returned `response` (or raised `error`): answer its waiters.

        If its label is still being made on a worker (the load was faster), this waits
        for it (`labelled`, bounded by `compare_timeout`), so that its `ResourceLoaded`
        names the label, not the request's text.
        """
        load_s = time.monotonic() - self.load_started.pop(rid)
        if rid in self.labelling and self.registrar.events.active:
            self.labelling[rid] = functools.partial(self.loaded, rid, response, error, load_s)
            return
        self.labelling.pop(rid, None)
        self.loaded(rid, response, error, load_s)

    def labelled(self, rid: str) -> None:
        """The label of `rid` is made (or failed): finish its load if it was waiting."""
        then = self.labelling.pop(rid, None)
        if then is not None:
            then()

    def loaded(self, rid: str, response: Any, error: BaseException | None, load_s: float) -> None:
        catalog = self.registrar.catalog
        waiters = self.loads.pop(rid)
        for waiter in waiters:
            self.loading_ids.pop(waiter.query_id, None)
        resource = catalog.resources[rid]
        if self.registrar.events.active:
            published_load(self.registrar, resource, waiters[0].query_id, load_s, error)
        if error is not None:
            catalog.begin_unload(rid)
            self.registrar.commit()

            def failed() -> None:
                self.teardown.remove_resource(resource)
                for waiter in waiters:
                    self.abandoned.discard(waiter.query_id)
                    waiter.reply.set_error(error)

            self.releases.release_dependencies(rid, failed)
            return
        show_response(self.registrar, catalog.finish_load(rid, response))
        live = self._add_consumers(rid, waiters)
        server = self.registrar.servers.get(resource.server)
        closed = server is None or server.closing
        told = (
            tuple(  # (a retry listed twice is added once)
                events.ConsumerAdded(self.registrar.name, rid, query_id, origin)
                for query_id, origin in {w.query_id: w.origin_rr for w in live}.items()
            )
            if self.registrar.events.active and not closed
            else ()
        )
        # written with the consumers they tell of, published before the answers; not
        # durable: unload it, fail the callers
        refusal: RrError | None = self.registrar.commit(*told)
        if refusal is None and closed:
            refusal = UnknownServerError(
                f"resource server '{self.registrar.name}/{resource.server}' closed"
            )
        if refusal is not None:
            for waiter in live:
                if catalog.has_consumer(waiter.query_id):  # a retry may be listed twice
                    catalog.release(waiter.query_id)  # (its ConsumerAdded was not published)
                waiter.reply.set_error(refusal)
            live = []
        for waiter in live:
            waiter.reply.set_result(response)
        if not resource.consumers:  # every caller gave up (or the server closed)
            self.teardown.unload_resource(resource, None)

    def _add_consumers(self, rid: str, waiters: list[Waiter]) -> list[Waiter]:
        """Make the waiters of a finished load its consumers; the ones still waiting.

        A waiter whose caller gave up meanwhile is answered and holds nothing; a retry
        listed twice is added once.
        """
        catalog = self.registrar.catalog
        live = []
        for waiter in waiters:
            if waiter.query_id in self.abandoned:  # its caller gave up: answer, hold nothing
                self.abandoned.discard(waiter.query_id)
                waiter.reply.set_error(CallTimeoutError(f"call {waiter.query_id} was given up"))
                continue
            live.append(waiter)
            if not catalog.has_consumer(waiter.query_id):
                catalog.add_consumer(rid, waiter.query_id, waiter.origin_rr)
        return live

    def serve_held(self) -> None:
        """Setup is done: serve the loads that waited for it (unknown servers now fail),
        and release restored resources of servers setup did not bring back."""
        held, self.held_loads = self.held_loads, []
        for load in held:
            self.on_load(load, load.reply)
        self.teardown.settle_parked()

    def serve_parked(self, rid: str) -> None:
        """Resource `rid` is gone: serve the loads parked behind its unload, afresh."""
        for load in self.after_unload.pop(rid, ()):
            self.on_load(load, load.reply)

    def unpark(self, query_id: str) -> Load | None:
        """Take the load of `query_id` out of the held, parked or queued loads, if there."""
        for loads in [self.held_loads, *self.after_unload.values()]:
            for load in loads:
                if load.query_id == query_id:
                    loads.remove(load)
                    return load
        return self.matching.take(query_id)

    def give_up(self, query_id: str) -> bool:
        """The caller of `query_id` gave up: drop its load if it is under way here.

        Whether it was: a load not started yet (held, parked behind an unload, queued for
        a match) never starts and its caller is answered as given up; one whose request
        user code compares is answered when that is done; one that runs is answered,
        holding nothing, when it finishes.
        """
        parked = self.unpark(query_id)
        if parked is not None:
            parked.reply.set_error(CallTimeoutError(f"call {query_id} was given up"))
            return True
        if self.matching.give_up(query_id):
            return True
        if query_id in self.loading_ids:  # it loads: answered when it finishes
            self.abandoned.add(query_id)
            return True
        return False

    def under_way_of(self, origin_rr: str) -> list[str]:
        """The query ids of registrar `origin_rr` whose loads are under way here."""
        loads = [
            *self.matching.waiting(),
            *self.held_loads,
            *(load for parked in self.after_unload.values() for load in parked),
        ]
        ids = [load.query_id for load in loads if load.origin_rr == origin_rr]
        ids += [w.query_id for ws in self.loads.values() for w in ws if w.origin_rr == origin_rr]
        return list(dict.fromkeys(ids))

    def under_way(self) -> set[str]:
        """The query ids whose loads are under way here (waiting, parked, held, matched)."""
        ids = {*self.loading_ids, *(load.query_id for load in self.matching.waiting())}
        ids.update(load.query_id for load in self.held_loads)
        ids.update(load.query_id for loads in self.after_unload.values() for load in loads)
        return ids

    def fail_waiting(self, error: RrError) -> None:
        """Answer every caller waiting on a load or an unload here with `error`."""
        for waiters in self.loads.values():
            for waiter in waiters:
                waiter.reply.set_error(error)
        for loads in [*self.after_unload.values(), self.held_loads]:
            for load in loads:
                load.reply.set_error(error)
        self.matching.fail_waiting(error)
        self.teardown.fail_waiting(error)


def published_load(
    registrar: Shared,
    resource: Resource,
    query_id: str,
    load_s: float,
    error: BaseException | None,
) -> None:
    """Publish how a load ended (`ResourceLoaded` or `LoadFailed`)."""
    if error is None:
        digest = resource.digest
        registrar.events.publish(
            events.ResourceLoaded(
                registrar.name,
                resource.server,
                resource.id,
                query_id,
                load_s,
                digest if digest is not None and digest != NO_DIGEST else None,
                resource.label if resource.label is not None else resource.request_text,
            )
        )
        return
    error_type, message = type(error).__qualname__, str(error)
    if isinstance(error, ResourceLoadError):  # this registrar's frame: what load raised
        error_type, message = error.stack[-1].exc_type, error.stack[-1].message
    registrar.events.publish(
        events.LoadFailed(
            registrar.name, resource.server, resource.id, query_id, error_type, message
        )
    )
