"""The event kinds: one frozen dataclass per thing a tree or a registrar does.

Each has its own fields first, then the keyword-only stamps it inherits, said once in
`_Stamped` (`at`, `host`, `hlc`: every kind) and `_Numbered` (`pid`, `seq`: every kind but
the supervisor's child events, whose `pid` is their own, the child's process). `_kind`
makes a kind's frozen, slotted dataclass with the stamps after its own fields, in the
order of `_STAMPS`: the order of the fields of its JSON line (`lines.to_line`), of its
outbox row, of its pickled state and of its `repr` (a dataclass base would put them first).
Adding a kind: its class here (`@_kind`, from `_Numbered`), in the `Event` union, and its
line in `text.describe`.
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
from rr_actors._platform import fork
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
    """The member name events of this process carry: per process (a simulated process
    starts with its creator's, as a process forked on a host is on that host)."""

    def __init__(self, name: str) -> None:
        self.name = name


def _inherited() -> _Host:
    """A simulated process's, as it starts: its creator's (installed while it creates)."""
    return _Host(_HOST.name)


_HOST: _Host = runtime.process_state(_Host(socket.gethostname()), _inherited)


def _current_host() -> str:
    return _HOST.name


def this_host() -> str:
    """The member name events of this process carry (`host`): see `set_host`."""
    return _HOST.name


def set_host(name: str) -> None:
    """Name this process's host in the events it builds from now on (`host`).

    A process that joins a system served on a `ZenohNetwork` with `tls` (its router, and
    the manager processes that attach through it) names it by the certificate's common
    name: the member name. Until then, and on a system without TLS, it is the
    machine's host name (`socket.gethostname()`).
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

    Each event then carries `seq`: 1, 2, 3, ... in the order they were built, so that a
    reader of the forwarded stream sees every event the process lost (a gap).
    """
    global _numbering
    _numbering = True


class _Pid:
    """The pid this process's events carry: `runtime.getpid()`, read at its first event
    (a simulated process's own pid in a simulation: each has its own `_Pid`)."""

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


fork.after_fork_in_child("the events' pid", _forked)


# -- the stamps every kind carries ----------------------------------------------------------

_T = TypeVar("_T")

_STAMPS = ("at", "pid", "seq", "host", "hlc")
"""The stamps' order, after a kind's own fields (each kind has the ones its base gives it)."""

_STAMPED: dict[type, dict[str, tuple[str, Any]]] = {}
"""Each stamps class's own stamps: name -> (annotation, default factory)."""


@dataclass_transform(frozen_default=True, kw_only_default=True)
def _stamps(cls: type[_T]) -> type[_T]:
    """Take the fields of `cls` (a class of stamps) for the kinds deriving from it.

    To a type checker, a frozen dataclass of keyword-only fields; at run time a plain class
    without them, which `_kind` adds to each kind after its own fields.
    Each field's default is `dataclasses.field(default_factory=...)`.

    Raises:
        TypeError: a field of `cls` is not named in `_STAMPS` (its place in a line).
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
    """`cls` as a kind of event: a frozen dataclass with slots, its own fields first, then
    the stamps of its bases (keyword-only, in the order of `_STAMPS`), which it does not
    derive from at run time (they are declarations: `_stamps`).

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
        hlc: its hybrid logical clock stamp (`rr_actors._core.hlc`): sort events of
            several hosts by it to put every cause before its effects.
    """

    at: float = dataclasses.field(default_factory=_hlc.CLOCK.wall)
    host: str = dataclasses.field(default_factory=_current_host)
    hlc: int = dataclasses.field(default_factory=_hlc.CLOCK.now)


@_stamps
class _Numbered(_Stamped):
    """What every event but a supervisor's child events carries too (keyword-only).

    Attributes:
        pid: the process it happened in (the registrar's, for a registrar's event).
        seq: its number among its process's events: 1, 2, 3, ... in a manager process,
            where a gap shows a lost event (see `number_events`); 0 where events are not
            numbered.
    """

    pid: int = dataclasses.field(default_factory=_current_pid)
    seq: int = dataclasses.field(default_factory=_next_seq)


# -- supervision ----------------------------------------------------------------------------


@_kind
class ChildStarted(_Stamped):
    """A supervisor started a child: on the supervisor's start, in order, or when added.

    Published by the supervisor once the child serves (its registrar accepts calls). A
    start after an exit is a [`ChildRestarted`][rr_actors.events.ChildRestarted] instead.

    Attributes:
        supervisor: name of the supervisor.
        child: name of the child (a manager or a nested supervisor).
        pid: the child's process (the supervisor's own process for a thread manager or
            a nested supervisor).
    """

    supervisor: str
    child: str
    pid: int


@_kind
class ChildExited(_Stamped):
    """A child's incarnation ended: it crashed, was killed, exited, or was stopped.

    Published by the supervisor when it sees the exit (from the process sentinel for a
    process manager), before it decides whether to restart the child.

    Attributes:
        supervisor: name of the supervisor.
        child: name of the child.
        pid: the process of the incarnation that ended (the supervisor's own process for
            a thread manager or a nested supervisor).
        reason: why it ended, for people (the same text as `ChildInfo.last_exit`).
        restart: the child's restart type (`"permanent"`, `"transient"`, `"temporary"`);
            `""` in a line of schema 3 or older (not known).
        normal: whether it ended normally (OTP's `normal`/`shutdown`: a `transient`
            child that ends so is not restarted).
        stopped: whether the supervisor stopped it itself (a sibling taken down with a
            crashed one, a give-up, a shutdown): not an exit its intensity counts.
        max_restarts: the supervisor's restart intensity: more than this many restarts
            ...
        period: ... within this many seconds and it gives up (OTP); with `restart` and
            `normal`, what a checker needs to judge the supervisor's decision.
        strategy: the supervisor's restart strategy (`"one_for_one"`, `"one_for_all"`,
            `"rest_for_one"`): which siblings a restart takes down with the child; `""`
            in a line of schema 5 or older (not known).
        children: the names of the supervisor's children, in start order (this one
            among them): the order the strategy stops them in (reverse) and restarts
            them in; `()` in a line of schema 5 or older.
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
        pid: the new incarnation's process (the supervisor's own process for a thread
            manager or a nested supervisor).
        restart_s: seconds from the supervisor seeing the exit to the new incarnation
            serving (its catalog restored), backoff delay included.
        at: when it serves again.
    """

    supervisor: str
    child: str
    pid: int
    restart_s: float


@_kind
class SupervisorGaveUp(_Numbered):
    """A supervisor exceeded its restart intensity and stopped all its children (OTP).

    A nested supervisor's parent then treats it as one crashed child (escalation); the
    top supervisor raises `SupervisorGaveUpError` to whoever waits on it.

    Attributes:
        supervisor: name of the supervisor that gave up.
        reason: why, for people (the message of the `SupervisorGaveUpError`).
        max_restarts: its restart intensity: at most this many restarts ...
        period: ... within this many seconds.
        at: when it gave up.
        pid: the supervisor's process.
    """

    supervisor: str
    reason: str
    max_restarts: int
    period: float


@_kind
class ManagerOverloaded(_Stamped):
    """A manager process answered its heartbeat late, overloaded: not hung, not killed.

    Published by its supervisor when the answer to a ping came after more than the
    manager's `heartbeat_timeout`, and the silence was excused: its registrar was busy
    with other messages (a flood of calls, loads on all its workers), or its threads
    waited for a CPU. At most one per ping, so at most one a `heartbeat_timeout`; the
    heartbeat's WARNING says it too (at most one a minute). A silence that is not
    excused ends in a kill instead (`ChildExited`, `"hung: ..."`).

    Attributes:
        supervisor: name of its supervisor.
        manager: name of the manager.
        pid: its process.
        silent_s: seconds from the ping to its answer.
        bound_s: its `heartbeat_timeout` (seconds).
        excused_s: seconds of the silence that did not count against it.
        busy_s: seconds of it its registrar was seen handling other messages (the rest
            of `excused_s` it waited for a CPU).
        queued: messages waiting in its registrar's mailbox when last asked (-1: not
            asked).
        at: when the answer was read.
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

    Published by the registrar when the load finished, before its result is written
    and before its first consumer is added and answered (a kill in between: the restart
    reports it [`InDoubt`][rr_actors.events.InDoubt]). A duplicate request loads
    nothing: it is a [`ConsumerAdded`][rr_actors.events.ConsumerAdded] only.

    Attributes:
        registrar: name of the provider registrar.
        server: name of the resource server that loaded it.
        resource_id: the new resource's id.
        query_id: the id of the query that caused the load (its first consumer).
        load_s: seconds the `load` callback took (its dependencies' loads included).
        digest: the catalog's digest of the request, for a request of plain values (`None`
            for other classes): two loads with the same `digest` at the same
            registrar and server are of equal requests (rule 1).
        label: the request's bounded display label: the server's `label(request)` (the
            registrar waits for it, made on a worker thread, at most `compare_timeout`;
            `"<label failed: ...>"` if it failed), or without one the catalog's bounded
            `repr`; `None` if it has none.
        trace: the W3C `traceparent` the call that caused it carried (as
            `ConsumerAdded.trace`), `""` for an untraced call.
        at: when it finished.
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

    Published by the registrar whose server's `load` raised (the origin of the error),
    after the sub-resources that load had already loaded were unloaded.

    Attributes:
        registrar: name of the provider registrar.
        server: name of the resource server whose `load` raised.
        resource_id: the id the resource would have had (it is not served).
        query_id: the id of the query that caused the load.
        error_type: the exception's type name (`type(exc).__name__`).
        message: the exception's message (`str(exc)`).
        trace: the W3C `traceparent` the call carried, as `CallAnswered.trace`.
        at: when it failed.
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
    """A server's `unload` callback ran: its last consumer released the resource.

    Published by the registrar after the resource's own dependencies were released and
    its `unload` callback returned (or raised: it is unloaded either way), once its
    removal is written (also without `save_on_modify`), the event in the same
    transaction: a SIGKILL right after the commit does not lose it (the supervisor's
    process reads it from the backup's outbox after the exit).

    Attributes:
        registrar: name of the provider registrar.
        server: name of the resource server that served it.
        resource_id: the resource's id.
        at: when it finished.
    """

    registrar: str
    server: str
    resource_id: str


