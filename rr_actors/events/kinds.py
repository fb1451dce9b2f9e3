"""The event kinds: one frozen dataclass per thing a tree or a registrar does.

Each has its own fields first, then the keyword-only stamps said once in `_Stamped` (`at`, `host`,
`hlc`) and `_Numbered` (`pid`, `seq`: all but the supervisor's child events). `_kind` puts them in
the order of `_STAMPS`: the key order of the JSON line (`lines.to_line`), the outbox row, the pickle
and the `repr`. A new kind: its class here (`@_kind`), in `Event`, and its line in `text.describe`.
"""

from __future__ import annotations

import dataclasses
import inspect
import itertools
import os
import socket
from typing import Any, TypeAlias, TypeVar, cast, dataclass_transform

from rr_actors._core import hlc as _hlc
from rr_actors._core import runtime
from rr_actors._platform import forkserver
from rr_actors._types import Status

__all__ = [
    "LISTED_ROWS",
    "CallAnswered",
    "CallFailed",
    "CallWithdrawn",
    "CatalogRestored",
    "ChildExited",
    "ChildRestarted",
    "ChildStarted",
    "ConsumerAdded",
    "ConsumerReleased",
    "Event",
    "EventsDropped",
    "EventsUnpublished",
    "InDoubt",
    "LoadFailed",
    "ManagerOverloaded",
    "QueriesFetched",
    "QueryForgotten",
    "RegistrarStopped",
    "ResourceLoaded",
    "ResourceUnloaded",
    "Rows",
    "ServerOverloaded",
    "ServerQueriesListed",
    "ShareAdmitted",
    "ShareRefused",
    "StatusAnswered",
    "StatusDelivered",
    "StatusHandled",
    "StatusSent",
    "SupervisorGaveUp",
    "UnloadCutShort",
]


class _Host:
    """The member name this process's events carry (a simulated process: its creator's)."""

    def __init__(self, name: str) -> None:
        self.name = name


def _inherited() -> _Host:
    return _Host(_HOST.name)


_HOST: _Host = runtime.process_state(_Host(socket.gethostname()), _inherited)


def _current_host() -> str:
    return _HOST.name


def this_host() -> str:
    """The member name events of this process carry (`host`): see `set_host`."""
    return _HOST.name


def set_host(name: str) -> None:
    """Name this process's host in the events it builds from now on (`host`): a TLS member's
    certificate common name; until then `socket.gethostname()`."""
    _HOST.name = name


_counter = itertools.count(1)
_numbering = False


def _next_seq() -> int:
    """The next number of this process's events, or 0 where events are not numbered."""
    if not _numbering:
        return 0
    return next(_counter)


def number_events() -> None:
    """Number the events this process builds from now on (`seq`; a manager process does)."""
    global _numbering
    _numbering = True


class _Pid:
    """The pid this process's events carry, read at its first event (one per simulated process)."""

    def __init__(self) -> None:
        self.pid = 0  # (not read yet)


_PID = runtime.process_state(_Pid(), _Pid)


def _current_pid() -> int:
    """`os.getpid()` without a system call per event (kept right across `fork`)."""
    pid = _PID.pid
    if not pid:
        pid = _PID.pid = runtime.getpid()
    return pid


def _forked() -> None:
    global _counter, _numbering
    _PID.pid = os.getpid()
    _counter = itertools.count(1)
    _numbering = False


forkserver.after_fork_in_child("the events' pid", _forked)


# -- the stamps every kind carries ----------------------------------------------------------

_T = TypeVar("_T")

_STAMPS = ("at", "pid", "seq", "host", "hlc")
_STAMPED: dict[type, dict[str, tuple[str, Any]]] = {}
"""Each stamps class's own stamps: name -> (annotation, default factory)."""


