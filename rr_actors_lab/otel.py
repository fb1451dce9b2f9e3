"""OpenTelemetry spans from the event stream: one subscriber turns events into spans.

    tracing = rr_actors_lab.otel.trace(sup)      # sup.subscribe(Tracing(...)) ──► spans
                                             # through the application's TracerProvider

Used as OpenTelemetry's instrumentation libraries are: it traces through the global
`TracerProvider` the application installs (read at every event). `trace` subscribes only
while spans would be recorded: with none installed yet, once one is (a watcher thread
looks); with a no-op provider, or without the `otel` extra (`opentelemetry-api`), never,
so tracing off costs the tree nothing. Nothing is traced in a registrar's turn: spans are
built afterwards, on the subscription's thread, from the events' `at` stamps (seconds,
turned into ns). Attributes follow the current RPC semantic conventions (`rpc/dup` in
`OTEL_SEMCONV_STABILITY_OPT_IN` adds the deprecated ones).

What becomes a span (the table: `docs/how-to/trace.md`): a `call` or `unload` (a CLIENT
span at the consumer, a SERVER span at the provider, its child, by the RPC semantic
conventions); a user callback (INTERNAL `<server>.load`, `<server>.unload`); a status (a
PRODUCER span, a CONSUMER span per hop, linked to the call's spans; a callback's run); a
restart (INTERNAL `restart <child>`, linked to the old and new incarnations' spans; spans
whose end a kill lost are ended at the exit, marked `rr_actors.end_lost`).

A caller's trace continues through the call: a `call`, `acall` or `unload` made under a
current span carries its W3C trace context to the provider (`rr_actors._core.traces`),
which runs `load` with the SERVER span current; the span ids are chosen then, so both
sides meet in whichever process each is made (an untraced call's derive from its query
id). Lost events (`EventsDropped`) are counted (`Tracing.dropped`), the spans they may
have cut marked `rr_actors.incomplete`.

`provider_from_environment`, `Exporting`: the `--trace` commands' SDK, set by `OTEL_*`.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import itertools
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any, Protocol

from rr_actors import events
from rr_actors._core import hlc, traces

try:
    from opentelemetry import trace as _api
except ImportError:  # the otel extra is missing: every event is ignored
    _api = None  # type: ignore[assignment]

__all__ = [
    "SCOPE",
    "SEMCONV_OPT_IN",
    "SYSTEM",
    "WATCH_EVERY",
    "Exporting",
    "Tracing",
    "provider_from_environment",
    "root_span",
    "trace",
]

SYSTEM = "rr_actors"
"""The `rpc.system.name` of every RPC span."""

SEMCONV_OPT_IN = "OTEL_SEMCONV_STABILITY_OPT_IN"
"""The variable whose `rpc/dup` adds the deprecated RPC attributes (read by each `Tracing`)."""

WATCH_EVERY = 0.1
"""Seconds between two looks for the global `TracerProvider`, while `trace` waits for one."""

SCOPE = "rr_actors_lab.otel"
"""The instrumentation scope (the tracer's name)."""

SWEEP_EVERY = 0.05
"""Seconds between two looks for what waited `pair_within` (or `pair_within`, if less)."""

_CALL_ENDS = (events.CallAnswered, events.CallFailed, events.CallWithdrawn)
# the context of a span with no parent (not one under what is current where it is made:
# `flush` may run in a thread with a span of its own current)
_ROOT: Any = _api.set_span_in_context(_api.INVALID_SPAN) if _api is not None else None
_UNLOADS = frozenset({"unload", "unload unanswered", "dependency", "stop"})
# a call's failure that says its server is not one its provider has: `rpc.method` `_OTHER`
_UNRECOGNIZED = frozenset({"UnknownServerError", "UnknownRegistrarError"})
_OTHER = "_OTHER"

logger = logging.getLogger("rr_actors")


def _old_rpc_names() -> bool:
    """Whether `OTEL_SEMCONV_STABILITY_OPT_IN` (comma-separated) asks for the deprecated RPC
    attributes beside the current ones (`rpc/dup`; `rpc`, or nothing: the current ones only)."""
    return "rpc/dup" in {v.strip() for v in os.environ.get(SEMCONV_OPT_IN, "").split(",")}


def _silent(provider: Any, tracer: Any) -> bool:
    """Whether `tracer` (of `provider`) records no span, ever: the API's no-op tracer (an SDK
    disabled by `OTEL_SDK_DISABLED`), or an SDK provider whose sampler drops every span."""
    if isinstance(tracer, _api.NoOpTracer):
        return True
    sampler = getattr(provider, "sampler", None)
    describe = getattr(sampler, "get_description", None)
    return callable(describe) and describe() == "AlwaysOffSampler"


class _Chosen:
    """An id generator giving the ids chosen for the next span (per thread), else its inner one's.

    A call's two sides, made by subscribers of different processes, must get the ids its
    trace context named (`rr_actors._core.traces`).
    """

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self._chosen = threading.local()

    def choose(self, trace_id: int, span_id: int) -> None:
        self._chosen.ids = (trace_id, span_id)

    def clear(self) -> None:
        self._chosen.ids = None

    def generate_trace_id(self) -> int:
        ids = getattr(self._chosen, "ids", None)
        return ids[0] if ids is not None else int(self.inner.generate_trace_id())

    def generate_span_id(self) -> int:
        ids = getattr(self._chosen, "ids", None)
        return ids[1] if ids is not None else int(self.inner.generate_span_id())

    def is_trace_id_random(self) -> bool:
        return True


class _Subscribable(Protocol):
    def subscribe(self, callback: Callable[[events.Event], object]) -> Any: ...


def _ns(at: float) -> int:
    return int(at * 1e9)


_derived = traces.derived


def _untraced(query_id: str, verb: str) -> tuple[int, int, int]:
    """The (trace id, CLIENT span id, flags) an untraced call (or unload) is given here:
    derived from its query id, so that its two sides, made by subscribers of different
    processes, meet, and a status hop names its spans (sampled)."""
    return _derived(query_id, bits=128), _derived(query_id, verb), 1


def _late(waiting: dict[tuple[str, str], _Half], before: float, most: int) -> list[Any]:
    """The keys of the sides waiting since before `before`, and of the oldest past `most`.

    Sides are in arrival order, so the look stops at the first one not late (a sweep per
    event costs the spans it makes, not every side waiting).
    """
    late = []
    for key, half in waiting.items():
        if half.arrived > before:
            break
        late.append(key)
    excess = len(waiting) - len(late) - most
    if excess > 0:
        late += itertools.islice(waiting, len(late), len(late) + excess)
    return late


def _old(half: _Half, exited: events.ChildExited, restarted: events.ChildRestarted) -> bool:
    """Whether `half` (a SERVER side) is of the incarnation that exited (a thread's restart
    keeps its pid: a side that ended before the exit)."""
    return half.pid == exited.pid and (exited.pid != restarted.pid or half.end <= exited.at)


@dataclasses.dataclass(slots=True)
class _Child:
    """A user callback's INTERNAL span, under its server span."""

    name: str
    start: float
    end: float
    attributes: dict[str, Any]
    error: tuple[str, str] | None = None  # (type, message)
    lost: str = ""  # its end was lost: what ended it


@dataclasses.dataclass(slots=True)
class _Half:
    """One side of an RPC, complete, waiting for its other side to be made a span."""

    service: str  # the provider registrar
    method: str  # the server
    start: float
    end: float
    attributes: dict[str, Any]
    error: tuple[str, str] | None = None
    children: list[_Child] = dataclasses.field(default_factory=list)
    links: list[Any] = dataclasses.field(default_factory=list)
    arrived: float = dataclasses.field(default_factory=time.monotonic)
    trace: str = ""  # the traceparent the call carried (its CLIENT span's id)
    caller_span: str = ""  # (a CLIENT side) the caller's span, its parent
    started: float = 0.0  # (a CLIENT side) when the call began, 0.0: not known
    pid: int = 0  # (a SERVER side) the provider's process
    lost: str = ""  # its end was lost: what ended it (a restart span's name)
    restart: _Opened | None = None  # (lost) the restart span that ended it
    root: bool = False  # no CLIENT side is known to exist: not given derived ids


@dataclasses.dataclass
class _Restart:
    exited: events.ChildExited
    restarted: events.ChildRestarted
    restored: float | None = None  # its first CatalogRestored's `at`
    arrived: float = dataclasses.field(default_factory=time.monotonic)


@dataclasses.dataclass
class _Opened:
    """A restart span started, open until the new incarnation's first span links to it."""

    span: Any
    end: float  # its end (seconds), given when it is ended
    arrived: float = dataclasses.field(default_factory=time.monotonic)
    ended: bool = False


@dataclasses.dataclass
class _Sent:
    """A status send: its span (once its `StatusSent` is heard) and the hops it made."""

    context: Any = None  # its span's context; None: its StatusSent not heard yet
    at: float = 0.0
    reached: dict[str, tuple[Any, float]] = dataclasses.field(default_factory=dict)
    waiting: list[events.StatusDelivered] = dataclasses.field(default_factory=list)
    # registrar not reached yet: the hops from it (heard first), waiting for its own hop
    upstream: dict[str, list[events.StatusDelivered]] = dataclasses.field(default_factory=dict)
    arrived: float = dataclasses.field(default_factory=time.monotonic)


class Tracing:
    """The subscriber that makes spans of events: `callback(event)` of a subscription.

    Let [`trace`][rr_actors_lab.otel.trace] subscribe it (it does so only while a provider
    records spans), or attach it yourself with `Supervisor.subscribe(tracing)` or
    `ResourceRegistrar.subscribe` (then every event reaches it, provider or not). Its calls
    run on the subscription's thread; `flush` and `close` may be called from any thread.

    The RPC spans follow the current semantic conventions (`rpc.system.name`, `rpc.method` =
    `<provider>/<server>`); `OTEL_SEMCONV_STABILITY_OPT_IN=rpc/dup` (read when it is made)
    adds the deprecated `rpc.system`, `rpc.service` and `rr_actors.new_pid`.

    Args:
        tracer_provider: the provider to trace through; `None` (the default) or the API's
            proxy: the global one, `opentelemetry.trace.get_tracer_provider()`, read at
            each event.
        pair_within: seconds a side of a call (a restart, a status hop) waits for the rest
            before it is made a span alone.
        max_pending: sides waiting at most; past it, the oldest is made a span alone
            (also the bound of the query ids, status sends and processes remembered).

    Attributes:
        dropped: events the stream said were lost before this subscriber took them
            (the `count`s of its `EventsDropped`); read from any thread.

    Raises:
        ConfigError: `pair_within` not a positive number or `max_pending` not a positive int.
    """

    def __init__(
        self,
        *,
        tracer_provider: Any = None,
        pair_within: float = 5.0,
        max_pending: int = 10_000,
    ) -> None:
        from rr_actors.errors import ConfigError  # noqa: PLC0415

        if isinstance(pair_within, bool) or not isinstance(pair_within, int | float):
            raise ConfigError(f"pair_within must be seconds > 0, not {pair_within!r}")
        if not pair_within > 0:
            raise ConfigError(f"pair_within must be seconds > 0, not {pair_within!r}")
        if isinstance(max_pending, bool) or not isinstance(max_pending, int) or max_pending < 1:
            raise ConfigError(f"max_pending must be an int > 0, not {max_pending!r}")
        if _api is not None and isinstance(tracer_provider, _api.ProxyTracerProvider):
            tracer_provider = None  # (the global one's stand-in: the global one)
        self._provider = tracer_provider
        self._old_names = _old_rpc_names()
        self._source: _Subscribable | None = None
        self._closing = threading.Event()
        self._watcher: threading.Thread | None = None
        self._subscribing = threading.Lock()  # (the watcher's subscribe against close)
        self._pair_within = float(pair_within)
        self._max_pending = max_pending
        self._lock = threading.Lock()
        self._tracer: Any = None
        self._tracer_of: Any = None
        self._subscription: Any = None
        self._loads: dict[tuple[str, str], events.ResourceLoaded] = {}
        self._servers: dict[tuple[str, str], _Half] = {}  # (query id, "call"/"unload")
        self._clients: dict[tuple[str, str], _Half] = {}
        self._released: dict[tuple[str, str], tuple[str, float]] = {}  # resource: query, at
        self._holders: dict[tuple[str, str], int] = {}  # resource: consumers seen added
        self._unloading: dict[tuple[str, str], tuple[tuple[str, str], _Half]] = {}  # last release
        self._exits: dict[str, events.ChildExited] = {}  # child: its last exit
        self._restarts: dict[int, _Restart] = {}  # the new pid: its restart
        self._doubts: dict[int, list[events.InDoubt]] = {}  # pid: what it found
        self._restored: dict[int, float] = {}  # pid: its first CatalogRestored's `at`
        self._served: dict[tuple[str, str], str] = {}  # (registrar, resource id): server
        self._called: dict[str, str] = {}  # query id held: its server (an unload's name)
        self._traced: dict[str, tuple[str, str]] = {}  # query id: its trace, serving registrar
        self._statuses: collections.OrderedDict[str, _Sent] = collections.OrderedDict()
        self._stalled: dict[str, _Sent] = {}  # the sends some of whose hops wait
        # (pid, registrar): the SERVER span made of its events that ended last, its end (a
        # manager's registrar is named as the child); (the new pid, child): its restart
        # span, still open
        self._last_of: dict[tuple[int, str], tuple[float, Any]] = {}
        self._opened: dict[tuple[int, str], _Opened] = {}
        # (the new pid, child): its restart span, ended before the new one's first span
        self._restarted_by: dict[tuple[int, str], Any] = {}
        self._lost_at: float | None = None  # (monotonic) when the stream last lost events
        self._lost_of: dict[int, int] = {}  # a process killed: events it built, lost
        self._swept = 0.0  # (monotonic) the last sweep after an event
        self._sweep_every = min(SWEEP_EVERY, self._pair_within)
        self.dropped = 0  # (the class docstring's Attributes)

    # -- the subscriber -----------------------------------------------------------------

    @property
    def subscribed(self) -> bool:
        """Whether `trace`'s subscription is open: made at once if a provider recorded spans
        then, else once the global one is installed (within `WATCH_EVERY` seconds)."""
        return self._subscription is not None

    def _current(self) -> Any:
        """The tracer to make spans with, or `None`: no provider, one that records nothing
        (`_silent`), or no extra."""
        if _api is None:
            return None
        provider = self._provider if self._provider is not None else _api.get_tracer_provider()
        if provider is self._tracer_of:  # (the one of the event before: no look)
            return self._tracer
        tracer: Any = None
        if not isinstance(provider, _api.ProxyTracerProvider | _api.NoOpTracerProvider):
            tracer = provider.get_tracer(SCOPE)
            if _silent(provider, tracer):
                tracer = None
            elif not isinstance(getattr(tracer, "id_generator", _Chosen), _Chosen):
                tracer.id_generator = _Chosen(tracer.id_generator)  # (the SDK's: ids chosen)
        self._tracer, self._tracer_of = tracer, provider
        return tracer

    def _waits(self) -> bool:
        """Whether it traces through the global provider, not installed yet (the proxy)."""
        return (
            _api is not None
            and self._provider is None
            and isinstance(_api.get_tracer_provider(), _api.ProxyTracerProvider)
        )

    def _subscribe(self, source: _Subscribable) -> None:
        """Subscribe to `source` now if spans would be recorded; if the global provider is
        not installed yet, once it is (a thread looks every `WATCH_EVERY` s); else never:
        with nothing to record, the tree forwards and queues no event for it."""
        self._source = source
        if self._current() is not None:
            self._subscription = source.subscribe(self)
        elif self._waits():
            self._watcher = threading.Thread(target=self._watch, name="rr-otel-watch", daemon=True)
            self._watcher.start()

    def _watch(self) -> None:
        """The watcher thread: subscribe once the global provider is installed."""
        while not self._closing.wait(WATCH_EVERY):
            if self._waits():
                continue
            with self._subscribing:
                if self._closing.is_set() or self._current() is None or self._source is None:
                    return
                try:
                    self._subscription = self._source.subscribe(self)
                except Exception as exc:  # noqa: BLE001 - (a source stopped meanwhile) logged
                    logger.warning("otel: could not subscribe to %r: %s", self._source, exc)
            return

    def __call__(self, event: events.Event) -> None:
        """Take one event (on the subscription's thread); make the spans it completes."""
        tracer = self._current()
        if tracer is None:
            return
        with self._lock:
            self._take(tracer, event)
            # what waited `pair_within`, looked for at most every SWEEP_EVERY seconds (or
            # once more sides wait than `max_pending`)
            now = time.monotonic()
            waiting = len(self._clients) + len(self._servers)
            if now >= self._swept + self._sweep_every or waiting > self._max_pending:
                self._swept = now
                self._sweep(tracer, now - self._pair_within)

    def flush(self) -> None:
        """Make spans now of every side and restart still waiting for the rest."""
        tracer = self._current()
        if tracer is None:
            return
        with self._lock:
            self._sweep(tracer, float("inf"))

    def close(self, *, timeout: float = 5.0) -> None:
        """Close the subscription `trace` made (if any; it makes none later), then `flush`;
        `timeout`: seconds at most to wait for the events already queued for this subscriber."""
        self._closing.set()
        with self._subscribing:
            subscription, self._subscription = self._subscription, None
        if self._watcher is not None and self._watcher is not threading.current_thread():
            self._watcher.join(timeout)
        if subscription is not None:
            subscription.wait_delivered(timeout=timeout)
            subscription.close()
        self.flush()

    def __enter__(self) -> Tracing:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    # -- events to sides ----------------------------------------------------------------

    def _take(self, tracer: Any, event: events.Event) -> None:  # noqa: PLR0912
        if self._restarts:  # its InDoubt come after its CatalogRestored: until its next event
            restart = self._restarts.get(event.pid)
            if (
                restart is not None
                and restart.restored is not None
                and not isinstance(event, events.InDoubt | events.CatalogRestored)
            ):
                del self._restarts[event.pid]
                self._restart_span(tracer, restart, restart.restored)
        if isinstance(event, events.ResourceLoaded):
            self._loads[event.registrar, event.query_id] = event
            self._served[event.registrar, event.resource_id] = event.server
        elif isinstance(event, events.ConsumerAdded):
            self._added(tracer, event)
        elif isinstance(event, events.LoadFailed):
            self._failed(tracer, event)
        elif isinstance(event, _CALL_ENDS):
            self._call_ended(tracer, event)
        elif isinstance(event, events.ConsumerReleased):
            self._release(tracer, event)
        elif isinstance(event, events.ResourceUnloaded):
            self._unloaded(tracer, event)
        elif isinstance(event, events.QueryForgotten):
            self._forgotten(tracer, event)
        elif isinstance(event, events.EventsDropped):
            self._dropped(event)
        elif isinstance(event, events.StatusSent):
            self._status_sent(tracer, event)
        elif isinstance(event, events.StatusDelivered):
            self._status_delivered(tracer, event)
        elif isinstance(event, events.StatusHandled):
            self._status_handled(tracer, event)
        elif isinstance(event, events.ChildExited):
            self._exits[event.child] = event
        elif isinstance(event, events.ChildRestarted):
            exited = self._exits.pop(event.child, None)
            if exited is None:
                return
            # (its process may have restored before the supervisor said so)
            self._restarts[event.pid] = _Restart(exited, event, self._restored.pop(event.pid, None))
        elif isinstance(event, events.InDoubt):
            self._doubts.setdefault(event.pid, []).append(event)
        elif isinstance(event, events.CatalogRestored):
            restart = self._restarts.get(event.pid)
            if restart is not None:
                if restart.restored is None:
                    restart.restored = event.at
            elif len(self._restored) < self._max_pending:
                self._restored.setdefault(event.pid, event.at)

    def _forgotten(self, tracer: Any, event: events.QueryForgotten) -> None:
        server = self._called.pop(event.query_id, "")
        self._traced.pop(event.query_id, None)
        if event.reason in _UNLOADS:
            attributes = self._rpc(event.serving_rr, server, event.query_id)
            attributes["rr_actors.registrar"] = event.registrar
            attributes["rr_actors.outcome"] = event.reason
            half = _Half(event.serving_rr, server, event.at, event.at, attributes)
            half.trace, half.caller_span = event.trace, event.caller_span
            if event.unload_sent:  # (its stamp: when the release began)
                half.started = hlc.seconds(event.unload_sent)
            self._client(tracer, (event.query_id, "unload"), half)

    def _dropped(self, event: events.EventsDropped) -> None:
        self.dropped += event.count
        self._lost_at = time.monotonic()
        if event.cause == "killed" and len(self._lost_of) < self._max_pending:
            self._lost_of[event.pid] = self._lost_of.get(event.pid, 0) + event.count

    def _rpc(self, service: str, method: str, query_id: str) -> dict[str, Any]:
        """A side's RPC attributes: the current conventions (`rpc.system.name`, `rpc.method`
        fully qualified, `<provider>/<server>`), with `rpc/dup` the deprecated ones too."""
        attributes = {
            "rpc.system.name": SYSTEM,
            "rpc.method": f"{service}/{method}",
            "rr_actors.query_id": query_id,
        }
        if self._old_names:
            attributes["rpc.system"] = SYSTEM
            attributes["rpc.service"] = service
        return attributes

    @staticmethod
    def _named(half: _Half, method: str) -> None:
        """Give `half` its server (`method`), learnt after it was made: its name, `rpc.method`."""
        half.method = method
        if half.attributes.get("rpc.method") != _OTHER:
            half.attributes["rpc.method"] = f"{half.service}/{method}"

    @staticmethod
    def _span_name(half: _Half) -> str:
        """`rpc.method` (`<provider>/<server>`); `rpc.system.name` for a server not recognized."""
        if half.attributes.get("rpc.method") == _OTHER:
            return SYSTEM
        return f"{half.service}/{half.method}"

    def _added(self, tracer: Any, event: events.ConsumerAdded) -> None:
        load = self._loads.pop((event.registrar, event.query_id), None)
        resource = (event.registrar, event.resource_id)
        server = self._served.get(resource, "")
        if server:
            self._holders[resource] = self._holders.get(resource, 0) + 1
        attributes = self._rpc(event.registrar, server, event.query_id)
        attributes["rr_actors.resource_id"] = event.resource_id
        attributes["rr_actors.consumer"] = event.consumer
        attributes["rr_actors.dedup"] = load is None
        attributes["rr_actors.outcome"] = "loaded" if load is not None else "dedup"
        half = _Half(event.registrar, server, event.at, event.at, attributes, trace=event.trace)
        half.pid = event.pid
        if event.query_id not in self._traced and len(self._traced) < self._max_pending:
            self._traced[event.query_id] = (event.trace, "")
        if load is not None:
            half.trace = half.trace or load.trace
            if load.digest is not None:
                attributes["rr_actors.digest"] = load.digest
            half.start = load.at - load.load_s
            callback = {"rr_actors.resource_id": load.resource_id}
            half.children.append(_Child(f"{load.server}.load", half.start, load.at, callback))
        self._server(tracer, (event.query_id, "call"), half)

    def _failed(self, tracer: Any, event: events.LoadFailed) -> None:
        attributes = self._rpc(event.registrar, event.server, event.query_id)
        attributes["rr_actors.resource_id"] = event.resource_id
        attributes["rr_actors.dedup"] = False
        attributes["rr_actors.outcome"] = "load failed"
        error = (event.error_type, event.message)
        half = _Half(event.registrar, event.server, event.at, event.at, attributes, error)
        half.trace, half.pid = event.trace, event.pid
        callback = {"rr_actors.resource_id": event.resource_id}
        half.children.append(_Child(f"{event.server}.load", event.at, event.at, callback, error))
        self._server(tracer, (event.query_id, "call"), half)

    def _call_ended(
        self, tracer: Any, event: events.CallAnswered | events.CallFailed | events.CallWithdrawn
    ) -> None:
        attributes = self._rpc(event.serving_rr, event.server, event.query_id)
        attributes["rr_actors.registrar"] = event.registrar
        error = None
        if isinstance(event, events.CallAnswered):
            if len(self._called) < self._max_pending:  # (its unload's span names it)
                self._called[event.query_id] = event.server
            if event.query_id in self._traced or len(self._traced) < self._max_pending:
                self._traced[event.query_id] = (event.trace, event.serving_rr)
            attributes["rr_actors.outcome"] = "answered"
            attributes["rr_actors.retry"] = event.retry
        elif isinstance(event, events.CallFailed):
            if event.error_type in _UNRECOGNIZED:  # (the conventions: a bounded cardinality)
                attributes["rpc.method_original"] = attributes["rpc.method"]
                attributes["rpc.method"] = _OTHER
            attributes["rr_actors.outcome"] = "failed"
            attributes["rr_actors.retry"] = event.retry
            attributes["rr_actors.may_have_executed"] = event.may_have_executed
            error = (event.error_type, event.message)
        else:
            attributes["rr_actors.outcome"] = f"withdrawn: {event.reason}"
        half = _Half(event.serving_rr, event.server, event.at, event.at, attributes, error)
        half.trace, half.caller_span, half.started = event.trace, event.caller_span, event.started
        self._client(tracer, (event.query_id, "call"), half)

    def _release(self, tracer: Any, event: events.ConsumerReleased) -> None:
        resource = (event.registrar, event.resource_id)
        self._released[resource] = (event.query_id, event.at)
        left = self._holders.get(resource)
        if left is not None:
            self._holders[resource] = left - 1
        if self._traced.get(event.query_id, ("", "-"))[1] == "":  # (the consumer's: its own)
            del self._traced[event.query_id]
        if event.reason != "unload":
            return
        server = self._served.get((event.registrar, event.resource_id), "")
        attributes = self._rpc(event.registrar, server, event.query_id)
        attributes["rr_actors.resource_id"] = event.resource_id
        attributes["rr_actors.consumer"] = event.consumer
        attributes["rr_actors.outcome"] = "released"
        half = _Half(event.registrar, server, event.at, event.at, attributes, trace=event.trace)
        half.pid = event.pid
        if left == 1:  # the last consumer: its ResourceUnloaded follows, to go under it
            self._unloading[resource] = ((event.query_id, "unload"), half)
        else:
            self._server(tracer, (event.query_id, "unload"), half)

    def _unloaded(self, tracer: Any, event: events.ResourceUnloaded) -> None:
        resource = (event.registrar, event.resource_id)
        query_id, began = self._released.pop(resource, ("", event.at))
        self._served.pop(resource, None)
        self._holders.pop(resource, None)
        child = _Child(
            f"{event.server}.unload", began, event.at, {"rr_actors.resource_id": event.resource_id}
        )
        parked = self._unloading.pop(resource, None)
        if parked is not None:
            key, half = parked
            half.end = max(half.end, event.at)
            half.children.append(child)
            self._server(tracer, key, half)
            return
        waiting = self._servers.get((query_id, "unload"))
        if waiting is not None:  # its release waits for its client: the callback goes under it
            self._named(waiting, event.server)
            waiting.end = max(waiting.end, event.at)
            waiting.children.append(child)
        else:
            self._emit_child(tracer, None, child, [])

    # -- statuses -----------------------------------------------------------------------

    def _sent(self, tracer: Any, status_id: str) -> _Sent:
        sent = self._statuses.get(status_id)
        if sent is None:
            sent = self._statuses[status_id] = _Sent()
            if len(self._statuses) > self._max_pending:  # the oldest send is forgotten
                _id, oldest = self._statuses.popitem(last=False)
                self._stalled.pop(_id, None)
                self._give_up(tracer, _id, oldest)
        return sent

    def _give_up(self, tracer: Any, status_id: str, sent: _Sent) -> None:
        """Make spans of the hops of `sent` still waiting: under a stand-in for its send
        if that was not heard, under the send if the hop before them was not."""
        if sent.context is None:
            self._stand_in(tracer, status_id, sent)
        while sent.upstream:
            _registrar, hops = sent.upstream.popitem()
            for hop in hops:
                self._hop(tracer, sent, hop, wait=False)

    def _call_links(self, query_id: str) -> list[Any]:
        """Links to the CLIENT and SERVER spans of the call of `query_id`, if it was heard."""
        known = self._traced.get(query_id)
        if known is None:
            return []
        parsed = traces.parse(known[0]) if known[0] else _untraced(query_id, "call")
        if parsed is None:
            return []
        trace_id, client, flags = parsed
        return [
            _api.Link(
                _api.SpanContext(
                    trace_id, span, is_remote=True, trace_flags=_api.TraceFlags(flags)
                ),
                {"rr_actors.query_id": query_id, "rr_actors.side": side},
            )
            for span, side in ((client, "client"), (traces.server_span(client), "server"))
        ]

    def _status_sent(self, tracer: Any, event: events.StatusSent) -> None:
        sent = self._sent(tracer, event.status_id)
        if sent.context is not None:  # (heard twice, or stood in for)
            return
        attributes = {
            "rr_actors.registrar": event.registrar,
            "rr_actors.query_id": event.query_id,
            "rr_actors.status": event.status.name,
            "rr_actors.status_id": event.status_id,
            "rr_actors.message": event.message,
        }
        span = self._start(
            tracer,
            (_derived(event.status_id, bits=128), _derived(event.status_id, "sent")),
            f"status {event.status.name}",
            kind=_api.SpanKind.PRODUCER,
            attributes=attributes,
            links=self._call_links(event.query_id),
            start_time=_ns(event.at),
        )
        span.end(end_time=_ns(event.at))
        sent.context, sent.at = span.get_span_context(), event.at
        for hop in sorted(sent.waiting, key=lambda h: h.hop):
            self._hop(tracer, sent, hop)
        sent.waiting.clear()

    def _stand_in(self, tracer: Any, status_id: str, sent: _Sent) -> None:
        """The span of a send whose `StatusSent` was not heard (dropped, or a subscriber
        of the consumers only), marked incomplete: its hops' parent."""
        first = min(sent.waiting, key=lambda h: h.hop)
        at = min(h.at - h.latency_s for h in sent.waiting)
        span = self._start(
            tracer,
            (_derived(status_id, bits=128), _derived(status_id, "sent")),
            f"status {first.status.name}",
            kind=_api.SpanKind.PRODUCER,
            attributes={
                "rr_actors.status": first.status.name,
                "rr_actors.status_id": status_id,
                "rr_actors.incomplete": True,
            },
            start_time=_ns(at),
        )
        span.end(end_time=_ns(at))
        sent.context, sent.at = span.get_span_context(), at
        for hop in sorted(sent.waiting, key=lambda h: h.hop):
            self._hop(tracer, sent, hop)
        sent.waiting.clear()

    def _status_delivered(self, tracer: Any, event: events.StatusDelivered) -> None:
        sent = self._sent(tracer, event.status_id)
        if sent.context is None:  # its send's span first: it is the parent
            sent.waiting.append(event)
            self._stalled[event.status_id] = sent
        else:
            self._hop(tracer, sent, event)
            if not sent.upstream:  # (nothing of it waits any more)
                self._stalled.pop(event.status_id, None)

    def _hop(
        self, tracer: Any, sent: _Sent, event: events.StatusDelivered, *, wait: bool = True
    ) -> None:
        """A hop's span: under the hop that brought the status to the registrar it came
        from (waited for, with `wait`, until `pair_within`), else under its send; linked
        to its call's spans."""
        serving = self._traced.get(event.query_id, ("", ""))[1]
        before = sent.reached.get(serving) if event.hop > 1 and serving else None
        if before is None and event.hop > 1 and serving and wait:
            sent.upstream.setdefault(serving, []).append(event)
            self._stalled[event.status_id] = sent
            return
        parent, start = before if before is not None else (sent.context, sent.at)
        attributes = {
            "rr_actors.registrar": event.registrar,
            "rr_actors.query_id": event.query_id,
            "rr_actors.status": event.status.name,
            "rr_actors.status_id": event.status_id,
            "rr_actors.hop": event.hop,
            "rr_actors.latency_s": event.latency_s,
        }
        span = self._start(
            tracer,
            (parent.trace_id, _derived(event.status_id, event.registrar, event.query_id)),
            f"status {event.status.name} hop {event.hop}",
            context=_api.set_span_in_context(_api.NonRecordingSpan(parent)),
            kind=_api.SpanKind.CONSUMER,
            attributes=attributes,
            links=self._call_links(event.query_id),
            start_time=_ns(min(start, event.at)),
        )
        span.end(end_time=_ns(event.at))
        if event.registrar not in sent.reached:
            sent.reached[event.registrar] = (span.get_span_context(), event.at)
            for hop in sent.upstream.pop(event.registrar, []):
                self._hop(tracer, sent, hop)

    def _status_handled(self, tracer: Any, event: events.StatusHandled) -> None:
        """A status callback's run: a trace of its own (the calls made in it its
        children: it ran with these ids current), linked to the hop that brought it."""
        hop = _api.SpanContext(
            _derived(event.status_id, bits=128),
            _derived(event.status_id, event.registrar, event.query_id),
            is_remote=True,
            trace_flags=_api.TraceFlags(1),
        )
        span = self._start(
            tracer,
            traces.status_callback(event.status_id, event.registrar, event.query_id),
            f"status {event.status.name} callback",
            context=_api.set_span_in_context(_api.INVALID_SPAN),  # (a root)
            kind=_api.SpanKind.INTERNAL,
            attributes={
                "rr_actors.registrar": event.registrar,
                "rr_actors.query_id": event.query_id,
                "rr_actors.status": event.status.name,
                "rr_actors.status_id": event.status_id,
            },
            links=[_api.Link(hop, {"rr_actors.status_id": event.status_id})],
            start_time=_ns(hlc.seconds(event.began) if event.began else event.at),
        )
        span.end(end_time=_ns(event.at))

    # -- sides to spans -----------------------------------------------------------------

    def _server(self, tracer: Any, key: tuple[str, str], half: _Half) -> None:
        if half.pid:  # (the provider's process; the subscriber's may be another)
            half.attributes["process.pid"] = half.pid
        client = self._clients.pop(key, None)
        if client is None:
            self._servers[key] = half
        else:
            self._emit(tracer, client, half, key)

    def _client(self, tracer: Any, key: tuple[str, str], half: _Half) -> None:
        server = self._servers.pop(key, None)
        if server is None:
            self._clients[key] = half
        else:
            self._emit(tracer, half, server, key)

    def _sweep(self, tracer: Any, before: float) -> None:
        """Make spans alone of the restarts and sides waiting since before `before`."""
        for pid in [p for p, r in self._restarts.items() if r.arrived <= before]:
            restart = self._restarts.pop(pid)  # (first: the releases whose unload it cut)
            self._restart_span(tracer, restart, restart.restored or restart.restarted.at)
        for resource in [r for r, (_k, h) in self._unloading.items() if h.arrived <= before]:
            self._server(tracer, *self._unloading.pop(resource))
        for status_id, sent in list(self._stalled.items()):
            if not (sent.waiting or sent.upstream):
                del self._stalled[status_id]
            elif sent.arrived <= before:
                del self._stalled[status_id]
                self._give_up(tracer, status_id, sent)
        for waiting in (self._clients, self._servers):
            for key in _late(waiting, before, self._max_pending):
                self._alone(tracer, waiting, key)
        for child in [c for c, o in self._opened.items() if o.arrived <= before]:
            opened = self._opened.pop(child)
            self._close_restart(opened)  # (the new one's first span, if any, links to it)
            self._restarted_by[child] = opened.span.get_span_context()
            if len(self._restarted_by) > self._max_pending:
                del self._restarted_by[next(iter(self._restarted_by))]
        if before == float("inf"):
            self._restarted_by.clear()
            self._called.clear()
            self._doubts.clear()
            self._exits.clear()
            self._restored.clear()

    def _alone(self, tracer: Any, waiting: dict[tuple[str, str], _Half], key: Any) -> None:
        """Make the side of `key` waiting in `waiting` (`_clients`, `_servers`) a span alone
        (marked incomplete if it may have waited for a side the stream lost)."""
        alone = waiting.pop(key, None)
        if alone is None:
            return
        lost = self._lost_at + self._pair_within if self._lost_at is not None else None
        if lost is not None and alone.arrived <= lost:  # its other side: lost?
            alone.attributes["rr_actors.incomplete"] = True
        clients = waiting is self._clients
        self._emit(tracer, alone if clients else None, None if clients else alone, key)

    def _emit(
        self, tracer: Any, client: _Half | None, server: _Half | None, key: tuple[str, str]
    ) -> None:
        context = None
        # the ids the call carried; an untraced one's, derived from its query id
        carried = (client.trace if client else "") or (server.trace if server else "")
        if carried:
            parsed = traces.parse(carried)
        elif server is not None and client is None and server.root:
            parsed = None
        else:
            parsed = _untraced(*key)
        if client is not None and server is not None:  # a side that did not know its server
            method = client.method or server.method
            self._named(client, method)
            self._named(server, method)
        if client is not None:
            start = min(client.start, server.start) if server is not None else client.start
            if client.started:  # (when the call began: known since event schema 7)
                start = client.started
            name = self._span_name(client)
            # (a caller's span: the call carried its trace)
            parent = traces.caller_parent(carried, client.caller_span) if carried else None
            span = self._start(
                tracer,
                (parsed[0], parsed[1]) if parsed is not None else None,
                name,
                context=_api.set_span_in_context(_api.NonRecordingSpan(parent))
                if parent is not None
                else _ROOT,
                kind=_api.SpanKind.CLIENT,
                attributes=client.attributes,
                links=client.links,
                start_time=_ns(start),
            )
            self._end(span, client.error, max(client.end, start), client.lost)
            context = _api.set_span_in_context(span)
        if server is not None:
            name = self._span_name(server)
            ids = None
            if parsed is not None:  # its parent: the CLIENT span the call named
                trace_id, client_span, flags = parsed
                ids = (trace_id, traces.server_span(client_span))
                if context is None:  # (not made here: the one its ids name)
                    called = _api.SpanContext(
                        trace_id, client_span, is_remote=True, trace_flags=_api.TraceFlags(flags)
                    )
                    context = _api.set_span_in_context(_api.NonRecordingSpan(called))
            links = server.links
            restart = (
                None if server.lost else self._restarted_by.pop((server.pid, server.service), None)
            )
            if restart is not None:  # the first after a restart ended
                links = [*links, _api.Link(restart, {"rr_actors.incarnation": "restart"})]
            span = self._start(
                tracer,
                ids,
                name,
                context=context if context is not None else _ROOT,
                kind=_api.SpanKind.SERVER,
                attributes=server.attributes,
                links=links,
                start_time=_ns(server.start),
            )
            if server.children:
                inner = _api.set_span_in_context(span)
                for child in server.children:
                    self._emit_child(tracer, inner, child, server.links)
            self._end(span, server.error, max(server.end, server.start), server.lost)
            self._incarnations(server, span.get_span_context())

    @staticmethod
    def _start(tracer: Any, ids: tuple[int, int] | None, name: str, **options: Any) -> Any:
        """`tracer.start_span(name, **options)`, with the (trace, span) ids `ids` if given
        (with the SDK's tracer; another one draws its own)."""
        chosen = getattr(tracer, "id_generator", None)
        if ids is None or not isinstance(chosen, _Chosen):
            return tracer.start_span(name, **options)
        chosen.choose(*ids)
        try:
            return tracer.start_span(name, **options)
        finally:
            chosen.clear()

    def _emit_child(self, tracer: Any, context: Any, child: _Child, links: list[Any]) -> None:
        span = tracer.start_span(
            child.name,
            context=context if context is not None else _ROOT,
            kind=_api.SpanKind.INTERNAL,
            attributes=child.attributes,
            links=links,
            start_time=_ns(child.start),
        )
        if child.error is not None:
            kind, message = child.error
            span.add_event(
                "exception",
                {"exception.type": kind, "exception.message": message},
                timestamp=_ns(child.end),
            )
        self._end(span, child.error, child.end, child.lost)

    @staticmethod
    def _end(span: Any, error: tuple[str, str] | None, end: float, lost: str = "") -> None:
        if error is not None:
            kind, message = error
            span.set_attribute("error.type", kind)
            span.set_status(_api.Status(_api.StatusCode.ERROR, f"{kind}: {message}"))
        elif lost:
            span.set_status(_api.Status(_api.StatusCode.ERROR, f"its end was lost: {lost}"))
        span.end(end_time=_ns(end))

    def _incarnations(self, server: _Half, made: Any) -> None:
        """Note a SERVER span made of a process's events: its last (a restart links to
        it), or its first after a restart (linked, the restart span ended); a span whose
        end was lost is linked from its restart span while that is open."""
        if server.restart is not None and not server.restart.ended:
            server.restart.span.add_link(
                made, {"rr_actors.incarnation": "old", "rr_actors.end_lost": True}
            )
        if not server.pid or server.lost:
            return
        incarnation = (server.pid, server.service)
        known = self._last_of.pop(incarnation, None)  # (the most recent last: oldest out)
        if known is None or known[0] <= server.end:  # (one made before may have ended later)
            known = (server.end, made)
        self._last_of[incarnation] = known
        if len(self._last_of) > self._max_pending:
            del self._last_of[next(iter(self._last_of))]
        opened = self._opened.pop(incarnation, None)
        if opened is not None:
            opened.span.add_link(made, {"rr_actors.incarnation": "new"})
            self._close_restart(opened)

    @staticmethod
    def _close_restart(opened: _Opened) -> None:
        opened.ended = True
        opened.span.end(end_time=_ns(opened.end))

    def _restart_span(self, tracer: Any, restart: _Restart, end: float) -> None:
        """The restart's span, linked to the old incarnation's last span (its sides still
        waiting for their callers' made first, alone: `_settle`); the spans the kill cut
        short, ended at the exit and marked."""
        exited, restarted = restart.exited, restart.restarted
        doubts = self._doubts.pop(restarted.pid, [])
        attributes: dict[str, Any] = {
            "rr_actors.supervisor": exited.supervisor,
            "rr_actors.child": exited.child,
            "rr_actors.reason": exited.reason,
            "process.pid": restarted.pid,  # (the new incarnation's: the restart made it)
            "rr_actors.old_pid": exited.pid,
            "rr_actors.restart_s": restarted.restart_s,
            "rr_actors.in_doubt": [d.query_id for d in doubts],
        }
        if self._old_names:
            attributes["rr_actors.new_pid"] = restarted.pid
        lost_events = self._lost_of.pop(exited.pid, 0)
        if lost_events:  # the dead process built them, never forwarded: spans missing
            attributes["rr_actors.events_lost"] = lost_events
            attributes["rr_actors.incomplete"] = True
        self._settle(tracer, exited, restarted)
        last = self._last_of.pop((exited.pid, exited.child), None)  # the old one's last span
        span = tracer.start_span(
            f"restart {exited.child}",
            context=_ROOT,
            kind=_api.SpanKind.INTERNAL,
            attributes=attributes,
            links=[_api.Link(last[1], {"rr_actors.incarnation": "old"})] if last else [],
            start_time=_ns(exited.at),
        )
        # open until the new incarnation's first span links to it (or `pair_within`)
        opened = _Opened(span, max([end, exited.at, *(d.at for d in doubts)]))
        previous = self._opened.pop((restarted.pid, exited.child), None)
        if previous is not None:
            self._close_restart(previous)
        self._opened[restarted.pid, exited.child] = opened
        links = [_api.Link(span.get_span_context())]
        ended_by = f"restart {exited.child}"
        lost = {"rr_actors.end_lost": True, "rr_actors.ended_by": ended_by}
        for key in [k for k, load in self._loads.items() if load.pid == exited.pid]:
            load = self._loads.pop(key)  # loaded, never added: cut between the two
            attributes = self._rpc(load.registrar, load.server, load.query_id) | lost
            half = _Half(load.registrar, load.server, load.at - load.load_s, exited.at, attributes)
            half.links, half.lost, half.restart, half.trace = links, ended_by, opened, load.trace
            half.pid = load.pid
            load_attributes = {"rr_actors.resource_id": load.resource_id}  # (it ended)
            half.children.append(
                _Child(f"{load.server}.load", half.start, load.at, load_attributes)
            )
            self._server(tracer, (load.query_id, "call"), half)
        doubts = self._cut_unloads(tracer, restart, doubts, opened)
        for doubt in doubts:  # started, never committed: cut inside its callback
            # its query id is the resource's (the call's is not known at the provider):
            # a load's call is the one failed call to that server that may have executed;
            # an unload's release, not heard (not a last consumer's `unload`): none
            calls = [
                key
                for key, half in self._clients.items()
                if (half.service, half.method) == (doubt.registrar, doubt.server)
                and half.attributes.get("rr_actors.may_have_executed")
                and doubt.cut in ("load", "")
            ]
            query_id = calls[0][0] if len(calls) == 1 else doubt.query_id
            attributes = self._rpc(doubt.registrar, doubt.server, query_id) | lost
            attributes["rr_actors.resource_id"] = doubt.query_id
            attributes["rr_actors.in_doubt"] = True
            half = _Half(doubt.registrar, doubt.server, exited.at, exited.at, attributes)
            half.links, half.lost, half.restart = links, ended_by, opened
            half.pid = attributes["process.pid"] = exited.pid  # (cut in the old incarnation)
            half.root = len(calls) != 1  # (its call not found: a root, not a lost child)
            verb = doubt.cut or "load"
            callback = {"rr_actors.resource_id": doubt.query_id} | lost
            half.children.append(
                _Child(f"{doubt.server}.{verb}", exited.at, exited.at, callback, lost=ended_by)
            )
            key = (query_id, "call" if verb == "load" else "unload")
            if half.root:  # (no other side to wait for)
                self._emit(tracer, None, half, key)
            else:
                self._server(tracer, key, half)

    def _settle(
        self, tracer: Any, exited: events.ChildExited, restarted: events.ChildRestarted
    ) -> None:
        """Make spans now, alone, of the old incarnation's SERVER sides still waiting for
        their callers' (another host's subscriber makes those, or the caller's is late):
        its last span is among them, and its restart span links to it when it starts
        (OpenTelemetry takes links then). A caller's side heard later is made alone, with
        the ids the call carried: still the parent."""
        for key in [
            key
            for key, half in self._servers.items()
            if half.service == exited.child and not half.lost and _old(half, exited, restarted)
        ]:
            self._alone(tracer, self._servers, key)

    def _cut_unloads(
        self,
        tracer: Any,
        restart: _Restart,
        doubts: list[events.InDoubt],
        opened: _Opened,
    ) -> list[events.InDoubt]:
        """The old incarnation's last releases whose unload's end the kill lost (their
        `ResourceUnloaded` never came): each ended at the exit, marked, its `unload`
        callback's span under it ended so too (the `InDoubt` of its resource, if any, is
        this span). The doubts left: those of no release heard."""
        exited = restart.exited
        ended_by = f"restart {exited.child}"
        lost = {"rr_actors.end_lost": True, "rr_actors.ended_by": ended_by}
        named = {(d.registrar, d.query_id): d for d in doubts if d.cut == "unload"}
        for resource in [
            r for r, (_k, h) in self._unloading.items() if _old(h, exited, restart.restarted)
        ]:
            key, half = self._unloading.pop(resource)
            self._released.pop(resource, None)  # (the next incarnation's unload: its own)
            doubt = named.pop(resource, None)
            half.attributes.update(lost)
            if doubt is not None:
                half.attributes["rr_actors.in_doubt"] = True
                self._named(half, half.method or doubt.server)
            half.links = [_api.Link(opened.span.get_span_context())]
            half.lost, half.restart, half.end = ended_by, opened, max(half.end, exited.at)
            callback = {"rr_actors.resource_id": resource[1]} | lost
            half.children.append(
                _Child(f"{half.method}.unload", half.start, half.end, callback, lost=ended_by)
            )
            self._server(tracer, key, half)
        return [d for d in doubts if d.cut != "unload" or (d.registrar, d.query_id) in named]


def trace(source: _Subscribable, **options: Any) -> Tracing:
    """Trace what `source` does: subscribe a [`Tracing`][rr_actors_lab.otel.Tracing] to it.

    It subscribes only while spans would be recorded: with no provider installed yet (the
    API's proxy), once the application installs the global one (a thread looks every
    `WATCH_EVERY` seconds; the events before are not heard); with a provider that records
    nothing (the API's no-op one, an SDK disabled or sampling `always_off`), or without the
    extra, never. Unsubscribed, it costs the tree nothing: no event is forwarded or queued.

    Args:
        source: a `Supervisor` (its whole tree, manager processes included) or a
            `ResourceRegistrar` (its own events): anything with `subscribe(callback)`.
        options: `Tracing`'s keyword arguments (`tracer_provider`, `pair_within`,
            `max_pending`).

    Returns:
        The subscriber, subscribed; `close()` it (or use it in a `with` block) to
        unsubscribe and make spans of what still waits.

    Raises:
        ConfigError: a bad option, `source` has no `subscribe`, or (subscribing at once)
            `source` cannot be subscribed to (a stopped supervisor); a later subscription
            that fails is logged (WARNING).
    """
    from rr_actors.errors import ConfigError  # noqa: PLC0415

    tracing = Tracing(**options)
    if not callable(getattr(source, "subscribe", None)):
        raise ConfigError(f"cannot trace {source!r}: it has no subscribe(callback)")
    tracing._subscribe(source)
    return tracing


@contextlib.contextmanager
def root_span(
    name: str, *, tracer_provider: Any = None, attributes: dict[str, Any] | None = None
) -> Iterator[Any]:
    """A block run under a new trace: an INTERNAL span with no parent, current in it.

    What `rr-actors demo --trace` runs each mission step under: the calls made in the block
    (on this thread, or in a task started in it) are its descendants; a span current when
    the block starts is not its parent (each step is a trace of its own).

        with otel.root_span("mission step drive"):   # the span ends with the block
            registrar.call("cm", "lidar", request)    # CLIENT span: its child

    Args:
        name: the span's name.
        tracer_provider: the provider to trace through; `None`: the global one.
        attributes: the span's attributes.

    Yields:
        The span; `None` without the otel extra or a provider installed (the block runs).
    """
    if _api is None:
        yield None
        return
    provider = tracer_provider if tracer_provider is not None else _api.get_tracer_provider()
    if isinstance(provider, _api.ProxyTracerProvider | _api.NoOpTracerProvider):
        yield None
        return
    from opentelemetry import context as _context  # noqa: PLC0415

    tracer = provider.get_tracer(SCOPE)
    with tracer.start_as_current_span(
        name, context=_context.Context(), kind=_api.SpanKind.INTERNAL, attributes=attributes
    ) as span:
        yield span


EXPORTERS = "opentelemetry_traces_exporter"
"""The entry-point group of span exporters, by the name `OTEL_TRACES_EXPORTER` gives."""


def provider_from_environment() -> Any:
    """An SDK `TracerProvider` set up by the `OTEL_*` environment variables, as
    `opentelemetry-instrument` sets one up.

    `OTEL_TRACES_EXPORTER`: comma-separated `opentelemetry_traces_exporter` entry points
    (`console`, `otlp` (default), `none`), each behind a `BatchSpanProcessor`; the resource,
    sampler and limits are the SDK's own reading of `OTEL_*`, and each exporter reads its own.

    Returns:
        The provider (not installed as the global one); `shutdown()` it to export the rest.

    Raises:
        ConfigError: the SDK (`opentelemetry-sdk`, the `otel` extra) is missing, or an
            exporter named is not installed.
    """
    from importlib.metadata import entry_points  # noqa: PLC0415

    from rr_actors.errors import ConfigError  # noqa: PLC0415

    try:
        from opentelemetry.sdk.resources import Resource  # noqa: PLC0415
        from opentelemetry.sdk.trace import TracerProvider  # noqa: PLC0415
        from opentelemetry.sdk.trace.export import BatchSpanProcessor  # noqa: PLC0415
    except ImportError as exc:
        raise ConfigError(
            f"tracing needs the otel extra (opentelemetry-sdk): pip install 'rr_actors[otel]' "
            f"({exc})"
        ) from None
    named = os.environ.get("OTEL_TRACES_EXPORTER", "otlp")
    names = [n.strip() for n in named.split(",") if n.strip() and n.strip() != "none"]
    exporters = []
    for name in names:
        found = entry_points(group=EXPORTERS, name=name)
        if not found:
            known = sorted(e.name for e in entry_points(group=EXPORTERS))
            raise ConfigError(
                f"OTEL_TRACES_EXPORTER names {name!r}, which is not installed "
                f"(installed: {', '.join(known) or 'none'}; 'otlp' comes with "
                f"opentelemetry-exporter-otlp)"
            )
        exporters.append(next(iter(found)).load()())
    provider = TracerProvider(resource=Resource.create())
    for exporter in exporters:
        provider.add_span_processor(BatchSpanProcessor(exporter))
    return provider


class Exporting:
    """What `--trace` does (`rr-actors demo`, `rr-actors experiment`): the spans of the trees it
    is given, exported where the `OTEL_*` environment variables say.

        with otel.Exporting() as exporting:      # provider_from_environment()
            exporting.trace(sup)                 # otel.trace(sup, tracer_provider=...)
            ...                                  # on leaving: close each, then export

    The provider becomes the global one unless the application installed one first.

    Raises:
        ConfigError: as `provider_from_environment`.
    """

    def __init__(self) -> None:
        self.provider = provider_from_environment()
        if _api is not None and isinstance(_api.get_tracer_provider(), _api.ProxyTracerProvider):
            _api.set_tracer_provider(self.provider)
        self._tracings: list[Tracing] = []

    def trace(self, source: _Subscribable) -> Tracing:
        """Trace `source` (a `Supervisor`, a registrar) through this provider; any thread."""
        tracing = trace(source, tracer_provider=self.provider)
        self._tracings.append(tracing)
        return tracing

    def root_span(self, name: str, **options: Any) -> contextlib.AbstractContextManager[Any]:
        """A block run under a new trace of this provider (`root_span`'s `name`, `attributes`)."""
        return root_span(name, tracer_provider=self.provider, **options)

    def close(self) -> None:
        """Close every `Tracing` made (their spans made), then export what waits."""
        for tracing in self._tracings:
            tracing.close()
        self._tracings.clear()
        self.provider.shutdown()

    def __enter__(self) -> Exporting:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