@_kind
class ConsumerAdded(_Numbered):
    """A query became a consumer of a served resource (a new load or a duplicate request).

    Published by the provider registrar when the consumer id is recorded in its catalog
    (with `save_on_modify`, once written, the event in the same transaction), before
    the caller is answered.

    Attributes:
        registrar: name of the provider registrar.
        resource_id: the resource's id.
        query_id: the consumer's query id.
        consumer: name of the consumer registrar (the query's `origin_rr`).
        trace: the W3C `traceparent` the call carried, as `CallAnswered.trace`.
    """

    registrar: str
    resource_id: str
    query_id: str
    consumer: str
    trace: str = ""


@_kind
class ConsumerReleased(_Numbered):
    """A consumer id of a served resource was released (an `unload`, or its consumer died).

    Published by the provider registrar when the id is removed from its catalog (with
    `save_on_modify`, once written, the event in the same transaction). If it was the
    last one, a [`ResourceUnloaded`][rr_actors.events.ResourceUnloaded] follows.

    Attributes:
        registrar: name of the provider registrar.
        resource_id: the resource's id.
        query_id: the released query id.
        consumer: name of the consumer registrar that held it.
        reason: why it was released: `"unload"` (its consumer called `unload`),
            `"abandoned"` (its caller gave the call up), `"death watch"` (its consumer
            died for good), `"reconcile"` (its consumer no longer held it after a
            restart), `"consumer stopped"` (its consumer was stopped while this
            registrar was down), `"server unregistered"` (`unregister_server`),
            `"name yielded"` (another registrar of its name was kept after a healed
            link, rule 22: its consumer reconciles with that one) or `"refused"` (the
            load's commit failed or its server closed: the caller was answered with an
            error).
        trace: the W3C `traceparent` the `Unload` carried (`rr_actors.otel`: its trace id,
            its CLIENT span's id, the sampled flag), `""` for another reason or an untraced one.
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

    Published by the consumer registrar when it recorded the answer (a durable one
    committed, before its caller is answered; a plain one when the caller handed it
    over). The provider published its [`ConsumerAdded`][rr_actors.events.ConsumerAdded]
    before it answered. The id is held until a
    [`QueryForgotten`][rr_actors.events.QueryForgotten] of it.

    Attributes:
        registrar: name of the consumer registrar.
        query_id: the call's query id.
        serving_rr: name of the provider registrar.
        server: name of the resource server there.
        parent: the resource of this registrar the query is a dependency of (the
            `resource_id` of its `ResourceLoaded`: the call was made inside that
            resource's `load`, rule 5), `None` for a call of its own.
        retry: the consumer already knew this id: it held it, or an earlier call with it
            failed as its provider died (rule 17); the answer adds no second consumer.
        started: when the call began (`call`/`acall` was made), wall clock seconds as
            `at`; 0.0 if not known (made while nobody listened, or an older line).
        trace: the W3C `traceparent` the call carried to its provider (its trace id,
            its CLIENT span's id, the sampled flag: `rr_actors.otel`), `""` when no
            OpenTelemetry span was current in the caller.
        caller_span: the id (16 hex) of the span current in the caller, the CLIENT
            span's parent; `""` with `trace`.
        at: when the answer was recorded.
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

    Published by the consumer registrar when it handled the failure (a withdrawn call
    is a [`CallWithdrawn`][rr_actors.events.CallWithdrawn] instead).

    Attributes:
        registrar: name of the consumer registrar.
        query_id: the call's query id.
        serving_rr: name of the provider registrar.
        server: name of the resource server there.
        error_type: the error's type name (`RegistrarUnavailableError`, ...).
        message: the error's message.
        may_have_executed: the provider died or stopped with the call in flight: it may
            have run the load and kept the id (rule 17). The consumer keeps the id until
            it reconciled with the provider's next start (whose unknown ids it releases)
            and a retry with the same id finds what it holds. `False`: the provider holds
            nothing for it (an error answer, or an answer given back).
        retry: the consumer already knew this id (see `CallAnswered.retry`).
        started: as `CallAnswered.started`.
        trace: as `CallAnswered.trace`.
        caller_span: as `CallAnswered.caller_span`.
        at: when the failure was handled.
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

    Published by the consumer registrar after the caller told the provider to give the
    id back (an answer that comes later is released there).

    Attributes:
        registrar: name of the consumer registrar.
        query_id: the call's query id.
        serving_rr: name of the provider registrar.
        server: name of the resource server there.
        reason: `"timeout"` (its `timeout` ran out: `CallTimeoutError`),
            `"interrupted"` (its caller stopped waiting with an exception) or
            `"registrar stopped"` (the consumer was stopped with the call in flight).
        started: as `CallAnswered.started`.
        trace: as `CallAnswered.trace`.
        caller_span: as `CallAnswered.caller_span`.
        at: when the withdrawal was handled.
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

    Published by the consumer registrar when the provider's answer came.

    Attributes:
        registrar: name of the consumer registrar.
        serving_rr: name of the provider registrar.
        server: name of the resource server there.
        query_ids: the ids the answer listed, in its order.
        started: the stamp (`hlc`) taken when the fetch began: the provider read its
            catalog between `started` and `hlc`.
        at: when the answer came.
    """

    registrar: str
    serving_rr: str
    server: str
    query_ids: tuple[str, ...] = ()
    started: int = 0