@dataclass_transform(frozen_default=True, kw_only_default=True)
def _stamps(cls: type[_T]) -> type[_T]:
    """Take the fields of `cls` as stamps for the kinds deriving from it (`TypeError`: one not
    in `_STAMPS`): a frozen keyword-only dataclass to a type checker, at run time without them."""
    annotations = inspect.get_annotations(cls)
    if unknown := sorted(annotations.keys() - set(_STAMPS)):
        raise TypeError(f"{cls.__name__}: {unknown} are not stamps (see _STAMPS)")
    _STAMPED[cls] = {
        name: (annotation, getattr(cls, name).default_factory)
        for name, annotation in annotations.items()
    }
    for name in annotations:
        delattr(cls, name)
    del cls.__annotations__
    return cls


@dataclass_transform(frozen_default=True)
def _kind(cls: type[_T]) -> type[_T]:
    """`cls` as a kind: a frozen slotted dataclass, its own fields first, then its bases' stamps
    (`TypeError`: it declares a field named as a stamp it inherits)."""
    stamps: dict[str, tuple[str, Any]] = {}
    for base in cls.__mro__[1:]:
        stamps.update(_STAMPED.get(base, {}))
    own = inspect.get_annotations(cls)
    if clash := sorted(stamps.keys() & own.keys()):
        raise TypeError(f"{cls.__name__}: {clash} are stamps it inherits")
    namespace = {k: v for k, v in vars(cls).items() if k not in ("__dict__", "__weakref__")}
    namespace["__qualname__"] = cls.__qualname__
    namespace["__annotations__"] = annotations = {**own, "_": "dataclasses.KW_ONLY"}
    for name in _STAMPS:
        if name in stamps:
            annotation, factory = stamps[name]
            annotations[name] = annotation
            namespace[name] = dataclasses.field(default_factory=factory)
    # Not derived from its stamps classes: a frozen `__init__`'s setattr walks Python bases.
    bases = tuple(base for base in cls.__bases__ if base not in _STAMPED) or (object,)
    kind = cast("type[_T]", type(cls.__name__, bases, namespace))
    return dataclasses.dataclass(frozen=True, slots=True)(kind)


@_stamps
class _Stamped:
    """What every event carries, after its own fields (keyword-only).

    Attributes:
        at: when it happened, wall clock (`time.time()` seconds).
        host: the member name of the host it happened on (see `set_host`).
        hlc: its hybrid logical clock stamp (`rr_actors._core.hlc`): sorting several hosts'
            events by it puts every cause before its effects.
    """

    at: float = dataclasses.field(default_factory=_hlc.CLOCK.wall)
    host: str = dataclasses.field(default_factory=_current_host)
    hlc: int = dataclasses.field(default_factory=_hlc.CLOCK.now)


@_stamps
class _Numbered(_Stamped):
    """What every event but a supervisor's child events carries too (keyword-only).

    Attributes:
        pid: the process it happened in (the registrar's, for a registrar's event).
        seq: its number among its process's events (1, 2, 3, ... in a manager process, where a
            gap shows a lost event: `number_events`); 0 where events are not numbered.
    """

    pid: int = dataclasses.field(default_factory=_current_pid)
    seq: int = dataclasses.field(default_factory=_next_seq)


# -- supervision ----------------------------------------------------------------------------


@_kind
class ChildStarted(_Stamped):
    """A supervisor started a child (at its start, or when added), and it serves; after an exit
    it is a [`ChildRestarted`][rr_actors.events.ChildRestarted].

    Attributes:
        child: name of the child (a manager or a nested supervisor).
        pid: the child's process (the supervisor's for a thread manager or a supervisor).
    """

    supervisor: str
    child: str
    pid: int


@_kind
class ChildExited(_Stamped):
    """A child's incarnation ended (crashed, killed, exited, stopped), before any restart.

    Attributes:
        pid: the process of the incarnation that ended (as `ChildStarted.pid`).
        reason: why it ended, for people (as `ChildInfo.last_exit`).
        restart: the child's restart type; `""` before schema 4.
        normal: it ended normally (OTP's `normal`/`shutdown`: a `transient` child stays down).
        stopped: the supervisor stopped it itself: not an exit its intensity counts.
        max_restarts: the supervisor's intensity: more restarts than this ...
        period: ... within this many seconds and it gives up (OTP).
        strategy: the supervisor's restart strategy; `""` before schema 6.
        children: the supervisor's children in start order; `()` before schema 6.
        at: when the supervisor saw it.
    """

    supervisor: str
    child: str
    pid: int
    reason: str
    restart: str = ""
    normal: bool = False
    stopped: bool = False
    max_restarts: int = 0
    period: float = 0.0
    strategy: str = ""
    children: tuple[str, ...] = ()


