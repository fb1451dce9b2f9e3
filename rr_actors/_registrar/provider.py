"""The provider side of a registrar actor: a resource's life, loaded once, shared, unloaded once.

```
 Load ─► Provider.on_load ── its id known? a retry (or DuplicateQueryIdError, rule 2)
   │   ── an equal request loaded? ─► share: one more consumer id (a dedup hit)
   │   │      (user code, a request's __hash__ and __eq__, off the actor: Matching)
   │   ├── loading? ─► wait for it (one load per resource, rule 3)
   │   ├── unloading? ─► parked until it is gone (Teardown.when_gone), then afresh
   │   └── new ─► start_load ─RunLoad─► ServerActor ─► load(request) on a worker or
   │              the process's loop ─► load_done ─► answer its waiters
 Unload / Abandon ─► Unloading.release(id) ── its load under way? ─► give_up
   │                                    └── the last consumer id? ─► unload_resource
   ▼
 Teardown.unload_resource ─► its dependencies released ─RunUnload─► ServerActor ─►
   unload(request, response) ─► remove_resource ─► the loads parked behind it
 Reconcile ─► Unloading.on_reconcile: ids no longer held released, loads not listed
   given up, those it lost named; earlier runs' Loads refused from then on (`Lives`)
```

A resource belongs to its server; its consumers are query ids (one per call, rule 2).
Why the actor never waits for user code, how coroutine callbacks run, and who decides
under overload: docs/explanation/inside.md, "The provider".

Why one module past the 1,200 lines of code a module keeps to: its parts are one story
(a load, its sharing, its release, its unload), and a restart runs them together (`Servers`
registers, `ServerActor` loads, `Provider` answers): a module more is a file more that each
restart crosses (issue 71, `benchmarks/call_files.py`). Where it splits by collaborator if
that count allows: `ServerActor`, `Teardown` and `Servers` (a server's actor, its registration,
a resource's unload through it; none calls `Provider` or `Unloading`), a module below this.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import functools
import inspect
import logging
import math
import weakref
from collections.abc import Awaitable, Callable
from typing import Any, NamedTuple, cast

from rr_actors import events
from rr_actors._catalog import (
    NO_DIGEST,
    Resource,
    ResourceState,
    describe,
    request_digest,
    runtime_key,
)
from rr_actors._catalog.digest import requests_equal
from rr_actors._core import runtime, traces
from rr_actors._core.actor import Actor
from rr_actors._core.directory import DIRECTORY, Reply
from rr_actors._core.loops import is_coroutine_function, process_loop
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._core.replies import CallbackReply, Join
from rr_actors._core.workers import Job, Workers
from rr_actors._platform.base import bound_reached
from rr_actors._registrar.display import show_request, show_response
from rr_actors._registrar.messages import (
    LOADING,
    Abandon,
    Fetch,
    ListServerQueries,
    Load,
    LoadContext,
    LoadPlace,
    Reconcile,
    ReconcileAsk,
    Reconciled,
    RegisterServer,
    ResponseUpdated,
    Revoke,
    RunLoad,
    RunUnload,
    Unload,
    UnloadOverran,
    UnregisterServer,
    UpdateResponse,
    check_picklable,
    exception_text,
    load_error,
)
from rr_actors._registrar.state import (
    Pace,
    Phase,
    Server,
    Shared,
    Waiter,
    consumers_by_origin,
    life_order,
)
from rr_actors._registrar.status import StatusRecord
from rr_actors._types import LoadCallback, Status, StatusUpdate, UnloadCallback
from rr_actors.config import MAX_DEPENDENCY_DEPTH
from rr_actors.errors import (
    CallTimeoutError,
    CatalogWriteError,
    ConfigError,
    DeadlineExceededError,
    DependencyCycleError,
    DuplicateNameError,
    DuplicateQueryIdError,
    OverloadedError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    ResourceLoadError,
    RrError,
    UnknownQueryError,
    UnknownServerError,
    _known_names,
)

logger = logging.getLogger("rr_actors")

_SHED_HEADROOM = 1.5
"""A queued load is shed unless its callers' time left exceeds this times its server's load time."""

_PROBE_LEFT = 0.02
"""Seconds a load must have left to run as a probe (`ServerActor.shed`): with less, its
`load` would begin after its caller gave up (GIL switch interval per thread ahead)."""

_REFUSALS_EVERY = 1.0
"""Seconds between two `ServerOverloaded` events of one server (refusals between counted)."""

_WANTING = 2.0
"""Seconds a refused consumer registrar counts as wanting loads there (`Admission`): twenty
times a refused caller's longest pause."""

_COME_BACK_MOST = 10.0
"""The longest pause a refused caller is told to take before it asks again, seconds."""

_LOAD_S_WEIGHT = 0.2
"""How far one load's run time moves its server's average: about the last ten loads count."""


class Share(NamedTuple):
    """What `Admission.refusal` decided a load of a consumer on: `ShareRefused`'s fields (`mine`:
    its `under_way`, `among`: its `consumers`; `since` on `runtime.monotonic()`)."""

    refused: bool
    pending: int
    mine: int
    share: int
    among: int
    ahead: int
    since: float
    waiting: tuple[int, ...]
    firsts: tuple[float, ...]


class Lives:
    """The run of each consumer registrar that reconciled here last (`Reconcile.life`): a
    `Load` of an earlier run is refused (presumed abort: docs/explanation/inside.md)."""

    __slots__ = ("_newest", "_reconciled")

    def __init__(self) -> None:
        self._reconciled: dict[str, str] = {}  # consumer registrar -> its run
        self._newest: dict[str, str] = {}  # consumer registrar -> its latest run heard of

    def reconciled(self, origin_rr: str, life: str) -> None:
        if life:
            self._reconciled[origin_rr] = life
        self.heard(origin_rr, life)

    def heard(self, origin_rr: str, life: str) -> None:
        """A `Load` or a `Reconcile` of run `life` of `origin_rr` came."""
        newest = self._newest.get(origin_rr, "")
        if life != newest and life_order(life) > life_order(newest):  # (most: the same run)
            self._newest[origin_rr] = life

    def newest(self, origin_rr: str) -> str:
        """The latest run of `origin_rr` heard of here ("": none)."""
        return self._newest.get(origin_rr, "")

    def fenced(self, origin_rr: str, life: str) -> bool:
        """Whether run `life` of `origin_rr` is earlier than the one that reconciled here last."""
        known = self._reconciled.get(origin_rr)
        # (most loads come from the run that reconciled last: no order to work out)
        if not life or known is None or life == known:
            return False
        return life_order(life) < life_order(known)