@_kind
class ServerQueriesListed(_Numbered):
    """A provider listed the queries its own server holds (`server_queries`, rule 10).

    Published by the provider registrar when its answer came back to the caller.

    Attributes:
        registrar: name of the provider registrar.
        server: name of its resource server.
        query_ids: the ids the answer listed, in its order.
        started: the stamp (`hlc`) taken when the listing began: the registrar read its
            catalog between `started` and `hlc`.
        at: when the answer came.
    """

    registrar: str
    server: str
    query_ids: tuple[str, ...] = ()
    started: int = 0


@_kind
class QueryForgotten(_Numbered):
    """A consumer forgot a query id it held (one a `CallAnswered` or a restore gave it).

    Published by the consumer registrar when it removed the id's client record, for
    every id a `CallAnswered` or its `CatalogRestored` (answered or not) showed it
    holding.

    Attributes:
        registrar: name of the consumer registrar.
        query_id: the forgotten query id.
        serving_rr: name of the provider registrar that served it.
        reason: why: `"unload"` (its `unload`, answered by the provider),
            `"unload unanswered"` (its `unload`, while the provider died or stopped: the
            provider releases it when it reconciles), `"dependency"` (released with the
            resource of this registrar it belonged to), `"stop"` (released by `stop()`),
            `"revoked"` (the provider's server was unregistered: `FATAL`, then revoked),
            `"provider lost"` (the provider is gone for good, rule 19: `FATAL`),
            `"unknown at reconcile"` (the provider's restart lost it, rule 20:
            `FATAL`), `"late dependency"` (answered after the load that made it had
            failed or was unloading: given back at once), `"registrar stopped"`
            (answered while this registrar stopped: given back), `"withdrawn"` (a
            retry of it was given up by its caller) or `"in doubt"` (restored, its call
            in flight when the last run died, or a sub-call of a resource gone: given
            back at the restart).
        unload_sent: for an id forgotten on the answer to its release (`"unload"`,
            `"unload unanswered"`, `"dependency"`, `"stop"`), the stamp (`hlc`) its
            `Unload` left at: the release began; 0 for the other reasons.
        reconciled: with `unload_sent`, the stamp at which the list of the last
            reconcile with its provider that was answered before that `Unload` left had
            left (rule 20: after the provider's restart, a healed link, or this
            registrar's start); 0 if none was. A release on its way when its provider
            was killed may reach the provider restarted without a backup, which no
            longer knows the id: if it left before the reconcile with that restart was
            answered (`reconciled` earlier than the restart), no `FATAL` is owed for
            the id (its consumer let it go: its reconcile skips an id being released).
        trace: for an id forgotten on the answer to its `unload`, the W3C `traceparent`
            the `Unload` carried (as `CallAnswered.trace`), `""` for an untraced one.
        caller_span: with `trace`, the id (16 hex) of the span current in the caller of
            `unload`.
        at: when it was forgotten.
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

    Published by the registrar when `send_status` is called, before delivery starts;
    every consumer that receives it publishes a
    [`StatusDelivered`][rr_actors.events.StatusDelivered].

    Attributes:
        registrar: name of the provider registrar.
        query_id: the query id `send_status` was given.
        status: the status code.
        message: the provider's free text.
        status_id: this send's id (a UUID4), carried by every hop: each
            `StatusDelivered` of it names it.
        at: when it was sent.
    """

    registrar: str
    query_id: str
    status: Status
    message: str
    status_id: str = ""