@_kind
class ChildRestarted(_Stamped):
    """A supervisor restarted a child after an exit, and the new incarnation serves.

    Attributes:
        pid: the new incarnation's process (as `ChildStarted.pid`).
        restart_s: seconds from the exit seen to serving again, backoff included.
    """

    supervisor: str
    child: str
    pid: int
    restart_s: float


@_kind
class SupervisorGaveUp(_Numbered):
    """A supervisor exceeded its restart intensity and stopped all its children (OTP).

    A nested one's parent treats it as a crashed child; the top one raises `SupervisorGaveUpError`.

    Attributes:
        supervisor: name of the supervisor that gave up.
        reason: why (the `SupervisorGaveUpError`'s message).
        max_restarts: its intensity: at most this many restarts ...
        period: ... within this many seconds.
    """

    supervisor: str
    reason: str
    max_restarts: int
    period: float


@_kind
class ManagerOverloaded(_Stamped):
    """A manager process answered its heartbeat late but excused (busy, or waiting for a CPU):
    not hung, not killed. At most one per ping.

    Attributes:
        manager: name of the manager.
        pid: its process.
        silent_s: seconds from the ping to its answer.
        bound_s: its `heartbeat_timeout` (seconds).
        excused_s: seconds of the silence that did not count against it.
        busy_s: seconds of it its registrar was seen busy (the rest: waiting for a CPU).
        queued: messages in its registrar's mailbox when last asked (-1: not asked).
    """

    supervisor: str
    manager: str
    pid: int
    silent_s: float
    bound_s: float
    excused_s: float
    busy_s: float
    queued: int


# -- provider side --------------------------------------------------------------------------


@_kind
class ResourceLoaded(_Numbered):
    """A server's `load` returned: a new resource is served (before its first consumer is written
    and answered; a duplicate request is a `ConsumerAdded` only).

    Attributes:
        resource_id: the new resource's id.
        query_id: the id of the query that caused the load (its first consumer).
        load_s: seconds the `load` took (its dependencies' loads included).
        digest: the catalog's digest of a request of plain values, else `None` (rule 1).
        label: the request's bounded label (`label(request)`, else a bounded `repr`), or `None`.
    """

    registrar: str
    server: str
    resource_id: str
    query_id: str
    load_s: float
    digest: int | None = None
    label: str | None = None
    trace: str = ""


@_kind
class LoadFailed(_Numbered):
    """A server's `load` raised (the call fails with `ResourceLoadError`), after what it had
    loaded was unloaded.

    Attributes:
        resource_id: the id the resource would have had.
        query_id: the id of the query that caused the load.
        error_type: `type(exc).__name__`.
        message: `str(exc)`.
    """

    registrar: str
    server: str
    resource_id: str
    query_id: str
    error_type: str
    message: str
    trace: str = ""


@_kind
class ResourceUnloaded(_Numbered):
    """A server's `unload` ran (or raised) after its last consumer went; written in the same
    transaction as the removal."""

    registrar: str
    server: str
    resource_id: str


@_kind
class ConsumerAdded(_Numbered):
    """A query became a consumer of a served resource, before the caller is answered.

    Attributes:
        query_id: the consumer's query id.
        consumer: name of the consumer registrar.
    """

    registrar: str
    resource_id: str
    query_id: str
    consumer: str
    trace: str = ""


@_kind
class ConsumerReleased(_Numbered):
    """A consumer id of a served resource was released; a `ResourceUnloaded` follows the last.

    Attributes:
        query_id: the released query id.
        consumer: name of the consumer registrar that held it.
        reason: `"unload"`, `"abandoned"` (its caller gave up), `"death watch"`,
            `"reconcile"`, `"consumer stopped"`, `"server unregistered"`, `"name yielded"`
            (rule 22) or `"refused"` (the load's commit failed or its server closed).
        trace: the `Unload`'s, as `CallAnswered.trace`.
    """

    registrar: str
    resource_id: str
    query_id: str
    consumer: str
    reason: str = "unload"
    trace: str = ""