class Admission:
    """Which new loads each server takes: at most its bound under way, and of them at most
    a fair share per consumer registrar while others want some (docs/explanation/inside.md,
    "The provider"). Free slots go first to consumers with fewer loads under way there."""

    __slots__ = ("counted", "of", "paced", "pending", "wanting")

    def __init__(self) -> None:
        self.pending: dict[str, int] = {}  # server -> its loads queued or running
        self.of: dict[str, dict[str, int]] = {}  # server -> consumer -> its loads of them
        # server -> consumer -> (first refused, last refused) since it was last admitted
        self.wanting: dict[str, dict[str, tuple[float, float]]] = {}
        self.counted: dict[str, tuple[str, str]] = {}  # resource id -> (server, consumer)
        # server -> consumer -> when the last of its refused callers was told to come back
        self.paced: dict[str, dict[str, float]] = {}

    def come_back(
        self, server: str, origin: str, every: float, deadline: float | None, waits: bool = True
    ) -> float | None:
        """Seconds after which a caller of `origin` refused at `server` should ask again
        (`OverloadedError.retry_after`; `None`: no estimate): one slot (`every`) after the last
        caller of `origin` told to come back; its place is kept only if it `waits` and it falls
        before its `deadline`.
        """
        if every <= 0.0:
            return None
        now = runtime.monotonic()
        chains = self.paced.setdefault(server, {})
        at = min(max(now, chains.get(origin, now)) + every, now + _COME_BACK_MOST)
        for name in [name for name, last in chains.items() if last < now]:
            del chains[name]  # (its callers came back already)
        if waits and (deadline is None or at < deadline):
            chains[origin] = at
            wanting = self.wanting.get(server, {})
            if origin in wanting:  # (it wants loads until it is back, and `_WANTING` after)
                first, last = wanting[origin]
                wanting[origin] = (first, max(last, at))
        if not chains:
            del self.paced[server]
        return at - now

    def refusal(self, server: str, origin: str, bound: int) -> Share | None:
        """Whether `server` takes no new load of consumer `origin` now (noted as wanting loads
        there if not), and on what: `None` if it takes it and no other consumer waits."""
        pending = self.pending.get(server, 0)
        if not pending and server not in self.wanting:  # (the hot path: nobody to share with)
            return None
        of = self.of.get(server, {})
        mine = of.get(origin, 0)
        wanting = self.wanting.get(server, {})
        now = runtime.monotonic()
        for name in [name for name, (_, last) in wanting.items() if now - last > _WANTING]:
            del wanting[name]
        if not wanting:
            self.wanting.pop(server, None)
        consumers = {*of, *wanting, origin}
        share = max(1, bound // len(consumers))
        since, told = wanting.get(origin, (now, now))  # (`told`: when it is back, if later)
        others = [(of.get(n, 0), first) for n, (first, _) in wanting.items() if n != origin]
        ahead = sum(other < (mine, since) for other in others)  # (fewer under way, or longer)
        counts = (pending, mine, share, len(consumers), ahead, since)
        waits = (tuple(loads for loads, _ in others), tuple(first for _, first in others))
        if pending + ahead < bound and mine < share:  # (a free slot each kept for those)
            return Share(False, *counts, *waits) if others else None
        self.wanting.setdefault(server, {})[origin] = (since, max(now, told))
        return Share(True, *counts, *waits)

    def admit(self, rid: str, server: str, origin: str) -> None:
        self.pending[server] = self.pending.get(server, 0) + 1
        mine = self.of.setdefault(server, {})
        mine[origin] = mine.get(origin, 0) + 1
        self.counted[rid] = (server, origin)
        wanting = self.wanting.get(server)
        if wanting is not None and wanting.pop(origin, None) is not None and not wanting:
            del self.wanting[server]

    def done(self, rid: str) -> None:
        counted = self.counted.pop(rid, None)
        if counted is None:
            return
        server, origin = counted
        left = self.pending[server] - 1
        if left > 0:
            self.pending[server] = left
        else:
            del self.pending[server]
        mine = self.of[server]
        if mine[origin] > 1:
            mine[origin] -= 1
        else:
            del mine[origin]
            if not mine:
                del self.of[server]


class ProviderRecord(StatusRecord):
    """The registrar's record as its provider side and the parts above see it."""

    provider: Provider
    lives: Lives  # the consumers' runs that reconciled: earlier ones fenced
    unloading: Unloading
    teardown: Teardown
    registry: Servers


class Provider:
    def __init__(self, registrar: ProviderRecord) -> None:
        self.registrar = registrar
        self.loads: dict[str, list[Waiter]] = {}  # resource id -> the callers waiting for it
        self.admission = Admission()  # each server's loads queued or running, by consumer
        self.loading_ids: dict[str, str] = {}  # a waiting caller's query id -> its resource
        self.abandoned: set[str] = set()  # query ids whose callers gave up while it loaded
        self.retried_held: set[str] = set()  # held before their last Load: its Abandon keeps
        self.held_loads: list[Load] = []  # for servers `setup` has not registered yet
        self.after_unload: dict[str, list[Load]] = {}  # resource id -> loads parked behind
        self.load_started: dict[str, float] = {}  # resource id -> when (`time.monotonic()`)
        # resource id -> its load's place in the queue for a worker, and its answer's reply
        self.places: dict[str, tuple[LoadPlace, Reply]] = {}
        # resource id -> its load's end, waiting for the label a worker makes (`None`: the
        # load still runs)
        self.labelling: dict[str, Callable[[], None] | None] = {}
        self.matching = Matching(registrar, self.serve)
        self.monitored: set[str] = set()  # the consumers whose restarts it hears (rule 20)

    # -- load -------------------------------------------------------------------------

    def refusal(self, message: Load) -> RrError | None:
        name, servers = self.registrar.name, self.registrar.servers
        server = servers.get(message.server)
        if server is None or server.closing:
            return UnknownServerError(
                f"no resource server '{name}/{message.server}'"
                + _known_names(message.server, (n for n, s in servers.items() if not s.closing))
            )
        if self.registrar.stopping:  # (its own end: named)
            return RegistrarStoppedError(f"registrar {name!r} is stopping", name)
        if self.registrar.lives.fenced(message.origin_rr, message.life):
            return RegistrarUnavailableError(
                f"registrar {message.origin_rr!r} restarted since it sent the load of "
                f"{message.query_id!r} to '{name}/{message.server}', and "
                "reconciled: that run holds nothing here"
            )
        if len(message.chain) >= MAX_DEPENDENCY_DEPTH:
            return DependencyCycleError(
                f"load chain deeper than {MAX_DEPENDENCY_DEPTH} at '{name}/"
                f"{message.server}': runaway recursion"
            )
        return None

    def on_load(self, message: Load, _reply: Reply) -> None:
        if message.origin_rr not in self.monitored:  # (its restarts: rule 20; once a life,
            MEMBERSHIP.monitor(self.registrar.name, message.origin_rr)  # kept by the membership)
            self.monitored.add(message.origin_rr)
        if (  # (the phase last: read through its enum class, a member costs ~1k instructions)
            message.server not in self.registrar.servers
            and self.registrar.phase is Phase.SETTING_UP
        ):
            self.held_loads.append(message)  # served once setup has registered its servers
            return
        if self.matching.busy(message.server):  # user code decides a match there now
            self.matching.queue(message)
            return
        self.serve(message)

    def serve(self, message: Load) -> None:
        """Serve a load (rules 1-3); what only user code can decide (a request without a
        digest) runs on a worker (`Matching`), and the load goes on from the step that waited."""
        refusal = self.refusal(message)
        if refusal is not None:
            message.reply.set_error(refusal)
            return
        self.registrar.lives.heard(message.origin_rr, message.life)
        self.abandoned.discard(message.query_id)  # a retry: its caller is back
        self.retried_held.discard(message.query_id)
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
        if error is None:
            error = self.refusal(message)  # (the server may have closed meanwhile)
        if error is not None:
            message.reply.set_error(error)
            return False
        return True

    def identify(self, message: Load, key: Any, digest: int | None) -> None:
        """Check what the load's query id names already: a retry, or an id reused (rule 2);
        `key`: the request's `runtime_key` if it has no digest."""
        catalog = self.registrar.catalog
        known: Resource | None = None
        holder: str | None = None
        if catalog.has_consumer(message.query_id):  # a retry of an answered call?
            known = catalog.resource_of(message.query_id)
            holder = known.consumers[message.query_id]
        elif message.query_id in self.loading_ids:  # a retry while its load runs?
            known = catalog.resources[self.loading_ids[message.query_id]]
            holder = self.origin_under_way(message.query_id)
        else:
            other = self.matching.named(message.query_id)  # (of another server)
            if other is not None and other is not message:
                message.reply.set_error(self.reused(message, other.server))
                return
        if known is None:
            self.look_up(message, key, digest)
        elif known.server != message.server or holder not in (None, message.origin_rr):
            # a retry repeats the call: another server, or another caller, is another call
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
        if not same:
            message.reply.set_error(self.reused(message, known.server))
        elif self.registrar.catalog.has_consumer(message.query_id):  # answered: the stored response
            self.retried_held.add(message.query_id)  # (its withdrawal gives back nothing)
            reply = message.reply  # (after the turn's commit: its id may be staged in it)
            self.registrar.commit_then(
                ok=lambda: reply.set_result(known.response),
                undo=reply.set_error,
                refuse=reply.set_error,
            )
        elif message.query_id in self.loading_ids:  # it waits for the load again
            waiter = Waiter(message.query_id, message.origin_rr, message.reply, message.trace)
            self.loads[self.loading_ids[message.query_id]].append(waiter)
        else:  # (released while its comparison ran: a new call now)
            self.look_up(message, key, request_digest(message.request))

    def look_up(self, message: Load, key: Any, digest: int | None) -> None:
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
        waiter = Waiter(message.query_id, message.origin_rr, message.reply, message.trace)
        if resource is None:
            self.start_load(self.registrar.servers[message.server], message, waiter, key)
        elif resource.state is ResourceState.UNLOADING:  # load it afresh once it is gone
            if resource.id not in self.after_unload:  # the first parked behind it
                self.registrar.teardown.when_gone(
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
            # (setdefault: a restored row left loading, not in doubt, by a classroom's
            # copy of `in_doubt` has no load running: its callers wait until they time out)
            self.loads.setdefault(resource.id, []).append(waiter)
            self.loading_ids[message.query_id] = resource.id
            if resource.id in self.places:  # (it may wait for a worker: not shed before)
                self.places[resource.id][0].extend(message.deadline)

    def share(self, resource: Resource, message: Load) -> None:
        shared = self.registrar
        shared.catalog.add_consumer(resource.id, message.query_id, message.origin_rr)
        told = (
            (
                events.ConsumerAdded(
                    shared.name, resource.id, message.query_id, message.origin_rr, message.trace
                ),
            )
            if shared.events.active
            else ()
        )
        reply, query_id, response = message.reply, message.query_id, resource.response

        def undo(failed: CatalogWriteError) -> None:  # not durable: the caller holds nothing
            if shared.catalog.has_consumer(query_id):
                shared.catalog.release(query_id)
            reply.set_error(failed)

        # written with it (and the rest of the turn), published before the answer
        shared.commit_then(
            *told, ok=lambda: reply.set_result(response), undo=undo, refuse=reply.set_error
        )

    def refused(self, server: Server, pending: int, bound: int) -> None:
        """A load of `server` was refused: one `ServerOverloaded` per `_REFUSALS_EVERY` at most."""
        publisher = self.registrar.events
        if not publisher.active:
            return
        now = runtime.monotonic()
        count, last = server.refusals or (0, now - _REFUSALS_EVERY)
        if now - last < _REFUSALS_EVERY:
            server.refusals = (count + 1, last)
            return
        server.refusals = (0, now)
        name = self.registrar.name
        publisher.publish(events.ServerOverloaded(name, server.name, pending, bound, count + 1))

    def start_load(self, server: Server, message: Load, waiter: Waiter, key: Any) -> None:
        """Load a request not loaded here, unless its server or its consumer has its share of
        loads under way (`Admission`): then `OverloadedError`."""
        bound = server.max_pending or self.registrar.config.max_pending
        origin = message.origin_rr
        on = self.admission.refusal(server.name, origin, bound)
        tell = self.registrar.events.active  # (each admission while others wait, each refusal
        if on is not None and tell and (not on.refused or on.pending < bound):  # with room)
            counts = (self.registrar.name, server.name, origin, on.pending, on.mine, on.share)
            facts = (bound, on.since, on.waiting, on.firsts)  # (refused, or others wait)
            self.registrar.events.publish(
                events.ShareRefused(*counts, on.among, on.ahead, *facts)
                if on.refused
                else events.ShareAdmitted(*counts, on.among, *facts)
            )
        if on is not None and on.refused:
            if on.pending >= bound:  # (not a consumer held to its share: the server is full)
                self.refused(server, on.pending, bound)
            why = (
                f"has {on.pending} loads queued or running, its bound (max_pending={bound})"
                if on.pending >= bound
                else f"has {on.mine} loads of {origin!r} queued or running, its share of its "
                f"bound (max_pending={bound}) while other consumers want loads there "
                f"({on.share}), or one that waits is served first"
            )
            every = server.pace.load_s / self.registrar.workers.max_workers
            after = self.admission.come_back(
                server.name, origin, every, message.deadline, message.waits
            )
            message.reply.set_error(
                OverloadedError(
                    f"'{self.registrar.name}/{server.name}' {why}: it takes no more for now"
                    + ("" if after is None else f" (ask again in {after:.3f} s)"),
                    self.registrar.name,
                    server.name,
                    bound,
                    after,
                )
            )
            return
        if self.registrar.saver.store is not None and key is None:  # (else checked with the key)
            try:  # the backup must be able to hold the request (a plain one: no user code)
                check_picklable(
                    message.request, f"the request to '{self.registrar.name}/{server.name}'"
                )
            except ConfigError as exc:
                message.reply.set_error(exc)
                return
        rid = runtime.new_id()
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
        self.admission.admit(rid, server.name, origin)
        self.loading_ids[message.query_id] = rid
        self.load_started[rid] = runtime.monotonic()
        reply = self.registrar.come_back(lambda value, error: self.load_done(rid, value, error))
        place = LoadPlace(message.deadline)
        self.places[rid] = (place, reply)
        chain = (*message.chain, rid)
        server.ref.tell(RunLoad(rid, message.request, chain, reply, place, message.trace, origin))

    def load_done(self, rid: str, response: Any, error: BaseException | None) -> None:
        """The load of `rid` returned `response` (or raised `error`): answer its waiters (after
        its label, if that is still being made, so that `ResourceLoaded` names it)."""
        if self.places.pop(rid, None) is None:  # withdrawn before it ran (`withdraw`)
            return
        load_s = runtime.monotonic() - self.load_started.pop(rid)
        if rid in self.labelling and self.registrar.events.active:
            self.labelling[rid] = functools.partial(self.loaded, rid, response, error, load_s)
            return
        self.labelling.pop(rid, None)
        self.loaded(rid, response, error, load_s)

    def labelled(self, rid: str) -> None:
        then = self.labelling.pop(rid, None)
        if then is not None:
            then()

    def loaded(self, rid: str, response: Any, error: BaseException | None, load_s: float) -> None:
        catalog = self.registrar.catalog
        waiters = self.loads.pop(rid)
        for waiter in waiters:
            self.loading_ids.pop(waiter.query_id, None)
        resource = catalog.resources[rid]
        self.admission.done(rid)
        if self.registrar.events.active:
            published_load(self.registrar, resource, waiters[0], load_s, error)
        if error is not None:
            catalog.begin_unload(rid)
            self.registrar.commit()

            def failed() -> None:
                self.registrar.teardown.remove_resource(resource)
                for waiter in waiters:
                    self.abandoned.discard(waiter.query_id)
                    waiter.reply.set_error(error)

            self.registrar.releases.release_dependencies(rid, failed)
            return
        show_response(self.registrar, catalog.finish_load(rid, response))
        live = self._add_consumers(rid, waiters)
        server = self.registrar.servers.get(resource.server)
        closed = server is None or server.closing
        told = (
            tuple(  # (a retry listed twice is added once)
                events.ConsumerAdded(self.registrar.name, rid, query_id, origin, trace)
                for query_id, (origin, trace) in {
                    w.query_id: (w.origin_rr, w.trace) for w in live
                }.items()
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
            self.registrar.teardown.unload_resource(resource, None)

    def _add_consumers(self, rid: str, waiters: list[Waiter]) -> list[Waiter]:
        """Make the waiters of a finished load its consumers (one that gave up holds nothing)."""
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
        """Setup is done: serve the loads that waited for it, and release restored resources of
        servers setup did not bring back."""
        held, self.held_loads = self.held_loads, []
        for load in held:
            self.on_load(load, load.reply)
        self.registrar.teardown.settle_parked()

    def serve_parked(self, rid: str) -> None:
        for load in self.after_unload.pop(rid, ()):
            self.on_load(load, load.reply)

    def unpark(self, query_id: str) -> Load | None:
        for loads in [self.held_loads, *self.after_unload.values()]:
            for load in loads:
                if load.query_id == query_id:
                    loads.remove(load)
                    return load
        return self.matching.take(query_id)

    def give_up(self, query_id: str) -> bool:
        """The caller of `query_id` gave up: drop its load if it is under way here (whether it
        was); one still waiting for a worker, all of whose callers gave up, never runs."""
        parked = self.unpark(query_id)
        if parked is not None:
            parked.reply.set_error(CallTimeoutError(f"call {query_id} was given up"))
            return True
        if self.matching.give_up(query_id):
            return True
        if query_id in self.loading_ids:  # it loads: answered when it finishes
            self.abandoned.add(query_id)
            self.withdraw(self.loading_ids[query_id])
            return True
        return False

    def withdraw(self, rid: str) -> None:
        """Shed the load of `rid` if every caller gave up and it still waits for a worker: it
        never runs, and its callers are answered as given up (rule 17)."""
        waiters = self.loads.get(rid, [])
        if not waiters or any(w.query_id not in self.abandoned for w in waiters):
            return
        if rid not in self.places:
            return
        place, reply = self.places[rid]
        if not place.withdraw():
            return
        del self.places[rid]
        reply.set_error(CallTimeoutError("withdrawn"))  # (its token freed: `load_done` skips it)
        self.load_started.pop(rid, None)
        self.labelling.pop(rid, None)
        catalog = self.registrar.catalog
        resource = catalog.resources[rid]
        for waiter in self.loads.pop(rid):
            self.loading_ids.pop(waiter.query_id, None)
        self.admission.done(rid)
        error = CallTimeoutError(
            f"the load of {describe(resource.request)} at '{self.registrar.name}/"
            f"{resource.server}' was withdrawn before it ran: every caller gave up"
        )
        if self.registrar.events.active:
            published_load(self.registrar, resource, waiters[0], 0.0, error)
        catalog.begin_unload(rid)
        self.registrar.commit()

        def gone() -> None:
            self.registrar.teardown.remove_resource(resource)
            for waiter in waiters:
                self.abandoned.discard(waiter.query_id)
                waiter.reply.set_error(CallTimeoutError(f"call {waiter.query_id} was given up"))

        self.registrar.releases.release_dependencies(rid, gone)

    def origin_under_way(self, query_id: str) -> str | None:
        rid = self.loading_ids.get(query_id)
        waiters = self.loads.get(rid, []) if rid is not None else []
        loads: list[Waiter | Load] = [
            *waiters,
            *self.matching.waiting(),
            *self.held_loads,
            *(load for parked in self.after_unload.values() for load in parked),
        ]
        return next((load.origin_rr for load in loads if load.query_id == query_id), None)

    def under_way_of(self, origin_rr: str) -> list[str]:
        loads = [
            *self.matching.waiting(),
            *self.held_loads,
            *(load for parked in self.after_unload.values() for load in parked),
        ]
        ids = [load.query_id for load in loads if load.origin_rr == origin_rr]
        ids += [w.query_id for ws in self.loads.values() for w in ws if w.origin_rr == origin_rr]
        return list(dict.fromkeys(ids))

    def under_way(self) -> set[str]:
        ids = {*self.loading_ids, *(load.query_id for load in self.matching.waiting())}
        ids.update(load.query_id for load in self.held_loads)
        ids.update(load.query_id for loads in self.after_unload.values() for load in loads)
        return ids - self.abandoned  # (given up: holds nothing, as a held id's withdrawn retry)

    def fail_waiting(self, error: RrError) -> None:
        for waiters in self.loads.values():
            for waiter in waiters:
                waiter.reply.set_error(error)
        for loads in [*self.after_unload.values(), self.held_loads]:
            for load in loads:
                load.reply.set_error(error)
        self.matching.fail_waiting(error)
        self.registrar.teardown.fail_waiting(error)


def published_load(
    registrar: Shared,
    resource: Resource,
    waiter: Waiter,
    load_s: float,
    error: BaseException | None,
) -> None:
    """Publish how a load ended (`ResourceLoaded` or `LoadFailed`), for the call of `waiter`."""
    query_id = waiter.query_id
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
                waiter.trace,
            )
        )
        return
    error_type, message = type(error).__qualname__, str(error)
    if isinstance(error, ResourceLoadError):  # this registrar's frame: what load raised
        error_type, message = error.stack[-1].exc_type, error.stack[-1].message
    registrar.events.publish(
        events.LoadFailed(
            registrar.name,
            resource.server,
            resource.id,
            query_id,
            error_type,
            message,
            waiter.trace,
        )
    )


# -- matching --------------------------------------------------------------------------


Then = Callable[[Any, BaseException | None], None]


def prepare(request: Any, *, pickled: str | None) -> Any:
    """On a worker: a request's `runtime_key` (its `__hash__`), and a check that it pickles
    (`pickled`: its name in the `ConfigError`, or `None` when no backup is kept)."""
    key = runtime_key(request)
    if pickled is not None:
        check_picklable(request, pickled)
    return key


def first_equal(request: Any, candidates: list[Any]) -> int | None:
    """On a worker: the index of the first candidate `== request`, if any; an `Exception`
    from `__eq__` means "different", any other `BaseException` propagates."""
    for index, stored in enumerate(candidates):
        if requests_equal(stored, request):
            return index
    return None


class Matching:
    def __init__(self, shared: Shared, serve: Callable[[Load], None]) -> None:
        self.registrar = shared
        self.serve = serve  # (`Provider.serve`: for the loads queued behind a match)
        self.in_flight: dict[str, Load] = {}  # server -> the load user code decides now
        self.queued: dict[str, collections.deque[Load]] = {}  # server -> loads meanwhile
        self.given_up: set[str] = set()  # ids of loads in flight whose caller gave up

    def busy(self, server: str) -> bool:
        return server in self.in_flight or server in self.queued

    def queue(self, load: Load) -> None:
        self.queued.setdefault(load.server, collections.deque()).append(load)

    def run(self, load: Load, what: str, work: Callable[[], Any], then: Then) -> None:
        """Run `work()` (user code) on a worker for `load`; then `then(result, error)` here,
        unless its caller gave up or the registrar failed it. `error`: what `work` raised (an
        `Exception`), else `ConfigError`; `CallTimeoutError` past `compare_timeout`. The loads
        queued behind it are served next.
        """
        server = load.server
        self.in_flight[server] = load
        where = f"'{self.registrar.name}/{server}'"
        limit = self.registrar.config.compare_timeout

        def back(value: Any, error: BaseException | None) -> None:
            if self.in_flight.get(server) is not load:  # failed by `fail_waiting` already
                return
            del self.in_flight[server]
            try:
                if load.query_id in self.given_up:
                    self.given_up.discard(load.query_id)
                    load.reply.set_error(CallTimeoutError(f"call {load.query_id} was given up"))
                else:
                    then(value, error)
            finally:
                self.next_in_line(server)

        done = self.registrar.come_back(back)

        def task() -> None:
            try:
                value = work()
            except Exception as exc:  # noqa: BLE001 - handed to the actor
                done.set_error(exc)
            except BaseException as exc:  # noqa: BLE001 - SystemExit & co: contained here
                done.set_error(
                    ConfigError(
                        f"{what} for a call to {where} raised {type(exc).__qualname__}: "
                        f"{exception_text(exc)}; the call fails, the registrar goes on"
                    )
                )
            else:
                done.set_result(value)

        def overdue() -> None:
            done.set_error(
                CallTimeoutError(
                    f"{what} for a call to {where} did not finish within {limit:g} s "
                    "(compare_timeout); the call fails, the registrar goes on"
                )
            )

        try:
            self.registrar.workers.submit(task, timeout=limit, on_overdue=overdue)
        except RuntimeError as exc:
            done.set_error(RuntimeError(f"no worker thread could start for {what}: {exc}"))

    def next_in_line(self, server: str) -> None:
        while server not in self.in_flight:
            waiting = self.queued.get(server)
            if not waiting:
                self.queued.pop(server, None)
                return
            load = waiting.popleft()
            if not waiting:
                del self.queued[server]
            self.serve(load)

    def take(self, query_id: str) -> Load | None:
        for server, loads in self.queued.items():
            for load in loads:
                if load.query_id == query_id:
                    loads.remove(load)
                    if not loads:
                        del self.queued[server]
                    return load
        return None

    def give_up(self, query_id: str) -> bool:
        if any(load.query_id == query_id for load in self.in_flight.values()):
            self.given_up.add(query_id)
            return True
        return False

    def named(self, query_id: str) -> Load | None:
        if not self.in_flight and not self.queued:  # (the usual case: nothing here)
            return None
        return next((load for load in self.waiting() if load.query_id == query_id), None)

    def waiting(self) -> list[Load]:
        return [*self.in_flight.values(), *(load for q in self.queued.values() for load in q)]

    def fail_waiting(self, error: RrError) -> None:
        for load in self.waiting():
            load.reply.set_error(error)
        self.in_flight.clear()
        self.queued.clear()
        self.given_up.clear()


# -- server actors ---------------------------------------------------------------------


def _no_thread(exc: RuntimeError) -> RuntimeError:
    bound = bound_reached(exc) or f"threads ({exc})"  # (the machine's, named with its value)
    error = RuntimeError(
        f"no worker thread for the callback: this machine's limit of {bound} was reached"
    )
    error.__cause__ = exc
    return error


class ServerActor(Actor):
    """A resource server: owns its callbacks and runs them on the registrar's workers (never
    on an actor thread), so different requests to one server load concurrently."""

    def __init__(
        self,
        registrar: str,
        name: str,
        load: LoadCallback,
        unload: UnloadCallback,
        workers: Workers,
        *,
        persisted: bool = False,
        pace: Pace | None = None,
    ) -> None:
        super().__init__()
        self.persisted = persisted  # responses must pickle: the catalog stores them
        self.registrar = registrar
        self.name = name
        self.load = load
        self.unload = unload
        self.workers = workers
        self.on_loop = is_coroutine_function(load), is_coroutine_function(unload)
        # its coroutines running (loop thread), in the order they started (a dict: a set
        # would cancel them in address order at a stop, which no replay repeats)
        self.tasks: dict[asyncio.Task[None], None] = {}
        # what its loads take lately (`ran`), shared with the provider (`Server.pace`)
        self.pace = Pace() if pace is None else pace
        self.latest: dict[str, float] = {}  # lane -> the latest deadline queued in it, at most

    def on_receive(self, message: Any) -> None:
        if isinstance(message, RunLoad):
            message.place.take(functools.partial(self._start_load, message))
        elif isinstance(message, RunUnload) and self.on_loop[1]:
            self._spawn(message)
        elif isinstance(message, RunUnload):
            timeout = message.timeout
            try:
                self.workers.submit(  # (urgent: never behind loads queued before it)
                    lambda: self._unload(message),
                    timeout=timeout,
                    on_overdue=None if timeout is None else functools.partial(self.late, message),
                    urgent=True,
                )
            except RuntimeError as exc:
                message.reply.set_error(_no_thread(exc))

    def _start_load(self, message: RunLoad) -> Job | None:
        """Start a load: its worker job while it waits for a place (withdrawable until one
        takes it), `None` if it failed. A coroutine's job holds its place while it runs. One
        that would be shed after its server's loads queued ahead in its lane (rounds of
        `max_workers`, none past its deadline less the headroom) fails so at once."""
        held, lane, load_s = self.on_loop[0], message.origin, self.pace.load_s
        key = (lane, self.name)
        waiting = self.workers.waiting(key)
        rounds = waiting // self.workers.max_workers  # (one round: a load on every worker)
        ahead = self.latest.get(lane, math.inf) if waiting else -math.inf  # (their deadline)
        if rounds and ahead < math.inf and load_s > 0:  # (none run past their own deadline)
            rounds = min(rounds, max(0, int((ahead - runtime.monotonic()) / load_s - 0.5)))
        refused = self.shed(message, rounds) if rounds else None
        if refused is not None:
            message.reply.set_error(refused)
            return None
        self.latest[lane] = max(ahead, message.place.deadline or math.inf)  # (monotonic: > 0)
        try:
            task = functools.partial(self._spawn if held else self._load, message)
            return self.workers.submit(task, lane=lane, held=held, key=key)
        except RuntimeError as exc:  # no thread could start: this load fails, no other
            message.reply.set_error(load_error(self.registrar, self.name, _no_thread(exc)))
            return None

    def on_stop(self) -> None:
        if self.on_loop[0] or self.on_loop[1]:
            tasks = self.tasks
            with contextlib.suppress(RuntimeError):  # (the loop is closed: nothing runs there)
                process_loop().call_soon_threadsafe(lambda: [t.cancel() for t in list(tasks)])

    def _spawn(self, message: RunLoad | RunUnload) -> None:
        """Run its coroutine callback on the process's loop; a load's worker place is released
        as it ends. A loop closed or stopped (as the process ends) runs nothing: the place is
        released at once (or as the loop drops the start it was handed) and `message.reply`
        fails, a load's callers with `ResourceLoadError` naming this registrar and server (an
        unload's with that `RuntimeError`)."""
        tasks, load = self.tasks, isinstance(message, RunLoad)
        coroutine = self._aload(message) if isinstance(message, RunLoad) else self._aunload(message)

        def start() -> None:
            lost.detach()
            task = asyncio.get_running_loop().create_task(coroutine)
            tasks[task] = None
            task.add_done_callback(lambda done: (tasks.pop(done, None), load and release()))

        def dead() -> None:
            coroutine.close()
            if load:
                release()
            state = "closed" if loop.is_closed() else "stopped"
            error = RuntimeError(f"the process's event loop is {state}: no coroutine starts there")
            message.reply.set_error(load_error(self.registrar, self.name, error) if load else error)

        loop, release = process_loop(), self.workers.release
        lost = weakref.finalize(start, dead)  # (a start dropped unrun: stopped, then closed)
        with contextlib.suppress(RuntimeError):  # (closed since)
            if loop.is_running():  # (else what it is handed never runs)
                loop.call_soon_threadsafe(start)
                return
        lost()

    def shed(self, message: RunLoad, rounds: int = 0) -> DeadlineExceededError | None:
        """As its load would start (after `rounds` of this server's loads): the error that
        sheds it, if its callers' deadline leaves less than `_SHED_HEADROOM` times what this
        server's loads take (`load_s`). A stale average is probed (refuses no load ahead):
        docs/explanation/inside.md, "The provider"."""
        deadline = message.place.deadline
        if deadline is None:
            return None
        now, pace = runtime.monotonic(), self.pace
        left, expected = deadline - now - rounds * pace.load_s, pace.load_s * _SHED_HEADROOM
        if left > expected:
            return None
        if now - pace.learned >= pace.load_s:  # stale
            if rounds:
                return None
            if left > _PROBE_LEFT:
                pace.learned = now  # (workers race here: a probe more or less, no harm)
                return None
            pace.load_s -= _LOAD_S_WEIGHT * pace.load_s  # (too late to probe: forget)
        return DeadlineExceededError(
            f"the load of {describe(message.request)} at '{self.registrar}/{self.name}' was "
            f"shed before it started: {max(left, 0.0):.3f} s were left of its callers' "
            f"timeout{f' after {rounds} rounds of its loads queued ahead' if rounds else ''}, "
            f"and its loads take {pace.load_s:.3f} s lately (it needs {_SHED_HEADROOM:g} "
            "times that)"
        )

    def ran(self, took: float) -> None:
        """A load ran for `took` seconds: the recent average moves toward it (workers may race)."""
        pace = self.pace
        pace.load_s += _LOAD_S_WEIGHT * (took - pace.load_s)
        pace.learned = runtime.monotonic()

    async def _aload(self, message: RunLoad) -> None:
        """A coroutine `load`, on the process's loop, under its call's SERVER span."""
        shed = self.shed(message)
        if shed is not None:
            message.reply.set_error(shed)
            return
        LOADING.set(LoadContext(self.registrar, message.resource_id, message.chain))
        if message.trace:
            traces.attach(message.trace)  # (the task's own context: nothing to detach)
        began = runtime.monotonic()
        try:
            try:
                response = await self.load(message.request)
            finally:
                self.ran(runtime.monotonic() - began)
            if self.persisted:
                check_picklable(response, "the response")
        except BaseException as exc:  # noqa: BLE001 - any exception fails the load (rule 4)
            message.reply.set_error(load_error(self.registrar, self.name, exc))
        else:
            message.reply.set_result(response)

    def late(self, message: RunUnload) -> None:
        """Its unload callback did not return within its `timeout`: its reply fails so."""
        late = f"the unload callback of '{self.registrar}/{self.name}' did not return within"
        message.reply.set_error(CallTimeoutError(f"{late} {message.timeout:g} s"))

    async def _aunload(self, message: RunUnload) -> None:
        """A coroutine `unload`, on the process's loop, cancelled past `timeout`, under its span."""
        if message.trace:
            traces.attach(message.trace)  # (the task's own context: nothing to detach)
        bound = asyncio.timeout(message.timeout)
        try:
            async with bound:
                await cast("Awaitable[None]", self.unload(message.request, message.response))
        except TimeoutError as exc:
            if not bound.expired():  # (the callback's own TimeoutError)
                message.reply.set_error(exc)
                return
            self.late(message)
        except BaseException as exc:  # noqa: BLE001 - logged by the registrar, never lost
            message.reply.set_error(exc)
        else:
            message.reply.set_result(None)

    def _load(self, message: RunLoad) -> None:
        shed = self.shed(message)
        if shed is not None:  # its `load` never runs; the registrar gives its ids back
            message.reply.set_error(shed)
            return
        token = LOADING.set(LoadContext(self.registrar, message.resource_id, message.chain))
        traced = traces.attach(message.trace) if message.trace else None
        began = runtime.monotonic()
        try:
            try:
                response = self.load(message.request)
            finally:
                self.ran(runtime.monotonic() - began)
            _refuse_awaitable(response)
            if self.persisted:
                check_picklable(response, "the response")
        except BaseException as exc:  # noqa: BLE001 - any exception fails the load (rule 4)
            message.reply.set_error(load_error(self.registrar, self.name, exc))
        else:
            message.reply.set_result(response)
        finally:
            if traced is not None:
                traces.detach(traced)
            LOADING.reset(token)

    def _unload(self, message: RunUnload) -> None:
        traced = traces.attach(message.trace) if message.trace else None
        try:
            self.unload(message.request, message.response)
        except BaseException as exc:  # noqa: BLE001 - logged by the registrar, never lost
            message.reply.set_error(exc)
        else:
            message.reply.set_result(None)
        finally:
            if traced is not None:
                traces.detach(traced)


def _refuse_awaitable(response: Any) -> None:
    """A plain `load` that returned an awaitable fails (`TypeError`): nobody would await it.
    It is closed (no "never awaited" warning)."""
    if not inspect.isawaitable(response):
        return
    close = getattr(response, "close", None)
    if close is not None:
        close()
    raise TypeError(
        "load returned an awaitable: make it a coroutine function (async def) for the "
        "registrar to await it"
    )


# -- releasing -------------------------------------------------------------------------


class Unloading:
    def __init__(self, registrar: ProviderRecord) -> None:
        self.registrar = registrar
        # consumer -> the round of the `Reconcile` asked of it (`Presence.lose`), the ids
        # it held here then and its latest run heard of here then, until it came
        self.asked: dict[str, tuple[int, frozenset[str], str]] = {}

    def expect(self, origin: str, round_: int, held: frozenset[str]) -> None:
        """Consumer `origin` was asked for a `Reconcile` by round `round_` (`Presence`), holding
        `held` here: kept until it comes (or a later run's; not one its lost run sent)."""
        self.asked[origin] = (round_, held, self.registrar.lives.newest(origin))

    def expected(self, origin: str) -> tuple[int, frozenset[str], str] | None:
        return self.asked.get(origin)

    def not_expected(self, origin: str) -> None:
        self.asked.pop(origin, None)

    def on_unload(self, message: Unload, reply: Reply) -> None:
        """Release the id; the answer carries the statuses still on their way to it (rule 9:
        they travel on another connection and may come after it), also with an `UnloadOverran`."""
        query_id, unacked = message.query_id, self.registrar.unacked

        def answered(_value: Any, error: BaseException | None) -> None:
            carried = unacked.of(query_id)
            overran = isinstance(error, CallTimeoutError)  # (unknown: released by a killed life)
            if isinstance(error, CallTimeoutError | UnknownQueryError) and (overran or carried):
                reply.set_result(UnloadOverran(carried, error))
            elif error is not None:
                reply.set_error(error)
            else:
                reply.set_result(carried)

        if self.held_by_another(query_id, message.origin_rr):
            reply.set_error(
                UnknownQueryError(
                    f"query id {query_id!r} is not held by {message.origin_rr!r} at "
                    f"{self.registrar.name!r}: another registrar's call used it"
                )
            )
            return
        self.release(query_id, CallbackReply(answered), "unload", message.trace)

    def on_abandon(self, message: Abandon, reply: Reply) -> None:
        kept = message.withdrawn and message.query_id in self.registrar.provider.retried_held
        if not kept and not self.held_by_another(message.query_id, message.origin_rr):
            self.release(message.query_id, None, "abandoned")
        reply.set_result(None)  # (a consumer's stop waits for it; a tell's goes nowhere)

    def held_by_another(self, query_id: str, origin_rr: str) -> bool:
        """Whether `query_id` is held (or loading) here for a registrar other than `origin_rr`:
        only its caller gives an id back (rule 2)."""
        holder = self.registrar.provider.origin_under_way(query_id)
        catalog = self.registrar.catalog
        if holder is None and catalog.has_consumer(query_id):
            holder = catalog.resource_of(query_id).consumers[query_id]
        return holder is not None and holder != origin_rr

    def holds_of(self, origin_rr: str) -> bool:
        return bool(self.registrar.catalog.consumers_from(origin_rr))

    def give_up_loads_of(self, origin_rr: str) -> None:
        """Give up the loads of consumer `origin_rr` under way here (each answered or unloaded)."""
        for query_id in self.registrar.provider.under_way_of(origin_rr):
            self.registrar.provider.give_up(query_id)

    def release_all_of(self, origin_rr: str, only: frozenset[str] | None = None) -> None:
        """Consumer `origin_rr` is gone for good: release every id it held here (or `only`
        these), and give up its loads under way (each unloaded once it ends)."""
        if only is None:
            self.give_up_loads_of(origin_rr)
        for query_id in self.registrar.catalog.consumers_from(origin_rr):
            if only is not None and query_id not in only:
                continue
            if self.registrar.catalog.has_consumer(query_id):  # (a release may have cascaded)
                self.release(query_id, None, "death watch")

    def release(self, query_id: str, reply: Reply | None, reason: str, trace: str = "") -> None:
        """Release consumer id `query_id` (rules 7-8); answer `reply` when it is done.

        `reason`: what `ConsumerReleased` says; `trace`: its `Unload`'s traceparent. While the
        backup cannot be written an `Unload` is refused; a give-up (`reply` is `None`) is
        carried out and written with the next write that succeeds.
        """
        unwritable = self.registrar.unwritable() if reply is not None else None
        if unwritable is not None:
            reply.set_error(unwritable)  # type: ignore[union-attr]
            return
        if self.registrar.provider.give_up(query_id):  # its load had not finished: not held
            if reply is not None:
                reply.set_result(None)
            return
        catalog = self.registrar.catalog
        try:
            resource = catalog.resource_of(query_id)
        except UnknownQueryError as exc:
            if reply is not None:
                reply.set_error(exc)
            return
        origin = resource.consumers[query_id]
        catalog.release(query_id)
        self.registrar.provider.retried_held.discard(query_id)
        shared = self.registrar
        told = (
            (events.ConsumerReleased(shared.name, resource.id, query_id, origin, reason, trace),)
            if shared.events.active
            else ()
        )
        step = shared.config.steps.unloads  # (a copy passed in: `RegistrarConfig.steps`)
        last = not resource.consumers if step is None else step(frozenset(resource.consumers))
        if reply is not None and not last and resource.state is ResourceState.LOADED:
            answer = reply  # (not the last: answered once written, with the rest of the turn)

            def undo(failed: CatalogWriteError) -> None:  # not durable: nothing changes
                if not catalog.has_consumer(query_id) and resource.id in catalog.resources:
                    catalog.add_consumer(resource.id, query_id, origin)
                answer.set_error(failed)

            shared.commit_then(
                *told, ok=lambda: answer.set_result(None), undo=undo, refuse=answer.set_error
            )
            return
        if last and resource.state is ResourceState.LOADED:  # one commit with its unload mark
            self.registrar.teardown.unload_resource(
                resource, reply, trace, released=(query_id, origin, told)
            )
            return
        failed = shared.commit(*told)  # (written with it)
        if failed is not None and reply is not None:  # not durable: nothing changes
            catalog.add_consumer(resource.id, query_id, origin)
            shared.commit()
            reply.set_error(failed)
            return
        if failed is not None:  # a give-up: carried out, written with the next write
            shared.publish(*told)
        if reply is not None:
            reply.set_result(None)

    def ask_to_reconcile(self, swept: set[str]) -> None:
        """This registrar serves (again): ask every registrar holding ids here to `Reconcile`,
        release those of one stopped for good meanwhile, and with a backup tell every other
        registrar too (it may hold ids this one lost, rule 20). `swept`: holders in the backup."""
        origins = self.registrar.catalog.consumer_origins() | swept
        for origin in sorted(origins):
            self.ask_holder(origin)
        if self.registrar.saver.store is not None and not self.registrar.announced:
            self.ask_everyone(set(origins))  # (announced: its supervisor tells everyone)

    def ask_holder(self, origin: str) -> None:
        """Ask consumer `origin` for a `Reconcile`, answered: stopped (also after the ask left:
        its stop could not give back what it held here) it holds nothing here (rule 12), unless
        a later run of it was heard of since (it reconciles for itself). Only its own stop says
        so: not this process's leaving the system. Reads no row: a lazy restore stays lazy."""
        asked = self.registrar.lives.newest(origin)

        def answered(_: Any, error: BaseException | None) -> None:
            if (
                isinstance(error, RegistrarStoppedError)
                and error.registrar == origin
                and self.registrar.lives.newest(origin) == asked
            ):
                self.release_stopped(origin)

        self.registrar.send(origin, functools.partial(self.ask, origin), answered)

    def ask(self, origin: str, reply: Reply | None = None) -> ReconcileAsk:
        """A `ReconcileAsk` for consumer `origin`, with the round of the ask standing for it
        (`Presence.ask_consumer`), so that its answer clears that ask too (`on_reconcile`)."""
        round_ = self.asked[origin][0] if origin in self.asked else 0
        return ReconcileAsk(
            self.registrar.name, life=self.registrar.life, round=round_, reply=reply
        )

    def ask_everyone(self, asked: set[str]) -> None:
        """Tell every registrar not in `asked` that this one (re)started: holders reconcile."""
        for name in sorted(DIRECTORY.names() - asked - {self.registrar.name}):
            with contextlib.suppress(RrError):
                DIRECTORY.lookup(name).tell(
                    ReconcileAsk(self.registrar.name, holds_yours=False, life=self.registrar.life)
                )

    def release_stopped(self, origin: str) -> None:
        """Consumer `origin` was stopped for good while this one was down or cut off (before
        it could give back what it held here): release its ids (rule 12)."""
        ids = self.registrar.catalog.consumers_from(origin)
        if ids:
            logger.warning(
                "registrar %s: consumer %s was stopped while this registrar was down or cut "
                "off; releasing the %d ids it held here",
                self.registrar.name,
                origin,
                len(ids),
            )
        for query_id in ids:
            if self.registrar.catalog.has_consumer(query_id):  # (a release may have cascaded)
                self.release(query_id, None, "consumer stopped")

    def on_reconcile(self, message: Reconcile, reply: Reply) -> None:
        """Release the ids of `origin_rr` it no longer holds; name those held here unknown.

        An id whose load is still under way here (waiting, parked, matched; not given up) is
        neither; one `origin_rr` does not list is given up (its caller's run died before the
        answer: presumed abort, or gave it back). The `Load`s of runs of `origin_rr`
        earlier than the one that sent it are refused from now on (`Lives`).
        """
        catalog = self.registrar.catalog
        held = set(message.held)
        asked = self.asked.get(message.origin_rr)
        if asked is not None and (  # (asked by `Presence.lose`: the answer, or a later run's;
            # none heard of since this run began: only the answer, to this run's ask)
            (message.round, message.ask_life) == (asked[0], self.registrar.life)
            or not message.life
            or (asked[2] != "" and life_order(message.life) > life_order(asked[2]))
        ):
            del self.asked[message.origin_rr]
        self.registrar.lives.reconciled(message.origin_rr, message.life)
        for query_id in self.registrar.provider.under_way_of(message.origin_rr):
            if query_id not in held:
                self.registrar.provider.give_up(query_id)
        mine = catalog.consumer_ids_from(message.origin_rr)
        step = self.registrar.config.steps.reconcile  # (a copy passed in: `config.steps`)
        told: tuple[str, ...] | None = None
        if step is None:
            stale = sorted(mine - held)
        else:
            gone, unknown_ids = step(
                frozenset(mine), frozenset(held), self.registrar.provider.under_way()
            )
            stale, told = sorted(set(gone) & mine), tuple(sorted(unknown_ids))
        if stale:
            logger.warning(
                "registrar %s: %s no longer holds %d of its ids here (released while this "
                "registrar was down, or lost in its own restart): releasing them",
                self.registrar.name,
                message.origin_rr,
                len(stale),
            )
        for query_id in stale:
            if catalog.has_consumer(query_id):  # (still: a release above may have cascaded)
                self.release(query_id, None, "reconcile")
        if told is None:  # (else a classroom's copy's answer)
            under_way = self.registrar.provider.under_way()
            told = tuple(q for q in message.held if q not in mine and q not in under_way)
        reply.set_result(Reconciled(told, self.registrar.life))  # (which run answered)


# -- teardown --------------------------------------------------------------------------

UNLOAD = "unload"
"""In a classroom's `release_order`: where the resource's own unload runs."""


class Teardown:
    def __init__(self, registrar: ProviderRecord) -> None:
        self.registrar = registrar
        self.unload_waiters: dict[str, list[Reply]] = {}  # resource id -> who waits for it
        # server name -> unloads of restored resources waiting for it to be registered
        self.parked_unloads: dict[str, list[Callable[[], None]]] = {}
        self.gone: dict[str, list[Callable[[], None]]] = {}  # id -> what runs when it is gone
        # resource id -> resource, of the unloads under way (not those parked)
        self.under_way: dict[str, Resource] = {}
        self.idle: list[Callable[[], None]] = []  # what runs once none is under way

    def unload_resource(
        self,
        resource: Resource,
        reply: Reply | None,
        trace: str = "",
        *,
        released: tuple[str, str, tuple[events.Event, ...]] | None = None,
    ) -> None:
        """The last consumer left: release the dependencies, then run `unload` (rule 7).

        `released`: that consumer's release, written in one transaction with the resource's
        `UNLOADING` mark (never a resource nobody holds and nobody unloads); not written, an
        `Unload` (`reply`) undoes both and fails. `trace`: the last `Unload`'s traceparent.
        """
        if not self.mark_unloading(resource, reply, released):
            return
        self.unload_waiters[resource.id] = [] if reply is None else [reply]
        self.under_way[resource.id] = resource

        def run_unload() -> None:
            self.under_way[resource.id] = resource
            server = self.registrar.servers.get(resource.server)
            if server is None and self.registrar.servers_settled:  # setup did not bring it back
                unloaded(None, None)
                return
            if server is None:  # restored, and no one has registered the server yet
                del self.under_way[resource.id]
                self.parked_unloads.setdefault(resource.server, []).append(run_unload)
                self.check_idle()
                return
            done = self.registrar.come_back(unloaded)
            timeout = self.registrar.config.unload_timeout
            server.ref.tell(RunUnload(resource.request, resource.response, done, timeout, trace))

        def unloaded(_: Any, error: BaseException | None) -> None:
            overdue = isinstance(error, CallTimeoutError)
            if overdue:  # it hangs: the resource is dropped as failed, its callers told
                logger.error(
                    "registrar %s: %s; resource %s (request %s) is dropped as failed, and "
                    "whatever it still holds is the server's to clean up",
                    self.registrar.name,
                    error,
                    resource.id,
                    describe(resource.request),
                )
            elif error is not None:
                logger.error(
                    "unload callback of '%s/%s' raised; the resource is released anyway",
                    self.registrar.name,
                    resource.server,
                    exc_info=error,
                )
            self.remove_resource(resource, unloaded=True)
            for ids in later:  # (a classroom's copy of `release_order`: after the unload)
                self.registrar.releases.release_dependencies(
                    resource.id, lambda: None, only=ids, trace=trace
                )
            for waiting in self.unload_waiters.pop(resource.id):
                if overdue:
                    waiting.set_error(error)  # type: ignore[arg-type]
                else:
                    waiting.set_result(None)
            self.under_way.pop(resource.id, None)
            self.check_idle()

        later: list[set[str]] = []  # the dependencies to release after the unload
        step = self.registrar.config.steps.release_order  # (a copy passed in: `config.steps`)
        if step is None:
            self.registrar.releases.release_dependencies(resource.id, run_unload, trace=trace)
            return
        held = [r.query.id for r in self.registrar.catalog.dependencies(resource.id)]
        order = list(step(tuple(held)))
        cut = order.index(UNLOAD)
        later.append(set(order[cut + 1 :]) & set(held))
        self.registrar.releases.release_dependencies(
            resource.id, run_unload, only=set(order[:cut]), trace=trace
        )

    def mark_unloading(
        self,
        resource: Resource,
        reply: Reply | None,
        released: tuple[str, str, tuple[events.Event, ...]] | None,
    ) -> bool:
        """Write `resource` `UNLOADING`, with its last consumer's release if `released`;
        `False`: that release was an `Unload`, not written, undone and `reply` failed."""
        shared = self.registrar
        shared.probe("unload_resource", resource)
        shared.catalog.begin_unload(resource.id)
        told = () if released is None else released[2]
        failed = shared.commit(*told)
        if failed is not None and released is not None and reply is not None:
            query_id, origin, _ = released  # not durable: nothing changes
            shared.catalog.cancel_unload(resource.id)
            shared.catalog.add_consumer(resource.id, query_id, origin)
            shared.commit()
            reply.set_error(failed)
            return False
        if failed is not None:  # (a give-up's events published all the same)
            shared.publish(*told)
        return True

    def busy(self) -> list[Resource]:
        """The resources whose unload is under way (not those parked)."""
        return list(self.under_way.values())

    def when_idle(self, then: Callable[[], None]) -> None:
        self.idle.append(then)
        self.check_idle()

    def check_idle(self) -> None:
        while not self.under_way and self.idle:
            self.idle.pop(0)()

    def remove_resource(self, resource: Resource, *, unloaded: bool = False) -> None:
        """Forget a resource that is gone; serve the loads parked behind its unload. An unload
        is written at once (a restore would run it again), with its `ResourceUnloaded`."""
        shared = self.registrar
        if resource.consumers and shared.config.steps.unloads is not None:  # a copy unloaded
            for query_id in list(resource.consumers):  # it under them: they lose it
                shared.catalog.release(query_id)
        shared.catalog.remove_resource(resource.id)
        told = (
            (events.ResourceUnloaded(shared.name, resource.server, resource.id),)
            if unloaded and shared.events.active
            else ()
        )
        if shared.commit(*told, now=unloaded) is not None:  # pending: the next write tries
            shared.publish(*told)  # (it was unloaded all the same)
        for then in self.gone.pop(resource.id, ()):  # e.g. loads parked behind its unload
            then()
        server = self.registrar.servers.get(resource.server)
        if (
            server is not None
            and server.closing
            and not self.registrar.yielding  # (a yield may be given up: it serves on)
            and not self.registrar.catalog.resources_of(server.name)
        ):
            del self.registrar.servers[server.name]
            server.ref.stop(block=False)

    def wait_for_unload(self, resource: Resource, reply: Reply) -> None:
        if resource.id in self.unload_waiters:
            self.unload_waiters[resource.id].append(reply)
        else:
            reply.set_result(None)

    def run_parked(self, server: str) -> None:
        for run_unload in self.parked_unloads.pop(server, ()):
            run_unload()

    def settle_parked(self) -> None:
        for server, unloads in list(self.parked_unloads.items()):
            if server not in self.registrar.servers:  # setup did not bring it back: release anyway
                logger.warning(
                    "registrar %s: server %r was not registered by setup; its restored "
                    "resources are released without their unload callback",
                    self.registrar.name,
                    server,
                )
                del self.parked_unloads[server]
                for run_unload in unloads:
                    run_unload()

    def when_gone(self, rid: str, then: Callable[[], None]) -> None:
        self.gone.setdefault(rid, []).append(then)

    def fail_waiting(self, error: RrError) -> None:
        for replies in self.unload_waiters.values():
            for reply in replies:
                reply.set_error(error)


# -- servers ---------------------------------------------------------------------------


def _log_failure(
    what: str,
    then: Callable[[], None],
    refused: list[ConfigError],
    _: Any,
    error: BaseException | None,
) -> None:
    """A continuation that logs a failed answer, then runs `then()`; a message too large
    for its receiver (`ConfigError`) is added to `refused`."""
    if error is not None:
        logger.warning("%s failed: %s", what, error)
        if isinstance(error, ConfigError):
            refused.append(error)
    then()


class Servers:
    def __init__(self, registrar: ProviderRecord) -> None:
        self.registrar = registrar

    def on_fetch(self, message: Fetch, reply: Reply) -> None:
        if message.server not in self.registrar.servers:
            reply.set_error(
                UnknownServerError(
                    f"no resource server '{self.registrar.name}/{message.server}'"
                    + _known_names(
                        message.server,
                        (n for n, s in self.registrar.servers.items() if not s.closing),
                    )
                )
            )
            return
        reply.set_result(
            [
                query
                for query in self.registrar.catalog.server_queries(
                    message.server, self.registrar.name
                )
                if query.origin_rr == message.origin_rr
            ]
        )

    def server(self, name: str) -> Server:
        """The open server `name`; `UnknownServerError` if none (or it is closing)."""
        server = self.registrar.servers.get(name)
        if server is None or server.closing:
            raise UnknownServerError(
                f"no resource server '{self.registrar.name}/{name}'"
                + _known_names(
                    name, (n for n, s in self.registrar.servers.items() if not s.closing)
                )
            )
        return server

    def on_register_server(self, message: RegisterServer, reply: Reply) -> None:
        name = message.name
        if name in self.registrar.servers:
            raise DuplicateNameError(
                f"resource server '{self.registrar.name}/{name}' already exists"
            )
        pace = Pace()
        ref = ServerActor.start(
            self.registrar.name,
            name,
            message.load,
            message.unload,
            self.registrar.workers,
            persisted=self.registrar.saver.store is not None,
            pace=pace,
        )
        self.registrar.servers[name] = Server(
            name,
            ref,
            message.on_status,
            label=message.label,
            max_pending=message.max_pending,
            pace=pace,
        )
        self.registrar.teardown.run_parked(name)
        reply.set_result(None)

    def on_unregister_server(self, message: UnregisterServer, reply: Reply) -> None:
        name = message.name
        server = self.server(name)
        server.closing = True
        resources = [
            r for r in self.registrar.catalog.resources_of(name) if r.state is ResourceState.LOADED
        ]

        def finish() -> None:
            if not self.registrar.catalog.resources_of(name) and name in self.registrar.servers:
                del self.registrar.servers[name]
                server.ref.stop(block=False)
            reply.set_result(None)

        join = Join(finish)
        for resource in resources:
            self.close_resource(resource, join.add())
        join.seal()

    def give_up_all(self, then: Callable[[], None]) -> None:
        """This registrar yields its name (rule 22): close every server, release every consumer
        id unsaid, unload each resource (loads and unloads under way waited for), then `then()`."""
        join = Join(then)
        for server in list(self.registrar.servers.values()):
            server.closing = True
            for resource in list(self.registrar.catalog.resources_of(server.name)):
                if resource.state is ResourceState.LOADED:
                    self.give_up(resource, join.add())
                elif resource.state is ResourceState.UNLOADING:
                    self.registrar.teardown.wait_for_unload(
                        resource, self.registrar.come_back(join.add())
                    )
                else:  # loading: refused when it finishes, then unloaded
                    self.registrar.teardown.when_gone(resource.id, join.add())
        join.seal()

    def give_up(self, resource: Resource, then: Callable[[], None]) -> None:
        self.release_all(resource, "name yielded")
        self.registrar.teardown.unload_resource(
            resource, self.registrar.come_back(lambda *_: then())
        )

    def release_all(self, resource: Resource, reason: str) -> None:
        """Release every consumer of `resource` here, each published with `reason`."""
        released = list(resource.consumers.items())
        for query_id, _ in released:
            self.registrar.catalog.release(query_id)
        if self.registrar.events.active:
            for query_id, origin in released:
                self.registrar.events.publish(
                    events.ConsumerReleased(
                        self.registrar.name, resource.id, query_id, origin, reason
                    )
                )

    def close_resource(self, resource: Resource, then: Callable[[], None]) -> None:
        self.registrar.probe("close_resource", resource)
        query_id = next(iter(resource.consumers))
        update = StatusUpdate(
            query_id,
            Status.FATAL,
            "resource server was unregistered",
            f"{self.registrar.name}/{resource.server}",
        )

        def revoke_and_unload() -> None:
            done = self.registrar.come_back(lambda *_: then())
            if resource.state is not ResourceState.LOADED:  # its consumers left meanwhile
                self.registrar.teardown.wait_for_unload(resource, done)
                return
            for origin, ids in consumers_by_origin(resource).items():
                with contextlib.suppress(RrError):
                    DIRECTORY.lookup(origin).tell(Revoke(ids))
            self.release_all(resource, "server unregistered")
            self.registrar.teardown.unload_resource(resource, done)

        event = runtime.new_id()
        if self.registrar.events.active:
            self.registrar.events.publish(
                events.StatusSent(
                    self.registrar.name, query_id, update.status, update.message, event
                )
            )
        # the FATAL's acknowledgements may complete on any thread: come back to this one
        back = self.registrar.come_back(lambda *_: revoke_and_unload())
        self.registrar.status.notify(
            resource, update, event, query_id, lambda: back.set_result(None)
        )

    def on_update_response(self, message: UpdateResponse, reply: Reply) -> None:
        query_id, response = message.query_id, message.response
        resource = self.registrar.catalog.resource_of(query_id)
        self.registrar.catalog.set_response(resource.id, response)
        show_response(self.registrar, resource)
        self.registrar.commit()
        refused: list[ConfigError] = []  # (a consumer that cannot take it: too large)

        def then() -> None:
            if refused:
                reply.set_error(refused[0])
            else:
                reply.set_result(None)

        join = Join(then)
        for origin, ids in consumers_by_origin(resource).items():
            self.registrar.send(
                origin,
                functools.partial(ResponseUpdated, ids, response),
                functools.partial(
                    _log_failure, f"telling {origin} about a new response", join.add(), refused
                ),
            )
        join.seal()

    def on_list_server_queries(self, message: ListServerQueries, reply: Reply) -> None:
        self.server(message.server)
        reply.set_result(self.registrar.catalog.server_queries(message.server, self.registrar.name))