@_kind
class StatusDelivered(_Numbered):
    """A status notification reached one consumer (one hop on its way to the top).

    Published by the consumer registrar once its client's status callback for this query
    ran (a consumer that passes the status on to its own consumers publishes this first).

    Attributes:
        registrar: name of the consumer registrar that received it.
        query_id: the receiver's own query id for the resource.
        status: the status code.
        hop: how many registrars the status crossed to get here (1: a direct consumer
            of the provider that sent it; 2: a consumer of that consumer; ...).
        latency_s: seconds from the provider's `send_status` to this delivery, on the
            wall clock (the hops may be in different processes).
        status_id: the id of the send it belongs to (its `StatusSent.status_id`); a
            query id gets each send once.
        at: when it was delivered.
        pid: the receiving registrar's process.
    """

    registrar: str
    query_id: str
    status: Status
    hop: int
    latency_s: float
    status_id: str = ""


@_kind
class StatusHandled(_Numbered):
    """A consumer's status callback returned (one run on a worker thread, or a coroutine's).

    Published by the process's status runner on the callback's worker thread (a
    coroutine's: on its loop's thread), as the callback returns (or raises), after its
    `StatusDelivered`. With `arrived`, `began` and `opened` a checker judges the runner's
    promise (rule 9; the check's rule `status-order`): each query id's callbacks run one
    at a time, in the order their statuses arrived; the next may begin before this one
    returned only once this one waited for a registrar (`opened`).

    Attributes:
        registrar: name of the consumer registrar whose client's callback it was.
        query_id: the receiver's own query id (the callback's `query.id`).
        status: the status code.
        status_id: the send it belongs to (its `StatusSent.status_id`).
        arrived: the callback's place in its process's arrival order (1, 2, ...: the
            runner numbers each callback queued): an id's statuses arrived in this order.
        began: the stamp (`hlc`) taken as the callback began; it returned at `hlc`.
        opened: the stamp at which it first waited for a registrar (a `send_status`,
            `call` or `unload` from inside it: its id's next callback may then begin
            beside it), 0 if it never did.
        at: when it returned.
        pid: the receiving registrar's process.
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

    `stop()` waits for the unloads of its registrar's resources that are under way (their
    dependencies being released, or their `unload` callback running) for at most half
    its timeout; one still under way then is cut short: the registrar stops anyway and
    publishes this. The callback runs on to its end on its worker thread (what it returns
    goes nowhere), and the resource stays in the backup as unloading: the next start
    reports it `InDoubt` (`cut="unload"`, rule 16).

    Attributes:
        registrar: name of the provider registrar that stopped.
        server: name of the resource server whose unload was cut short.
        resource_id: the resource's id.
        at: when the stop gave up waiting.
    """

    registrar: str
    server: str
    resource_id: str