# -- consumer side --------------------------------------------------------------------------


@_kind
class CallAnswered(_Numbered):
    """A consumer's call was answered: the consumer holds its query id until a `QueryForgotten`.

    Attributes:
        parent: the resource of this registrar whose `load` made the call (rule 5), or `None`.
        retry: the consumer already knew this id (rule 17): no second consumer.
        started: when the call was made, wall clock seconds; 0.0 if not known.
        trace: the W3C `traceparent` the call carried (`rr_actors_lab.otel`), `""` if untraced.
        caller_span: the id (16 hex) of the span current in the caller; `""` with `trace`.
    """

    registrar: str
    query_id: str
    serving_rr: str
    server: str
    parent: str | None = None
    retry: bool = False
    started: float = 0.0
    trace: str = ""
    caller_span: str = ""


@_kind
class CallFailed(_Numbered):
    """A consumer's call failed (not withdrawn): its caller got an error, and holds no id.

    Attributes:
        error_type: the error's type name.
        message: the error's message.
        may_have_executed: the provider went with the call in flight and may hold the id
            (rule 17): the consumer keeps it until it reconciled with the provider's restart.
        retry: as `CallAnswered.retry`.
        parent: as `CallAnswered.parent`: its load's end gives a kept id back (rule 17).
    """

    registrar: str
    query_id: str
    serving_rr: str
    server: str
    error_type: str
    message: str
    may_have_executed: bool = False
    retry: bool = False
    started: float = 0.0
    trace: str = ""
    caller_span: str = ""
    parent: str | None = None


@_kind
class CallWithdrawn(_Numbered):
    """A consumer's call was given up before its answer: what it added given back (rule 17).

    Attributes:
        reason: `"timeout"`, `"interrupted"` or `"registrar stopped"`.
    """

    registrar: str
    query_id: str
    serving_rr: str
    server: str
    reason: str = "timeout"
    started: float = 0.0
    trace: str = ""
    caller_span: str = ""


@_kind
class QueriesFetched(_Numbered):
    """A consumer fetched the ids it holds at a provider's server (`fetch_queries`, rule 10).

    Attributes:
        query_ids: the ids the answer listed, in its order.
        started: the `hlc` stamp when it began: the provider read between it and `hlc`.
    """

    registrar: str
    serving_rr: str
    server: str
    query_ids: tuple[str, ...] = ()
    started: int = 0


@_kind
class ServerQueriesListed(_Numbered):
    """A provider listed the queries its own server holds (`server_queries`, rule 10).

    Attributes:
        query_ids: the ids the answer listed, in its order.
        started: as `QueriesFetched.started`.
    """

    registrar: str
    server: str
    query_ids: tuple[str, ...] = ()
    started: int = 0


@_kind
class QueryForgotten(_Numbered):
    """A consumer forgot a query id it held.

    Attributes:
        query_id: the forgotten query id.
        reason: `"unload"`, `"unload unanswered"` (the provider releases it when it
            reconciles), `"dependency"`, `"stop"`, `"revoked"` (`FATAL`), `"provider lost"`
            (rule 19, `FATAL`), `"unknown at reconcile"` (rule 20, `FATAL`; also when a
            retry of it failed at a provider that ran a new load for it), `"late
            dependency"`, `"registrar stopped"`, `"withdrawn"` or `"in doubt"`.
        unload_sent: for a release, the `hlc` stamp its `Unload` left at; else 0.
        reconciled: with `unload_sent`, the stamp at which the last reconcile with its
            provider answered before had left (rule 20: a release before a restarted
            provider's reconcile owes no `FATAL`); 0 if none.
        trace: for an `unload`, as `CallAnswered.trace`.
        caller_span: with `trace`, as `CallAnswered.caller_span`.
    """

    registrar: str
    query_id: str
    serving_rr: str
    reason: str
    unload_sent: int = 0
    reconciled: int = 0
    trace: str = ""
    caller_span: str = ""


