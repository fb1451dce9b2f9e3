"""The event kinds: one frozen dataclass per thing a tree or a registrar does.

Each has its own fields first, then the keyword-only stamps said once in `_Stamped` (`at`,
`host`, `hlc`: every kind) and `_Numbered` (`pid`, `seq`: every kind but the supervisor's
child events, whose `pid` is the child's). `_kind` puts the stamps after the own fields in
the order of `_STAMPS`: the order of the JSON line's keys (`lines.to_line`), of the outbox
row, of the pickled state and of the `repr`. Adding a kind: its class here (`@_kind`), in
the `Event` union, and its line in `text.describe`.
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
    "StatusDelivered",
    "StatusHandled",
    "StatusSent",
    "SupervisorGaveUp",
    "UnloadCutShort",
]


class _Host:
    """The member name this process's events carry (a simulated process starts with its
    creator's)."""

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
    """Name this process's host in the events it builds from now on (`host`).

    A member of a `ZenohNetwork` with `tls` names it by its certificate's common name; until
    then, and without TLS, it is `socket.gethostname()`.
    """
    _HOST.name = name


_counter = itertools.count(1)
_numbering = False


def _next_seq() -> int:
    """The next number of this process's events, or 0 where events are not numbered."""
    if not _numbering:
        return 0
    return next(_counter)


def number_events() -> None:
    """Number the events this process builds from now on (a manager process does).

    Each event then carries `seq` 1, 2, 3, ...: a gap in the forwarded stream is a lost event.
    """
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
    """Take the fields of `cls` as stamps for the kinds deriving from it.

    A frozen keyword-only dataclass to a type checker; at run time a plain class without them.

    Raises:
        TypeError: a field of `cls` is not named in `_STAMPS`.
    """
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
    """`cls` as a kind: a frozen slotted dataclass, its own fields first, then its bases' stamps.

    Raises:
        TypeError: `cls` declares a field named as a stamp it inherits.
    """
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
    # Not derived from its stamps classes at run time: `object.__setattr__`, which a frozen
    # `__init__` calls per field, walks the class's bases of Python classes each time.
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
    """A supervisor started a child (at its start, in order, or when added), and it serves.

    A start after an exit is a [`ChildRestarted`][rr_actors.events.ChildRestarted] instead.

    Attributes:
        supervisor: name of the supervisor.
        child: name of the child (a manager or a nested supervisor).
        pid: the child's process (the supervisor's own for a thread manager or a nested
            supervisor).
    """

    supervisor: str
    child: str
    pid: int


@_kind
class ChildExited(_Stamped):
    """A child's incarnation ended: it crashed, was killed, exited, or was stopped.

    Published by the supervisor when it sees the exit, before it decides on a restart.

    Attributes:
        supervisor: name of the supervisor.
        child: name of the child.
        pid: the process of the incarnation that ended (as `ChildStarted.pid`).
        reason: why it ended, for people (as `ChildInfo.last_exit`).
        restart: the child's restart type (`"permanent"`, `"transient"`, `"temporary"`); `""`
            in a line of schema 3 or older.
        normal: whether it ended normally (OTP's `normal`/`shutdown`: a `transient` child that
            ends so is not restarted).
        stopped: whether the supervisor stopped it itself (a sibling taken down, a give-up, a
            shutdown): not an exit its intensity counts.
        max_restarts: the supervisor's intensity: more restarts than this ...
        period: ... within this many seconds and it gives up (OTP).
        strategy: the supervisor's strategy (`"one_for_one"`, `"one_for_all"`,
            `"rest_for_one"`); `""` in a line of schema 5 or older.
        children: the supervisor's children in start order (the strategy stops them in
            reverse); `()` in a line of schema 5 or older.
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
        supervisor: name of the supervisor.
        child: name of the child.
        pid: the new incarnation's process (as `ChildStarted.pid`).
        restart_s: seconds from the supervisor seeing the exit to the new incarnation serving,
            backoff included.
    """

    supervisor: str
    child: str
    pid: int
    restart_s: float


@_kind
class SupervisorGaveUp(_Numbered):
    """A supervisor exceeded its restart intensity and stopped all its children (OTP).

    A nested supervisor's parent then treats it as one crashed child; the top supervisor raises
    `SupervisorGaveUpError` to whoever waits on it.

    Attributes:
        supervisor: name of the supervisor that gave up.
        reason: why, for people (the `SupervisorGaveUpError`'s message).
        max_restarts: its intensity: at most this many restarts ...
        period: ... within this many seconds.
    """

    supervisor: str
    reason: str
    max_restarts: int
    period: float