@_kind
class ServerOverloaded(_Numbered):
    """A server refused new loads: it had its `max_pending` loads queued or running.

    Published by the provider registrar at a server's first refusal, then at most once a
    second while refusals go on (each call refused waits and asks again, or raises
    `OverloadedError`: its `CallFailed` says which). Shed loads are `LoadFailed` events
    (`error_type` `DeadlineExceededError`).

    Attributes:
        registrar: name of the provider registrar.
        server: name of the server.
        pending: its new loads queued or running at this refusal (its queue's depth).
        bound: its `max_pending` (its own, or its registrar's).
        refused: calls it refused since the previous `ServerOverloaded` of it (this
            one's included).
        at: when it refused.
    """

    registrar: str
    server: str
    pending: int
    bound: int
    refused: int


# -- recovery and the stream itself ---------------------------------------------------------


@_kind
class InDoubt(_Numbered):
    """A restarted registrar found a query whose load started but was never committed.

    Published by the registrar while it restores its catalog (semantics rule 16): the
    load may have started something before the crash that nobody will release.
    Published at every restore that finds it: an entry stays in the backup until a
    `setup` that was offered it returned (`ResourceRegistrar.settle_in_doubt`), so a
    manager that died during `setup` publishes it again, with the same `query_id`:
    the same load found again, not a second one.

    Attributes:
        registrar: name of the restored registrar.
        query_id: the in-doubt resource's id.
        server: the server it belongs to (`""` in events written before it was known).
        cut: what the crash cut short: `"load"` or `"unload"` (`""`: not known).
        at: when it was found.
        pid: the restored registrar's process.
    """

    registrar: str
    query_id: str
    server: str = ""
    cut: str = ""