# -- status ---------------------------------------------------------------------------------


@_kind
class StatusSent(_Numbered):
    """A provider sent a status about a loaded resource (`send_status`), before delivery.

    Attributes:
        query_id: the query id `send_status` was given.
        message: the provider's free text.
        status_id: this send's id (a UUID4), named by each of its `StatusDelivered`.
        patience: seconds each callback it reaches may take (`None`: unbounded).
    """

    registrar: str
    query_id: str
    status: Status
    message: str
    status_id: str = ""
    patience: float | None = None


@_kind
class StatusDelivered(_Numbered):
    """A status reached one consumer: its client's status callback ran.

    Attributes:
        query_id: the receiver's own query id for the resource.
        hop: registrars the status crossed (1: a direct consumer of the sender).
        latency_s: seconds from `send_status` to this delivery, wall clock.
        status_id: its `StatusSent.status_id`; a query id gets each send once.
    """

    registrar: str
    query_id: str
    status: Status
    hop: int
    latency_s: float
    status_id: str = ""


@_kind
class StatusHandled(_Numbered):
    """A consumer's status callback returned (or raised), on its worker thread or loop.

    A checker judges rule 9 (`status-order`) with `arrived`, `began` and `opened`: an id's
    callbacks run one at a time in arrival order, the next early only once this one waited.

    Attributes:
        query_id: the receiver's own query id (the callback's `query.id`).
        status_id: its `StatusSent.status_id`.
        arrived: the callback's place in its process's arrival order (1, 2, ...).
        began: the `hlc` stamp as it began; it returned at `hlc`.
        opened: the stamp at which it first waited for a registrar, 0 if it never did.
    """

    registrar: str
    query_id: str
    status: Status
    status_id: str
    arrived: int
    began: int
    opened: int = 0


@_kind
class StatusAnswered(_Numbered):
    """A provider's `send_status` was answered (`StatusDelivery`), on the last answer's thread.

    Attributes:
        status_id: its `StatusSent.status_id`.
        reached: its consumer ids not given up on: a callback of each ran and returned first.
        gave_up: the consumer ids, at any hop, whose callback it gave up on (its patience).
    """

    registrar: str
    query_id: str
    status_id: str
    reached: tuple[str, ...] = ()
    gave_up: tuple[str, ...] = ()


@_kind
class UnloadCutShort(_Numbered):
    """A clean `stop()` gave up waiting (half its timeout) for an unload under way: the callback
    runs on, and the next start reports it `InDoubt` (`cut="unload"`, rule 16)."""

    registrar: str
    server: str
    resource_id: str


@_kind
class ServerOverloaded(_Numbered):
    """A server refused new loads at its `max_pending` (`bound`), `pending` of them queued or
    running: at its first refusal, then at most once a second, `refused` counting the calls it
    refused since its previous `ServerOverloaded`, this one included (shed loads are
    `LoadFailed`, `DeadlineExceededError`)."""

    registrar: str
    server: str
    pending: int
    bound: int
    refused: int


@_kind
class ShareRefused(_Numbered):
    """A server with room (`pending` < `bound`, its `max_pending`) refused a load of `consumer`
    holding `under_way` of them: past its `share` (`bound // consumers`, at least 1; `consumers`
    with loads there or refused within 2 s, it included), or behind `ahead` of those waiting
    (`waiting`: each other's loads under way; `firsts`: its first refusal; `()` before schema 9)
    with fewer, or as many and refused before `since` (its own first refusal, or now; the
    provider's `time.monotonic()`, seconds). One per refusal; at the bound, `ServerOverloaded`."""

    registrar: str
    server: str
    consumer: str
    pending: int
    under_way: int
    share: int
    consumers: int
    ahead: int
    bound: int
    since: float = 0.0
    waiting: tuple[int, ...] = ()
    firsts: tuple[float, ...] = ()


@_kind
class ShareAdmitted(_Numbered):
    """A server admitted a load of `consumer` while others waited there (as it decided: one whose
    request or record then fails is not started), on `ShareRefused`'s counts, but `ahead`."""

    registrar: str
    server: str
    consumer: str
    pending: int
    under_way: int
    share: int
    consumers: int
    bound: int
    since: float
    waiting: tuple[int, ...]
    firsts: tuple[float, ...]