@_kind
class ManagerOverloaded(_Stamped):
    """A manager process answered its heartbeat late, overloaded: not hung, not killed.

    Published by its supervisor when a ping's answer came after more than the manager's
    `heartbeat_timeout` and the silence was excused (its registrar busy with other messages, or
    its threads waiting for a CPU); at most one per ping. A silence not excused ends in a kill
    (`ChildExited`, `"hung: ..."`).

    Attributes:
        supervisor: name of its supervisor.
        manager: name of the manager.
        pid: its process.
        silent_s: seconds from the ping to its answer.
        bound_s: its `heartbeat_timeout` (seconds).
        excused_s: seconds of the silence that did not count against it.
        busy_s: seconds of it its registrar was seen handling other messages (the rest of
            `excused_s` it waited for a CPU).
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
    """A server's `load` callback returned: a new resource is served.

    Published before the result is written and its first consumer answered (a kill in between:
    the restart reports it [`InDoubt`][rr_actors.events.InDoubt]). A duplicate request is a
    [`ConsumerAdded`][rr_actors.events.ConsumerAdded] only.

    Attributes:
        registrar: name of the provider registrar.
        server: name of the resource server that loaded it.
        resource_id: the new resource's id.
        query_id: the id of the query that caused the load (its first consumer).
        load_s: seconds the `load` callback took (its dependencies' loads included).
        digest: the catalog's digest of a request of plain values (`None` otherwise): equal
            digests at one registrar and server are equal requests (rule 1).
        label: the request's bounded display label: the server's `label(request)` (waited for
            at most `compare_timeout`; `"<label failed: ...>"` if it failed), else the
            catalog's bounded `repr`; `None` if it has none.
        trace: the W3C `traceparent` the call carried (as `CallAnswered.trace`).
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
    """A server's `load` callback raised; the call fails with `ResourceLoadError`.

    Published by the registrar whose `load` raised, after the sub-resources it had loaded were
    unloaded.

    Attributes:
        registrar: name of the provider registrar.
        server: name of the resource server whose `load` raised.
        resource_id: the id the resource would have had.
        query_id: the id of the query that caused the load.
        error_type: `type(exc).__name__`.
        message: `str(exc)`.
        trace: as `CallAnswered.trace`.
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
    """A server's `unload` callback ran (or raised): its last consumer released it.

    Published after its dependencies were released and its removal written, the event in the
    same transaction: the supervisor reads it from the backup's outbox after a SIGKILL.

    Attributes:
        registrar: name of the provider registrar.
        server: name of the resource server that served it.
        resource_id: the resource's id.
    """

    registrar: str
    server: str
    resource_id: str


@_kind
class ConsumerAdded(_Numbered):
    """A query became a consumer of a served resource (a new load or a duplicate request).

    Published when the id is recorded (with `save_on_modify`, in the same transaction), before
    the caller is answered.

    Attributes:
        registrar: name of the provider registrar.
        resource_id: the resource's id.
        query_id: the consumer's query id.
        consumer: name of the consumer registrar (the query's `origin_rr`).
        trace: as `CallAnswered.trace`.
    """

    registrar: str
    resource_id: str
    query_id: str
    consumer: str
    trace: str = ""


@_kind
class ConsumerReleased(_Numbered):
    """A consumer id of a served resource was released (an `unload`, or its consumer died).

    Published when the id is removed (with `save_on_modify`, in the same transaction); if it
    was the last, a [`ResourceUnloaded`][rr_actors.events.ResourceUnloaded] follows.

    Attributes:
        registrar: name of the provider registrar.
        resource_id: the resource's id.
        query_id: the released query id.
        consumer: name of the consumer registrar that held it.
        reason: `"unload"`, `"abandoned"` (its caller gave the call up), `"death watch"` (its
            consumer died for good), `"reconcile"` (its consumer no longer held it after a
            restart), `"consumer stopped"` (stopped while this registrar was down),
            `"server unregistered"`, `"name yielded"` (another registrar of its name was kept
            after a healed link, rule 22) or `"refused"` (the load's commit failed or its
            server closed: the caller got an error).
        trace: the `traceparent` the `Unload` carried (as `CallAnswered.trace`), else `""`.
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
    """A consumer's call was answered and the consumer holds its query id now.

    Published by the consumer registrar when it recorded the answer (a durable one committed),
    before its caller is answered; the id is held until a
    [`QueryForgotten`][rr_actors.events.QueryForgotten] of it.

    Attributes:
        registrar: name of the consumer registrar.
        query_id: the call's query id.
        serving_rr: name of the provider registrar.
        server: name of the resource server there.
        parent: the resource of this registrar whose `load` made the call (rule 5), `None` for
            a call of its own.
        retry: the consumer already knew this id (it held it, or an earlier call with it
            failed as its provider died, rule 17): no second consumer.
        started: when `call`/`acall` was made, wall clock seconds; 0.0 if not known.
        trace: the W3C `traceparent` the call carried (trace id, CLIENT span id, sampled flag:
            `rr_actors.otel`), `""` when no OpenTelemetry span was current in the caller.
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
    """A consumer's call failed: its caller got an error, and holds no query id.

    A withdrawn call is a [`CallWithdrawn`][rr_actors.events.CallWithdrawn] instead.

    Attributes:
        registrar: name of the consumer registrar.
        query_id: the call's query id.
        serving_rr: name of the provider registrar.
        server: name of the resource server there.
        error_type: the error's type name (`RegistrarUnavailableError`, ...).
        message: the error's message.
        may_have_executed: the provider died or stopped with the call in flight and may hold
            the id (rule 17): the consumer keeps it until it reconciled with the provider's
            next start, and a retry with the same id finds what it holds.
        retry: as `CallAnswered.retry`.
        started: as `CallAnswered.started`.
        trace: as `CallAnswered.trace`.
        caller_span: as `CallAnswered.caller_span`.
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


@_kind
class CallWithdrawn(_Numbered):
    """A consumer's call was given up before its answer: nothing is left of it (rule 17).

    Published after the caller told the provider to give the id back.

    Attributes:
        registrar: name of the consumer registrar.
        query_id: the call's query id.
        serving_rr: name of the provider registrar.
        server: name of the resource server there.
        reason: `"timeout"` (`CallTimeoutError`), `"interrupted"` (its caller stopped waiting
            with an exception) or `"registrar stopped"`.
        started: as `CallAnswered.started`.
        trace: as `CallAnswered.trace`.
        caller_span: as `CallAnswered.caller_span`.
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
        registrar: name of the consumer registrar.
        serving_rr: name of the provider registrar.
        server: name of the resource server there.
        query_ids: the ids the answer listed, in its order.
        started: the `hlc` stamp when the fetch began: the provider read its catalog between
            `started` and `hlc`.
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
        registrar: name of the provider registrar.
        server: name of its resource server.
        query_ids: the ids the answer listed, in its order.
        started: the `hlc` stamp when the listing began (as `QueriesFetched.started`).
    """

    registrar: str
    server: str
    query_ids: tuple[str, ...] = ()
    started: int = 0


@_kind
class QueryForgotten(_Numbered):
    """A consumer forgot a query id a `CallAnswered` or its `CatalogRestored` showed it holding.

    Attributes:
        registrar: name of the consumer registrar.
        query_id: the forgotten query id.
        serving_rr: name of the provider registrar that served it.
        reason: `"unload"` (answered by the provider), `"unload unanswered"` (the provider
            died or stopped: it releases the id when it reconciles), `"dependency"` (released
            with its resource), `"stop"`, `"revoked"` (the provider's server was
            unregistered: `FATAL`), `"provider lost"` (gone for good, rule 19: `FATAL`),
            `"unknown at reconcile"` (the provider's restart lost it, rule 20: `FATAL`),
            `"late dependency"` (answered after its load failed or was unloading),
            `"registrar stopped"` (answered while this registrar stopped), `"withdrawn"` (a
            retry given up by its caller) or `"in doubt"` (restored with its call in flight,
            or a sub-call of a resource gone: given back at the restart).
        unload_sent: for a release (`"unload"`, `"unload unanswered"`, `"dependency"`,
            `"stop"`), the `hlc` stamp its `Unload` left at; else 0.
        reconciled: with `unload_sent`, the stamp at which the last reconcile list with its
            provider answered before that `Unload` left had left (rule 20); 0 if none. A
            release that left before the reconcile with a restarted provider (without a
            backup) owes no `FATAL` for the id.
        trace: for an `unload`, the `traceparent` its `Unload` carried (as
            `CallAnswered.trace`).
        caller_span: with `trace`, the id (16 hex) of the span current in `unload`'s caller.
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
    """A provider sent a status notification about a loaded resource (`send_status`).

    Published before delivery starts; each consumer that receives it publishes a
    [`StatusDelivered`][rr_actors.events.StatusDelivered].

    Attributes:
        registrar: name of the provider registrar.
        query_id: the query id `send_status` was given.
        status: the status code.
        message: the provider's free text.
        status_id: this send's id (a UUID4), named by each of its `StatusDelivered`.
    """

    registrar: str
    query_id: str
    status: Status
    message: str
    status_id: str = ""


@_kind
class StatusDelivered(_Numbered):
    """A status notification reached one consumer (one hop on its way to the top).

    Published once the client's status callback for this query ran (before the consumer passes
    it on to its own consumers).

    Attributes:
        registrar: name of the consumer registrar that received it.
        query_id: the receiver's own query id for the resource.
        status: the status code.
        hop: registrars the status crossed to get here (1: a direct consumer of the sender).
        latency_s: seconds from `send_status` to this delivery, on the wall clock.
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
    """A consumer's status callback returned (or raised).

    Published on the callback's worker thread (a coroutine's: its loop's thread), after its
    `StatusDelivered`. With `arrived`, `began` and `opened` a checker judges rule 9 (check
    `status-order`): an id's callbacks run one at a time in arrival order, the next beginning
    early only once this one waited for a registrar (`opened`).

    Attributes:
        registrar: name of the consumer registrar whose client's callback it was.
        query_id: the receiver's own query id (the callback's `query.id`).
        status: the status code.
        status_id: its `StatusSent.status_id`.
        arrived: the callback's place in its process's arrival order (1, 2, ...).
        began: the `hlc` stamp as it began; it returned at `hlc`.
        opened: the stamp at which it first waited for a registrar (a `send_status`, `call`
            or `unload` from inside it), 0 if it never did.
    """

    registrar: str
    query_id: str
    status: Status
    status_id: str
    arrived: int
    began: int
    opened: int = 0


@_kind
class UnloadCutShort(_Numbered):
    """A clean `stop()` ended while a resource's unload was still under way.

    `stop()` waits at most half its timeout for its resources' unloads; one still under way is
    cut short: its callback runs on to its end (its result goes nowhere) and the resource stays
    in the backup as unloading, reported `InDoubt` (`cut="unload"`, rule 16) at the next start.

    Attributes:
        registrar: name of the provider registrar that stopped.
        server: name of the resource server whose unload was cut short.
        resource_id: the resource's id.
    """

    registrar: str
    server: str
    resource_id: str


@_kind
class ServerOverloaded(_Numbered):
    """A server refused new loads: it had its `max_pending` loads queued or running.

    Published at a server's first refusal, then at most once a second while refusals go on
    (each refused call's `CallFailed` says how it ended). Shed loads are `LoadFailed`
    (`DeadlineExceededError`).

    Attributes:
        registrar: name of the provider registrar.
        server: name of the server.
        pending: its new loads queued or running at this refusal.
        bound: its `max_pending` (its own, or its registrar's).
        refused: calls it refused since its previous `ServerOverloaded`, this one's included.
    """

    registrar: str
    server: str
    pending: int
    bound: int
    refused: int


# -- recovery and the stream itself ---------------------------------------------------------


@_kind
class InDoubt(_Numbered):
    """A restarted registrar found a query whose load started but was never committed (rule 16).

    Published at every restore that finds it, with the same `query_id`: an entry stays in the
    backup until a `setup` offered it returned (`ResourceRegistrar.settle_in_doubt`).

    Attributes:
        registrar: name of the restored registrar.
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
    """Events were lost here: a queue was full, or a manager process was killed.

    Delivered in the stream where the gap is, after the events that did arrive.

    Attributes:
        count: how many events were lost in this gap.
        cause: `"full"` (a subscriber's queue, a forwarder's buffer or a bound on bytes),
            `"killed"` (a dead manager process's events built but not forwarded, counted by
            its supervisor after the exit) or `"refused"` (a batch no member's certificate
            sealed, at a TLS `ZenohNetwork.subscribe_events`).
        pid: the process that lost them.
    """

    count: int
    cause: str = "full"


# -- what a catalog holds -------------------------------------------------------------------

Rows: TypeAlias = tuple[tuple[str, ...], ...]
"""Rows of plain strings (what `CatalogRestored` and `RegistrarStopped` list)."""

LISTED_ROWS = 10_000
"""Rows a catalog event lists per kind; above it lists none (`complete` is `False`)."""


@_kind
class CatalogRestored(_Numbered):
    """A registrar with a backup started: what its catalog holds, before it serves.

    Published once per start with a backup (an empty or new one too), before setup and any
    call; a checker re-synchronises here. In-doubt resources are listed, then reported by
    `InDoubt`.

    Attributes:
        registrar: name of the restored registrar.
        resources: `(resource id, server, state, digest, failed)` per served resource: `state`
            `"loaded"`, `"loading"` or `"unloading"`, `digest` in decimal (`""` if none),
            `failed` `"failed"` if reported `FATAL`, else `""`.
        consumers: `(query id, resource id, consumer registrar)` per consumer id.
        clients: `(query id, serving registrar, server, parent resource id or "")` per query
            this registrar holds.
        counts: `(resources, consumers, clients)`.
        complete: `False` when a kind had more than `LISTED_ROWS` rows: none are listed.
        digest: a SHA-256 (hex, first 16 digits) of the three kinds' sorted rows; `""` when
            they are not listed.
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
    """A registrar stopped cleanly: what its catalog still holds at the end (rule 12).

    Published when `stop()` finished unloading what it held as a consumer; a killed registrar
    publishes none. Its fields are `CatalogRestored`'s.
    """

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
    | InDoubt
    | CatalogRestored
    | RegistrarStopped
    | UnloadCutShort
    | ServerOverloaded
    | EventsDropped
)
"""Any event of this module (what a subscriber's callback receives)."""