@_kind
class EventsDropped(_Numbered):
    """Events were lost here: a queue was full, or a manager process was killed.

    With `cause="full"`: a subscriber's bounded queue (or a forwarder's buffer) was
    full. Delivered in the stream where the gap is: the events before it arrived,
    `count` events after them did not, the events after this notice arrive again.

    With `cause="killed"`: a manager process ended (a SIGKILL, the heartbeat's kill of
    a hung one) with `count` events built but not yet forwarded; its supervisor's
    process counted them after the exit (the events it built are numbered in a small
    shared file) and publishes this notice, with the dead process's pid, after the last
    events that did arrive from it.

    With `cause="refused"`: a system-wide subscriber (`ZenohNetwork.subscribe_events`,
    with TLS) dropped a batch of `count` events that no member's certificate sealed.

    Attributes:
        count: how many events were lost in this gap.
        cause: `"full"` (a queue or buffer, or a subscriber's bound on bytes), `"killed"`
            (the tail of a dead manager process's events) or `"refused"` (a batch no
            member sealed).
        at: when the gap was closed (the notice made).
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

    Published once per start of a registrar that has a backup (an empty or a new one
    too), before its setup runs and before any call is served; a checker of the stream
    re-synchronises here (what the registrar held before is replaced by this). In-doubt
    resources (`loading`, `unloading`) are listed, then reported by `InDoubt`.

    Attributes:
        registrar: name of the restored registrar.
        resources: `(resource id, server, state, digest, failed)` per served resource,
            `state` being `"loaded"`, `"loading"` or `"unloading"`, `digest` the request's
            digest in decimal (as `ResourceLoaded.digest`; `""` for a request of another
            class), `failed` `"failed"` if its provider reported it `FATAL` (no equal
            request is matched with it any more), else `""`.
        consumers: `(query id, resource id, consumer registrar)` per consumer id.
        clients: `(query id, serving registrar, server, parent resource id or "")` per
            query this registrar holds (its client records).
        counts: `(resources, consumers, clients)`: how many rows there are.
        complete: whether the rows are listed (`False`: a kind had more than
            `LISTED_ROWS` rows, and none are listed; `counts` says what it held).
        digest: a SHA-256 (hex, first 16 digits) of the sorted rows of the three kinds;
            `""` when they are not listed (it would cost a read of every row, which a
            restore does not do before it serves).
        at: when it was published.
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

    Published when `stop()` finished unloading what it held as a consumer, with the
    rows left: what its own servers serve (kept for a restart) and what it could not
    give back. A registrar killed (SIGKILL, a crash) publishes none.

    Attributes:
        registrar: name of the stopped registrar.
        resources: `(resource id, server, state, digest, failed)` per served resource
            (see `CatalogRestored`).
        consumers: `(query id, resource id, consumer registrar)` per consumer id.
        clients: `(query id, serving registrar, server, parent resource id or "")`.
        counts: `(resources, consumers, clients)`.
        complete: whether the rows are listed (see `CatalogRestored`).
        digest: as in `CatalogRestored`.
        at: when it was published.
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
"""Any event of this module (a subscriber's callback receives these)."""