# -- recovery and the stream itself ---------------------------------------------------------


@_kind
class InDoubt(_Numbered):
    """A restarted registrar found a load started but never committed (rule 16): at every restore
    until a `setup` offered it returned (`ResourceRegistrar.settle_in_doubt`).

    Attributes:
        query_id: the in-doubt resource's id.
        server: the server it belongs to (`""` in older events).
        cut: what the crash cut short: `"load"` or `"unload"` (`""`: not known).
    """

    registrar: str
    query_id: str
    server: str = ""
    cut: str = ""


@_kind
class EventsDropped(_Numbered):
    """Events were lost here, at this place in the stream.

    Attributes:
        count: how many events were lost in this gap.
        cause: `"full"` (a queue, a buffer or a bound on bytes), `"killed"` (a dead manager
            process's events not forwarded, counted by its supervisor) or `"refused"` (a
            batch no member's certificate sealed).
        pid: the process that lost them.
    """

    count: int
    cause: str = "full"


@_kind
class EventsUnpublished(_Numbered):
    """A killed manager process numbered these events and died before publishing them (in
    neither its journal nor its backup's outbox): no event is lost, the numbers are no gap.

    Attributes:
        seqs: the numbers no event took, ascending.
        pid: the process that numbered them.
    """

    seqs: tuple[int, ...]


# -- what a catalog holds -------------------------------------------------------------------

Rows: TypeAlias = tuple[tuple[str, ...], ...]
"""Rows of plain strings (what `CatalogRestored` and `RegistrarStopped` list)."""

LISTED_ROWS = 10_000
"""Rows a catalog event lists per kind; above it lists none (`complete` is `False`)."""


@_kind
class CatalogRestored(_Numbered):
    """A registrar with a backup started: what its catalog holds, before setup and any call.

    A checker re-synchronises here; in-doubt resources are listed, then reported `InDoubt`.

    Attributes:
        resources: `(resource id, server, state, digest, failed)` per served resource: `state`
            `"loaded"`, `"loading"` or `"unloading"`, `digest` in decimal or `""`, `failed`
            `"failed"` (reported `FATAL`) or `""`.
        consumers: `(query id, resource id, consumer registrar)` per consumer id.
        clients: `(query id, serving registrar, server, parent resource id or "")` per query
            this registrar holds.
        counts: `(resources, consumers, clients)`.
        complete: `False` when a kind had over `LISTED_ROWS` rows: none are listed.
        digest: SHA-256 (16 hex) of the sorted rows; `""` when they are not listed.
    """

    registrar: str
    resources: Rows
    consumers: Rows
    clients: Rows
    counts: tuple[int, ...] = (0, 0, 0)
    complete: bool = True
    digest: str = ""


@_kind
class RegistrarStopped(_Numbered):
    """A registrar stopped cleanly (rule 12): what its catalog still holds, as `CatalogRestored`."""

    registrar: str
    resources: Rows
    consumers: Rows
    clients: Rows
    counts: tuple[int, ...] = (0, 0, 0)
    complete: bool = True
    digest: str = ""


Event: TypeAlias = (
    ChildStarted
    | ChildExited
    | ChildRestarted
    | SupervisorGaveUp
    | ManagerOverloaded
    | ResourceLoaded
    | LoadFailed
    | ResourceUnloaded
    | ConsumerAdded
    | ConsumerReleased
    | CallAnswered
    | CallFailed
    | CallWithdrawn
    | QueriesFetched
    | ServerQueriesListed
    | QueryForgotten
    | StatusSent
    | StatusDelivered
    | StatusHandled
    | StatusAnswered
    | InDoubt
    | CatalogRestored
    | RegistrarStopped
    | UnloadCutShort
    | ServerOverloaded
    | ShareRefused
    | ShareAdmitted
    | EventsDropped
    | EventsUnpublished
)
"""Any event of this module (what a subscriber's callback receives)."""
