"""What a supervision tree and its registrars do, as frozen dataclasses (one per event kind).

Subscribe with `Supervisor.subscribe(callback)` (every child and every registrar of the
tree, manager processes included) or `ResourceRegistrar.subscribe(callback)` (one
registrar); both return an [`rr_actors.Subscription`][rr_actors.Subscription], and the
callback runs on a subscriber thread of its own, never in a registrar's mailbox.

Every event has its own fields first, then two keyword-only ones:

- `at`: when it happened, wall clock (`time.time()` seconds), so that events of several
  processes can be put on one timeline;
- `pid`: the process it happened in (for child events, the child's process).

Events pickle (they cross from manager processes to the supervisor's), and
[`to_dict`][rr_actors.events.to_dict] / [`from_dict`][rr_actors.events.from_dict] turn them
into JSON-able dicts and back (one JSON line per event is how experiments write
`events.jsonl`). [`describe`][rr_actors.events.describe] gives the one human line that is
also logged at INFO.

Durations are in seconds. Query and resource ids are UUID4 strings; `describe` shows their
first 8 characters.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
import typing
from typing import Any, TypeAlias

from rr_actors._core.bus import Publisher
from rr_actors._types import Status
from rr_actors.errors import ConfigError

__all__ = [
    "ChildExited",
    "ChildRestarted",
    "ChildStarted",
    "ConsumerAdded",
    "ConsumerReleased",
    "Event",
    "EventsDropped",
    "InDoubt",
    "LoadFailed",
    "ResourceLoaded",
    "ResourceUnloaded",
    "StatusDelivered",
    "StatusSent",
    "SupervisorGaveUp",
    "describe",
    "from_dict",
    "to_dict",
]

SCHEMA = 1
"""Version of the dicts `to_dict` writes (the `"schema"` key); `from_dict` reads this one."""


def _now() -> Any:
    return dataclasses.field(default_factory=time.time)


def _this_process() -> Any:
    return dataclasses.field(default_factory=_current_pid)


_pid = os.getpid()


def _current_pid() -> int:
    """`os.getpid()` without a system call per event (kept right across `fork`)."""
    return _pid


def _forked() -> None:
    global _pid
    _pid = os.getpid()


os.register_at_fork(after_in_child=_forked)


# -- supervision ----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, slots=True)
class ChildStarted:
    """A supervisor started a child: on the supervisor's start, in order, or when added.

    Published by the supervisor once the child serves (its registrar accepts calls). A
    start after an exit is a [`ChildRestarted`][rr_actors.events.ChildRestarted] instead.

    Attributes:
        supervisor: name of the supervisor.
        child: name of the child (a manager or a nested supervisor).
        pid: the child's process (the supervisor's own process for a thread manager or
            a nested supervisor).
        at: when it happened, wall clock (`time.time()` seconds).
    """

    supervisor: str
    child: str
    pid: int
    _: dataclasses.KW_ONLY
    at: float = _now()


@dataclasses.dataclass(frozen=True, slots=True)
class ChildExited:
    """A child's incarnation ended: it crashed, was killed, exited, or was stopped.

    Published by the supervisor when it sees the exit (from the process sentinel for a
    process manager), before it decides whether to restart the child.

    Attributes:
        supervisor: name of the supervisor.
        child: name of the child.
        pid: the process of the incarnation that ended (the supervisor's own process for
            a thread manager or a nested supervisor).
        reason: why it ended, for people (the same text as `ChildInfo.last_exit`).
        at: when the supervisor saw it, wall clock (`time.time()` seconds).
    """

    supervisor: str
    child: str
    pid: int
    reason: str
    _: dataclasses.KW_ONLY
    at: float = _now()


@dataclasses.dataclass(frozen=True, slots=True)
class ChildRestarted:
    """A supervisor restarted a child after an exit, and the new incarnation serves.

    Attributes:
        supervisor: name of the supervisor.
        child: name of the child.
        pid: the new incarnation's process (the supervisor's own process for a thread
            manager or a nested supervisor).
        restart_s: seconds from the supervisor seeing the exit to the new incarnation
            serving (its catalog restored), backoff delay included.
        at: when it serves again, wall clock (`time.time()` seconds).
    """

    supervisor: str
    child: str
    pid: int
    restart_s: float
    _: dataclasses.KW_ONLY
    at: float = _now()


@dataclasses.dataclass(frozen=True, slots=True)
class SupervisorGaveUp:
    """A supervisor exceeded its restart intensity and stopped all its children (OTP).

    A nested supervisor's parent then treats it as one crashed child (escalation); the
    top supervisor raises `SupervisorGaveUpError` to whoever waits on it.

    Attributes:
        supervisor: name of the supervisor that gave up.
        reason: why, for people (the message of the `SupervisorGaveUpError`).
        max_restarts: its restart intensity: at most this many restarts ...
        period: ... within this many seconds.
        at: when it gave up, wall clock (`time.time()` seconds).
        pid: the supervisor's process.
    """

    supervisor: str
    reason: str
    max_restarts: int
    period: float
    _: dataclasses.KW_ONLY
    at: float = _now()
    pid: int = _this_process()


# -- provider side --------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, slots=True)
class ResourceLoaded:
    """A server's `load` callback returned: a new resource is served.

    Published by the registrar when the load finished (and, with `save_on_modify`, is
    durable), before its first consumer gets the answer. A duplicate request loads
    nothing: it is a [`ConsumerAdded`][rr_actors.events.ConsumerAdded] only.

    Attributes:
        registrar: name of the provider registrar.
        server: name of the resource server that loaded it.
        resource_id: the new resource's id.
        query_id: the id of the query that caused the load (its first consumer).
        load_s: seconds the `load` callback took (its dependencies' loads included).
        at: when it finished, wall clock (`time.time()` seconds).
        pid: the registrar's process.
    """

    registrar: str
    server: str
    resource_id: str
    query_id: str
    load_s: float
    _: dataclasses.KW_ONLY
    at: float = _now()
    pid: int = _this_process()


@dataclasses.dataclass(frozen=True, slots=True)
class LoadFailed:
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
        at: when it failed, wall clock (`time.time()` seconds).
        pid: the registrar's process.
    """

    registrar: str
    server: str
    resource_id: str
    query_id: str
    error_type: str
    message: str
    _: dataclasses.KW_ONLY
    at: float = _now()
    pid: int = _this_process()


@dataclasses.dataclass(frozen=True, slots=True)
class ResourceUnloaded:
    """A server's `unload` callback ran: its last consumer released the resource.

    Published by the registrar after the resource's own dependencies were released and
    its `unload` callback returned (or raised: it is unloaded either way).

    Attributes:
        registrar: name of the provider registrar.
        server: name of the resource server that served it.
        resource_id: the resource's id.
        at: when it finished, wall clock (`time.time()` seconds).
        pid: the registrar's process.
    """

    registrar: str
    server: str
    resource_id: str
    _: dataclasses.KW_ONLY
    at: float = _now()
    pid: int = _this_process()


@dataclasses.dataclass(frozen=True, slots=True)
class ConsumerAdded:
    """A query became a consumer of a served resource (a new load or a duplicate request).

    Published by the provider registrar when the consumer id is recorded in its catalog.

    Attributes:
        registrar: name of the provider registrar.
        resource_id: the resource's id.
        query_id: the consumer's query id.
        consumer: name of the consumer registrar (the query's `origin_rr`).
        at: when it happened, wall clock (`time.time()` seconds).
        pid: the provider registrar's process.
    """

    registrar: str
    resource_id: str
    query_id: str
    consumer: str
    _: dataclasses.KW_ONLY
    at: float = _now()
    pid: int = _this_process()


@dataclasses.dataclass(frozen=True, slots=True)
class ConsumerReleased:
    """A consumer id of a served resource was released (an `unload`, or its consumer died).

    Published by the provider registrar when the id is removed from its catalog. If it
    was the last one, a [`ResourceUnloaded`][rr_actors.events.ResourceUnloaded] follows.

    Attributes:
        registrar: name of the provider registrar.
        resource_id: the resource's id.
        query_id: the released query id.
        consumer: name of the consumer registrar that held it.
        at: when it happened, wall clock (`time.time()` seconds).
        pid: the provider registrar's process.
    """

    registrar: str
    resource_id: str
    query_id: str
    consumer: str
    _: dataclasses.KW_ONLY
    at: float = _now()
    pid: int = _this_process()


# -- status ---------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, slots=True)
class StatusSent:
    """A provider sent a status notification about a loaded resource (`send_status`).

    Published by the registrar when `send_status` is called, before delivery starts;
    every consumer that receives it publishes a
    [`StatusDelivered`][rr_actors.events.StatusDelivered].

    Attributes:
        registrar: name of the provider registrar.
        query_id: the query id `send_status` was given.
        status: the status code.
        message: the provider's free text.
        at: when it was sent, wall clock (`time.time()` seconds).
        pid: the provider registrar's process.
    """

    registrar: str
    query_id: str
    status: Status
    message: str
    _: dataclasses.KW_ONLY
    at: float = _now()
    pid: int = _this_process()


@dataclasses.dataclass(frozen=True, slots=True)
class StatusDelivered:
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
        at: when it was delivered, wall clock (`time.time()` seconds).
        pid: the receiving registrar's process.
    """

    registrar: str
    query_id: str
    status: Status
    hop: int
    latency_s: float
    _: dataclasses.KW_ONLY
    at: float = _now()
    pid: int = _this_process()


# -- recovery and the stream itself ---------------------------------------------------------


@dataclasses.dataclass(frozen=True, slots=True)
class InDoubt:
    """A restarted registrar found a query whose load started but was never committed.

    Published by the registrar while it restores its catalog (semantics rule 16): the
    load may have started something before the crash that nobody will release.

    Attributes:
        registrar: name of the restored registrar.
        query_id: the in-doubt query's id.
        at: when it was found, wall clock (`time.time()` seconds).
        pid: the restored registrar's process.
    """

    registrar: str
    query_id: str
    _: dataclasses.KW_ONLY
    at: float = _now()
    pid: int = _this_process()


@dataclasses.dataclass(frozen=True, slots=True)
class EventsDropped:
    """Events were lost here: a subscriber's bounded queue (or a forwarder's buffer) was full.

    Delivered in the stream where the gap is: the events before it arrived, `count`
    events after them did not, the events after this notice arrive again.

    Attributes:
        count: how many events were lost in this gap.
        at: when the gap was closed (the notice made), wall clock (`time.time()` seconds).
        pid: the process that lost them.
    """

    count: int
    _: dataclasses.KW_ONLY
    at: float = _now()
    pid: int = _this_process()


Event: TypeAlias = (
    ChildStarted
    | ChildExited
    | ChildRestarted
    | SupervisorGaveUp
    | ResourceLoaded
    | LoadFailed
    | ResourceUnloaded
    | ConsumerAdded
    | ConsumerReleased
    | StatusSent
    | StatusDelivered
    | InDoubt
    | EventsDropped
)
"""Any event of this module (a subscriber's callback receives these)."""

_TYPES: dict[str, type[Event]] = {cls.__name__: cls for cls in typing.get_args(Event)}


# -- JSON lines -----------------------------------------------------------------------------


def to_dict(event: Event) -> dict[str, Any]:
    """Return `event` as JSON-able data: `"type"` (the class name), its fields, `"schema"`.

    A `Status` becomes its name (`"FATAL"`). `json.dumps(to_dict(event))` is one line of
    an `events.jsonl` file; [`from_dict`][rr_actors.events.from_dict] reads it back.

    Args:
        event: any event of this module.

    Returns:
        A new dict of strings, numbers and `"type"`/`"schema"` keys.
    """
    data: dict[str, Any] = {"type": type(event).__name__}
    for field in dataclasses.fields(event):
        value = getattr(event, field.name)
        data[field.name] = value.name if isinstance(value, Status) else value
    data["schema"] = SCHEMA
    return data


def from_dict(data: dict[str, Any]) -> Event:
    """Rebuild an event from [`to_dict`][rr_actors.events.to_dict] output.

    Every field must be present (`at` and `pid` too: they say when and where it
    happened, not when it was read) and of its type; an `int` is accepted for a `float`.

    Args:
        data: a dict as `to_dict` returns it (for example, one parsed JSON line).

    Returns:
        An event equal to the one `to_dict` was given.

    Raises:
        ConfigError: `data` is not a dict, has another `"schema"`, an unknown `"type"`,
            unknown or missing fields, or a value of the wrong type; the message names
            what was wrong.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"an event must be a dict, got {type(data).__name__}")
    if data.get("schema") != SCHEMA:
        raise ConfigError(f"unsupported event schema {data.get('schema')!r} (expected {SCHEMA})")
    name = data.get("type")
    cls = _TYPES.get(name) if isinstance(name, str) else None
    if cls is None:
        raise ConfigError(f"unknown event type {name!r}")
    types = _field_types(cls)
    given = set(data) - {"type", "schema"}
    unknown = sorted(given - set(types))
    missing = [field for field in types if field not in given]
    if unknown or missing:
        problems = [f"unknown fields {unknown}"] * bool(unknown)
        problems += [f"missing fields {missing}"] * bool(missing)
        raise ConfigError(f"{name}: {', '.join(problems)}")
    values = {f: _convert(cls.__name__, f, kind, data[f]) for f, kind in types.items()}
    return cls(**values)


def _field_types(cls: type[Event]) -> dict[str, type]:
    hints = typing.get_type_hints(cls)
    return {field.name: hints[field.name] for field in dataclasses.fields(cls)}


def _convert(event: str, field: str, kind: type, value: object) -> Any:
    """Check one field's value from a dict (and turn a status name into a `Status`)."""
    if kind is Status and isinstance(value, str) and value in Status.__members__:
        return Status[value]
    if kind is float and isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    if kind in (int, str) and isinstance(value, kind) and not isinstance(value, bool):
        return value
    expected = "a Status name" if kind is Status else kind.__name__
    raise ConfigError(f"{event}.{field} must be {expected}, got {value!r}")


# -- one human line -------------------------------------------------------------------------


def describe(event: Event) -> str:  # noqa: PLR0911, PLR0912 - one case per event kind
    """Return one human line about `event` (the INFO log line and terminal timelines).

    Ids are shortened to their first 8 characters; durations are in ms below a second.
    The `at` and `pid` every event has are left to the log record's own fields, except
    for child events, where the pid says which incarnation it was.

    Args:
        event: any event of this module.

    Returns:
        One line without a line break, for example `"erm restarted after 23.1 ms (pid 4242)"`.
    """
    match event:
        case ChildStarted():
            return f"{event.child} started (pid {event.pid})"
        case ChildExited():
            return f"{event.child} exited: {_text(event.reason)} (pid {event.pid})"
        case ChildRestarted():
            return f"{event.child} restarted after {_seconds(event.restart_s)} (pid {event.pid})"
        case SupervisorGaveUp():
            return (
                f"supervisor {event.supervisor} gave up (more than {event.max_restarts} "
                f"restarts within {event.period:g} s): {_text(event.reason)}"
            )
        case ResourceLoaded():
            return (
                f"{event.registrar}/{event.server} loaded {_id(event.resource_id)} "
                f"in {_seconds(event.load_s)} (query {_id(event.query_id)})"
            )
        case LoadFailed():
            return (
                f"{event.registrar}/{event.server} failed to load {_id(event.resource_id)} "
                f"(query {_id(event.query_id)}): {event.error_type}: {_text(event.message)}"
            )
        case ResourceUnloaded():
            return f"{event.registrar}/{event.server} unloaded {_id(event.resource_id)}"
        case ConsumerAdded():
            return (
                f"{event.registrar}: {event.consumer} consumes {_id(event.resource_id)} "
                f"(query {_id(event.query_id)})"
            )
        case ConsumerReleased():
            return (
                f"{event.registrar}: {event.consumer} released {_id(event.resource_id)} "
                f"(query {_id(event.query_id)})"
            )
        case StatusSent():
            return (
                f"{event.registrar} sent {event.status.name} for query {_id(event.query_id)}: "
                f"{_text(event.message)}"
            )
        case StatusDelivered():
            return (
                f"{event.registrar} received {event.status.name} for query "
                f"{_id(event.query_id)} (hop {event.hop}, {_seconds(event.latency_s)} after "
                f"it was sent)"
            )
        case InDoubt():
            return (
                f"{event.registrar}: query {_id(event.query_id)} is in doubt "
                f"(its load started before a crash and was never committed)"
            )
        case EventsDropped():
            return f"{event.count} events dropped (a subscriber or forwarder fell behind)"
    typing.assert_never(event)


def _id(value: str) -> str:
    return value[:8]


def _seconds(value: float) -> str:
    return f"{value * 1e3:.1f} ms" if abs(value) < 1.0 else f"{value:.2f} s"


_LONGEST_TEXT = 200
"""Characters of free text (messages, reasons) `describe` keeps; the rest becomes `...`."""


def _text(value: str) -> str:
    line = value.replace("\r", "\\r").replace("\n", "\\n")
    if len(line) > _LONGEST_TEXT:
        return line[: _LONGEST_TEXT - 3] + "..."
    return line


# -- for rr_actors' own publishers -------------------------------------------------------------


def publisher(logger: logging.Logger | None = None) -> Publisher[Event]:
    """A `Publisher` of these events: INFO lines through `describe`, `EventsDropped` notices.

    What registrars and supervisors publish on; not needed by programs that subscribe.

    Args:
        logger: where each event is also logged at INFO (when that logger is enabled
            for INFO), or `None` for no log lines.
    """
    return Publisher(logger=logger, describe=describe, notice=EventsDropped)
