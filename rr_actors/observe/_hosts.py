"""The observer across hosts: each host shares its page's state as JSON; any host shows all.

```
 host B (sharing)                                   host A (serving a page)
 LiveSource ─► local Hub ─► Share ── delta (JSON puts, numbered) ──► SystemView ─► page Hub
                             │  └─── state (queryable: JSON) ◄──── asked at a gap ┘   │
                             │  └─── here (liveliness token) ────► live / stale       │
                             └ fault (queryable) ◄── JSON command ── page's button ───┘
                  LinkWatch ─► "links" (each member's link: up, or cut since when, why)
```

Keys (`rr_actors._transport.zenoh.wire.Keys`, all under `rr/<system>/obs/<member>/`):
`delta`, `state`, `fault`, `here`. The system's access control admits them for members
only (mutual TLS, then Zenoh's ACL on `rr/<system>/**`).

What crosses is JSON (`json`, never a pickle), and what a host receives is checked before
it reaches the page (`valid_*`): a section it does not know, a value of the wrong shape,
a message too big or out of sequence is dropped (out of sequence: the whole state is
asked again). The page shows every text with `textContent`, never as HTML.

A delta is `{"v": 1, "member", "instance", "seq", "sections": [[key, "v"|"p", value or
patch]], "events": [...], "missed"}`; a patch is `_delta.diff`'s. The state is `{"v": 1,
"member", "instance", "seq", "sections": {key: value}, "events": [...]}`, consistent
with the delta numbered `seq`. The shared sections are `host` (member, title, pid,
allow_faults), `tree`, `catalog/<registrar>`, `links`, `ended`.

A fault command is `{"kind": "kill"|"hang"|"resume"|"fatal", "by": member, ...}` with
the fields of the page's own request (`_faults.inject`); the answer `{"ok", "message",
"status"}`. A host that was not opened with `allow_faults=True` refuses every one, with
that reason.

Threads: `Share` has one (`rr-observe-share-<member>`); `SystemView` one executor
(`rr-observe-system`); Zenoh's callbacks only queue. A fault command runs on a thread of
its own (a FATAL waits for its delivery), at most `MAX_FAULTS` at once.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import json
import logging
import threading
import time
import uuid
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from rr_actors._core.serial import SerialExecutor
from rr_actors._transport.zenoh.wire import ObserverKey
from rr_actors.config import NAME
from rr_actors.observe._delta import apply, diff
from rr_actors.observe._faults import KINDS, FaultRefused, Faults, inject
from rr_actors.observe._hub import BATCH, RING, Hub
from rr_actors.observe._sources import event_dict
from rr_actors.observe._view import dependency_graph

if TYPE_CHECKING:
    import zenoh

    from rr_actors import events as events_module
    from rr_actors._core.bus import Subscription
    from rr_actors._transport.zenoh.net import Services

__all__ = [
    "COALESCE",
    "LINKS_EVERY",
    "MAX_MESSAGE",
    "Share",
    "SystemView",
    "valid_catalog",
    "valid_tree",
]

logger = logging.getLogger("rr_actors")

VERSION = 1
"""The version of what crosses (a message of another version is dropped)."""

COALESCE = 0.01
"""Seconds the share waits after a change, so that changes close together go as one."""

LINKS_EVERY = 0.5
"""Seconds between two looks at this host's links (and at hosts that owe a state)."""

FLUSH_TIMEOUT = 2.0
"""Seconds a stopping supervisor's observer waits for its final state to be shared."""

ASK_EVERY = 1.0
"""Seconds between two asks of one host's state (after a gap, a token back, a timeout)."""

STATE_TIMEOUT = 5.0
"""Seconds a host has to answer an ask for its state."""

FAULT_TIMEOUT = 8.0
"""Seconds a page's host waits for another host's answer to a fault command."""

MAX_MESSAGE = 32 * 1024 * 1024
"""Bytes a delta or a state may have (a catalog of 10,000 resources is a few MiB)."""

MAX_COMMAND = 4096
"""Bytes a fault command may have."""

MAX_FAULTS = 4
"""Fault commands from other hosts run at once; one more is refused."""

EVENTS_WINDOW = 0.5
"""Seconds the system's event stream holds an event for others to overtake it (its
hybrid logical clock order; `ZenohNetwork.subscribe_events`)."""


def _dumps(value: Any) -> bytes:
    return json.dumps(value, separators=(",", ":")).encode()


def _shared(key: str) -> bool:
    """Whether a section of a host's own hub crosses to other hosts."""
    if key in ("host", "tree", "links", "ended"):
        return True
    return key.startswith("catalog/") and NAME.fullmatch(key[8:]) is not None


# -- this host's share --------------------------------------------------------------------------


class Share:
    """Publishes this host's observer state (its hub's sections and events) to the system.

    Args:
        hub: the host's own hub (what its `LiveSource` keeps up to date).
        services: the router's session and what goes with it.
        member: this host's member name.
        host: what the page says of this host (title, pid).
        faults: the teaching mode's faults (`None`: every fault command is refused).
        all_events: share every event of the hub; `False`: only the observer's own
            (a fault from a page), when the pages get the events of every host from the
            system's event stream (`ZenohNetwork.subscribe_events`).
    """

    def __init__(
        self,
        hub: Hub,
        services: Services,
        member: str,
        *,
        host: dict[str, Any],
        faults: Faults | None,
        all_events: bool = True,
    ) -> None:
        self.member = member
        self._all_events = all_events
        self.hub = hub
        self._services = services
        self._faults = faults
        self._keys = services.keys
        self.instance = uuid.uuid4().hex[:12]
        self._lock = threading.Lock()  # held while a message is made (and `state`)
        self._seq = 0
        self._values: dict[str, Any] = {}
        self._events: collections.deque[dict[str, Any]] = collections.deque(maxlen=RING)
        self._listeners: list[Callable[[dict[str, Any]], None]] = []
        self._queries: collections.deque[zenoh.Query] = collections.deque()
        self._wake = threading.Event()
        self._closing = threading.Event()
        self._running_faults = threading.BoundedSemaphore(MAX_FAULTS)
        self._passes = threading.Condition()
        self._started = self._done = 0  # the thread's passes: begun, and ended
        self.sent_bytes = 0
        self.sent_messages = 0
        hub.put("host", {**host, "member": member, "allow_faults": faults is not None})
        self._unlisten = hub.listen(self._wake.set)
        session = services.session
        self._publisher = session.declare_publisher(self._key("delta"))
        self._state = session.declare_queryable(self._key("state"), self._on_state)
        self._fault = session.declare_queryable(self._key("fault"), self._on_fault)
        self._thread = threading.Thread(
            target=self._run, name=f"rr-observe-share-{member}", daemon=True
        )
        self._thread.start()
        self._token = session.liveliness().declare_token(self._key("here"))

    def _key(self, part: str) -> str:
        return self._keys.observer(ObserverKey(self.member, part))

    def listen(self, listener: Callable[[dict[str, Any]], None]) -> None:
        """Call `listener(message)` with every delta (on the share's thread; must not block)."""
        with self._lock:
            self._listeners.append(listener)

    def state(self) -> dict[str, Any]:
        """The whole state now, consistent with the delta numbered its `seq` (any thread)."""
        with self._lock:
            return self._state_now()

    def _state_now(self) -> dict[str, Any]:
        return {
            "v": VERSION,
            "member": self.member,
            "instance": self.instance,
            "seq": self._seq,
            "sections": dict(self._values),
            "events": list(self._events),
        }

    def flush(self, timeout: float = FLUSH_TIMEOUT) -> bool:
        """Wait until what the hub holds now was shared (a pass of the share's thread that
        began after this call ended); whether it was within `timeout` seconds.

        A supervisor that stops shares its final state so before its network closes
        (`Observer.source_ended`). Runs on the calling thread; not on the share's own.
        """
        with self._passes:
            begun = self._started
            self._wake.set()
            return self._passes.wait_for(
                lambda: self._done > begun or self._closing.is_set(), timeout
            )

    def close(self, timeout: float = 5.0) -> None:
        """Stop sharing: the token goes first (pages show this host stale), then the rest."""
        if self._closing.is_set():
            return
        self._closing.set()
        self._wake.set()
        with self._passes:
            self._passes.notify_all()  # (a flush waits no more)
        self._unlisten()
        for declared in (self._token, self._state, self._fault, self._publisher):
            with contextlib.suppress(Exception):
                declared.undeclare()  # type: ignore[no-untyped-call]
        self._thread.join(timeout)
        with contextlib.suppress(Exception):
            while self._queries:
                self._queries.popleft().drop()  # type: ignore[no-untyped-call]

    # -- the thread -----------------------------------------------------------------------

    def _run(self) -> None:
        seen: dict[str, int] = {}
        last_seq = 0
        links_at = 0.0
        while not self._closing.is_set():
            self._wake.wait(LINKS_EVERY)
            self._wake.clear()
            if self._closing.wait(COALESCE):
                return
            with self._passes:
                self._started += 1
            try:
                if time.monotonic() - links_at >= LINKS_EVERY:
                    links_at = time.monotonic()
                    self.hub.put("links", self._links())
                last_seq = self._send(seen, last_seq)
                self._answer_state()
            except Exception:
                if self._closing.is_set():
                    return
                logger.exception("observer of %s: sharing its state failed", self.member)
            finally:
                with self._passes:
                    self._done += 1
                    self._passes.notify_all()

    def _links(self) -> list[dict[str, Any]]:
        return [
            {"member": m.member, "up": m.up, "since": m.since, "where": m.where, "why": m.why}
            for m in sorted(self._services.links())
            if m.member != self.member
        ]

    def _send(self, seen: dict[str, int], last_seq: int) -> int:
        """Publish what changed in the hub since the last delta; the last event's seq."""
        changes = self.hub.changes(seen, last_seq)
        if changes.events:
            last_seq = changes.events[-1]["seq"]
        elif changes.missed:
            last_seq = self.hub.last_seq
        items: list[list[Any]] = []
        with self._lock:
            for key, _, value in changes.sections:
                if not _shared(key):
                    continue
                old = self._values.get(key)
                if value is None:
                    self._values.pop(key, None)
                    items.append([key, "v", None])
                    continue
                if old is None:
                    items.append([key, "v", value])
                else:
                    patch = diff(old, value)
                    if patch is None:
                        continue
                    items.append([key, "p", patch])
                self._values[key] = value
            events = [
                {**e, "member": self.member}
                for e in changes.events
                if self._all_events or e.get("type") == "ObserverFault"
            ]
            if not (items or events or changes.missed):
                return last_seq
            self._events.extend(events)
            self._seq += 1
            message = {
                "v": VERSION,
                "member": self.member,
                "instance": self.instance,
                "seq": self._seq,
                "sections": items,
                "events": events,
                "missed": changes.missed,
            }
            data = _dumps(message)
            self._publisher.put(data)
            self.sent_bytes += len(data)
            self.sent_messages += 1
            for listener in self._listeners:
                listener(message)
        return last_seq

    # -- asked by other hosts ---------------------------------------------------------------

    def _on_state(self, query: zenoh.Query) -> None:  # (Zenoh's thread: queue it)
        self._queries.append(query)
        self._wake.set()

    def _answer_state(self) -> None:
        while self._queries:
            query = self._queries.popleft()
            try:
                with self._lock:
                    data = _dumps(self._state_now())
                query.reply(query.key_expr, data)
                self.sent_bytes += len(data)
            finally:
                query.drop()  # type: ignore[no-untyped-call]

    def _on_fault(self, query: zenoh.Query) -> None:  # (Zenoh's thread: hand it over)
        if not self._running_faults.acquire(blocking=False):
            self._answer(query, False, "too many fault commands at once: try again", 503)
            return
        thread = threading.Thread(
            target=self._run_fault, args=(query,), name="rr-observe-fault", daemon=True
        )
        thread.start()

    def _run_fault(self, query: zenoh.Query) -> None:
        try:
            data = query.payload.to_bytes() if query.payload is not None else b""
            try:
                message = self._command(data)
            except FaultRefused as exc:
                self._answer(query, False, str(exc), exc.status)
            else:
                self._answer(query, True, message, 200)
        except Exception:
            logger.exception("observer of %s: a fault command failed", self.member)
            self._answer(query, False, "the command failed on this host (see its log)", 500)
        finally:
            self._running_faults.release()

    def _command(self, data: bytes) -> str:
        """Check and run one fault command; what was done (`FaultRefused`: why not)."""
        if len(data) > MAX_COMMAND:
            raise FaultRefused("the command is too large", 413)
        try:
            command = json.loads(data)
        except ValueError:
            raise FaultRefused("the command is not JSON", 400) from None
        if not isinstance(command, dict):
            raise FaultRefused("the command must be a JSON object", 400)
        kind, by = command.get("kind"), command.get("by")
        if not isinstance(by, str) or not NAME.fullmatch(by):
            raise FaultRefused("the command names no member it comes from (by)", 400)
        if kind not in KINDS:
            raise FaultRefused(f"no fault {kind!r} ({', '.join(KINDS)})", 404)
        if self._faults is None:
            raise FaultRefused(
                f"{self.member} does not allow faults: its observer was opened without "
                "allow_faults=True",
                403,
            )
        done = inject(self._faults, kind, command)
        text = f"{done} (from {by}'s page)"
        self.hub.add_event({"type": "ObserverFault", "kind": kind, "text": text, "at": time.time()})
        return done

    def _answer(self, query: zenoh.Query, ok: bool, message: str, status: int) -> None:
        try:
            with contextlib.suppress(Exception):
                query.reply(
                    query.key_expr, _dumps({"ok": ok, "message": message, "status": status})
                )
        finally:
            with contextlib.suppress(Exception):
                query.drop()  # type: ignore[no-untyped-call]


# -- what a host receives is checked ----------------------------------------------------------


def _text(value: Any, *, none: bool = False) -> bool:
    return isinstance(value, str) or (none and value is None)


def _number(value: Any, *, none: bool = False) -> bool:
    if value is None:
        return none
    return isinstance(value, int | float) and not isinstance(value, bool)


def valid_tree(node: Any, depth: int = 0) -> bool:
    """Whether `node` is a tree section as a `LiveSource` makes it (names, states, numbers)."""
    if not isinstance(node, dict) or depth > 16:
        return False
    if not (_text(node.get("name")) and _text(node.get("kind")) and _text(node.get("state"))):
        return False
    for key in ("pid", "restarts", "restart_due", "server_time", "max_restarts", "period"):
        if key in node and not _number(node[key], none=True):
            return False
    for key in ("last_exit", "gave_up", "isolation", "restart", "strategy"):
        if key in node and not _text(node[key], none=True):
            return False
    children = node.get("children", [])
    if not isinstance(children, list):
        return False
    return all(valid_tree(child, depth + 1) for child in children)


def _rows(value: Any, fields: Mapping[str, Callable[[Any], bool]]) -> bool:
    return isinstance(value, list) and all(
        isinstance(row, dict) and all(check(row.get(f)) for f, check in fields.items())
        for row in value
    )


_CONSUMER = {"query_id": _text, "origin": _text}
_RESOURCE: dict[str, Callable[[Any], bool]] = {
    "id": _text,
    "server": _text,
    "state": _text,
    "in_doubt": lambda v: isinstance(v, bool),
    "request": _text,
    "response": _text,
    "label": lambda v: _text(v, none=True),
    "consumers": lambda v: _rows(v, _CONSUMER),
}
_CLIENT: dict[str, Callable[[Any], bool]] = {
    "query_id": _text,
    "serving_rr": _text,
    "server": _text,
    "request": _text,
    "parent": lambda v: _text(v, none=True),
    "loaded": lambda v: isinstance(v, bool),
}


def valid_catalog(section: Any) -> bool:
    """Whether `section` is a catalog section as a `LiveSource` makes it."""
    if not isinstance(section, dict):
        return False
    if not (
        _text(section.get("registrar"))
        and _text(section.get("kind"))
        and _text(section.get("state"))
        and isinstance(section.get("available"), bool)
        and _text(section.get("error"), none=True)
    ):
        return False
    catalog = section.get("catalog")
    if catalog is None:
        return True
    return (
        isinstance(catalog, dict)
        and catalog.get("registrar") == section["registrar"]
        and isinstance(catalog.get("servers"), list)
        and all(_text(s) for s in catalog["servers"])
        and _rows(catalog.get("resources"), _RESOURCE)
        and _rows(catalog.get("clients"), _CLIENT)
        and _rows(catalog.get("in_doubt", []), {"id": _text, "request": _text})
    )


_LINK = {
    "member": _text,
    "up": lambda v: isinstance(v, bool),
    "since": _number,
    "where": _text,
    "why": _text,
}


def _valid_section(key: str, value: Any) -> bool:
    if value is None:
        return True
    if key == "tree":
        return valid_tree(value)
    if key == "links":
        return _rows(value, _LINK)
    if key == "ended":
        return isinstance(value, dict) and _number(value.get("at"))
    if key == "host":
        return (
            isinstance(value, dict)
            and _text(value.get("member"))
            and _text(value.get("title"))
            and isinstance(value.get("allow_faults"), bool)
            and _number(value.get("pid"), none=True)
        )
    return valid_catalog(value)


def _valid_event(event: Any) -> bool:
    return (
        isinstance(event, dict)
        and _text(event.get("type"))
        and _number(event.get("at"))
        and _text(event.get("text"), none=True)
        and isinstance(event.get("seq"), int)
    )


# -- a page's view of every host ------------------------------------------------------------------


@dataclasses.dataclass
class _Mirror:
    """What a page's host knows of one host's state."""

    member: str
    instance: str | None = None
    seq: int = 0
    last_event: int = 0
    sections: dict[str, Any] = dataclasses.field(default_factory=dict)
    published: set[str] = dataclasses.field(default_factory=set)
    here: bool = False  # its token is there
    synced: bool = False  # its state arrived since it came (back)
    behind: bool = False  # a delta was missed: its state is asked again (shown meanwhile)
    newest: tuple[str, int] = ("", 0)  # the newest delta seen: (instance, seq)
    since: float = dataclasses.field(default_factory=time.time)
    why: str = ""
    asked: float = -ASK_EVERY  # monotonic


class SystemView:
    """Keeps a page's hub up to date with every host's shared state.

    Sections of the page's hub: `hosts`, `links`, `graph` (across every host), and per
    host `host/<member>/tree`, `host/<member>/catalog/<registrar>`,
    `host/<member>/ended`; every host's events, each with its `member`: from the
    system's event stream (`subscribe`, in hybrid logical clock order) when there is
    one, else as each host shares them.

    Args:
        hub: the page's hub.
        services: the router's session and what goes with it.
        member: this host's member name (`None`: it shares nothing, only shows).
        share: this host's share (its own state comes from it directly, not over Zenoh).
        subscribe: the system's event stream (`ZenohNetwork.subscribe_events`), or
            `None`.
    """

    def __init__(
        self,
        hub: Hub,
        services: Services,
        member: str | None,
        share: Share | None,
        subscribe: Callable[..., Subscription[events_module.Event]] | None = None,
    ) -> None:
        self.hub = hub
        self.member = member
        self._services = services
        self._keys = services.keys
        self._share = share
        self._mirrors: dict[str, _Mirror] = {}
        self._executor = SerialExecutor("rr-observe-system", every=(LINKS_EVERY, self._tick))
        session = services.session
        if share is not None:
            own = self._mirror(share.member)
            own.here = True
            share.listen(self._on_own)
            self._executor.submit(functools.partial(self._own_state, share.state()))
        self._deltas = session.declare_subscriber(self._keys.observers("delta"), self._on_delta)
        self._tokens = session.liveliness().declare_subscriber(
            self._keys.observers("here"), self._on_token, history=True
        )
        self._links_listener = session.info.declare_link_events_listener(
            self._on_link, history=False
        )
        self._events_of_system = (
            None if subscribe is None else subscribe(self._on_event, window=EVENTS_WINDOW)
        )

    def _on_link(self, _event: Any) -> None:  # (Zenoh's thread: a link came or went)
        self._executor.submit(functools.partial(self._refresh, graph=False))

    def _on_event(self, event: events_module.Event) -> None:  # (its subscriber thread)
        data = event_dict(event)
        data["member"] = data.get("host") or "?"
        self.hub.add_event(data)

    def close(self, timeout: float = 5.0) -> None:
        """Stop following the hosts (within `timeout` seconds)."""
        for declared in (self._deltas, self._tokens, self._links_listener):
            with contextlib.suppress(Exception):
                declared.undeclare()  # type: ignore[no-untyped-call]
        if self._events_of_system is not None:
            self._events_of_system.close(timeout=timeout)
        self._executor.close(timeout=0)
        self._executor.join(timeout)

    def _mirror(self, member: str) -> _Mirror:
        mirror = self._mirrors.get(member)
        if mirror is None:
            mirror = self._mirrors[member] = _Mirror(member)
        return mirror

    def _on_own(self, message: dict[str, Any]) -> None:  # (the share's thread: queue it)
        self._executor.submit(functools.partial(self._own, message))

    def _local(self, member: str) -> bool:
        return self._share is not None and member == self._share.member

    # -- Zenoh's threads: queue ------------------------------------------------------------

    def _on_delta(self, sample: zenoh.Sample) -> None:
        at = self._keys.parse_observer(str(sample.key_expr))
        if at is None or self._local(at.member):
            return
        data = sample.payload.to_bytes()
        self._executor.submit(functools.partial(self._delta, at.member, data))

    def _on_token(self, sample: zenoh.Sample) -> None:
        import zenoh  # noqa: PLC0415 - (the zenoh extra; imported already by the session)

        at = self._keys.parse_observer(str(sample.key_expr))
        if at is None or self._local(at.member):
            return
        here = sample.kind == zenoh.SampleKind.PUT
        self._executor.submit(functools.partial(self._token, at.member, here))

    def _on_reply(self, member: str, reply: Any) -> None:
        ok = getattr(reply, "ok", None)
        if ok is not None:
            data = ok.payload.to_bytes()
            self._executor.submit(functools.partial(self._state, member, data))

    # -- the executor's thread -------------------------------------------------------------

    def _token(self, member: str, here: bool) -> None:
        mirror = self._mirror(member)
        mirror.here, mirror.synced = here, False  # (back: what it missed comes with its state)
        mirror.since = time.time()
        mirror.why = "" if here else self._why(member)
        if here:
            self._ask(mirror, force=True)
        self._refresh(graph=True)

    def _ask(self, mirror: _Mirror, *, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - mirror.asked < ASK_EVERY:
            return
        mirror.asked = now
        key = self._keys.observer(ObserverKey(mirror.member, "state"))
        try:
            self._services.session.get(
                key, functools.partial(self._on_reply, mirror.member), timeout=STATE_TIMEOUT
            )
        except Exception:
            logger.debug("observer: asking %s for its state failed", mirror.member, exc_info=True)

    def _decode(self, member: str, data: bytes) -> dict[str, Any] | None:
        if len(data) > MAX_MESSAGE:
            logger.warning("observer: %s sent %d bytes, more than allowed", member, len(data))
            return None
        try:
            message = json.loads(data)
        except ValueError:
            return None
        if (
            not isinstance(message, dict)
            or message.get("v") != VERSION
            or message.get("member") != member
            or not _text(message.get("instance"))
            or not isinstance(message.get("seq"), int)
        ):
            return None
        return message

    def _state(self, member: str, data: bytes) -> None:
        message = self._decode(member, data)
        if message is None or not isinstance(message.get("sections"), dict):
            return
        self._apply_state(self._mirror(member), message)

    def _own_state(self, message: dict[str, Any]) -> None:
        self._apply_state(self._mirror(message["member"]), message)

    def _apply_state(self, mirror: _Mirror, message: dict[str, Any]) -> None:
        if (
            mirror.synced
            and mirror.instance == message["instance"]
            and message["seq"] <= mirror.seq
        ):
            return  # (older than what it has)
        if mirror.instance != message["instance"]:
            mirror.last_event = 0
        sections = {
            key: value
            for key, value in message["sections"].items()
            if isinstance(key, str) and _shared(key) and _valid_section(key, value)
        }
        mirror.instance, mirror.seq, mirror.sections = message["instance"], message["seq"], sections
        mirror.synced = True
        newest_instance, newest_seq = mirror.newest  # (a delta newer than this state came)
        mirror.behind = newest_instance == mirror.instance and newest_seq > mirror.seq
        if not self._local(mirror.member) and not mirror.here:
            mirror.synced = False  # (a late answer from a host that went meanwhile)
        self._events(mirror, message.get("events"))
        self._publish(mirror, set(sections) | mirror.published)
        self._refresh(graph=True)

    def _delta(self, member: str, data: bytes) -> None:
        message = self._decode(member, data)
        if message is None:
            return
        self._apply_delta(self._mirror(member), message)

    def _own(self, message: dict[str, Any]) -> None:
        self._apply_delta(self._mirror(message["member"]), message)

    def _apply_delta(self, mirror: _Mirror, message: dict[str, Any]) -> None:
        if mirror.newest[0] != message["instance"] or mirror.newest[1] < message["seq"]:
            mirror.newest = (message["instance"], message["seq"])
        same = mirror.instance == message["instance"]
        if same and message["seq"] <= mirror.seq:
            return  # (already in the state it has)
        if not (mirror.synced and same and message["seq"] == mirror.seq + 1):
            if self._local(mirror.member):
                self._own_state(self._share.state() if self._share else message)
            elif mirror.here:
                mirror.behind = True  # (asked now, or at the next tick)
                self._ask(mirror)
            return
        changed = set()
        try:
            items = message.get("sections")
            if not isinstance(items, list):
                raise TypeError("sections")  # noqa: TRY301 - one way out for any bad shape
            updated = dict(mirror.sections)
            for key, how, value in items:
                if not isinstance(key, str) or not _shared(key):
                    continue
                new = apply(updated.get(key), value) if how == "p" else value
                if not _valid_section(key, new):
                    raise TypeError(key)  # noqa: TRY301
                if new is None:
                    updated.pop(key, None)
                else:
                    updated[key] = new
                changed.add(key)
        except (TypeError, ValueError, KeyError, AttributeError, IndexError):
            logger.debug("observer: a malformed delta from %s", mirror.member, exc_info=True)
            mirror.synced = False
            self._ask(mirror, force=True)
            return
        mirror.sections, mirror.seq = updated, message["seq"]
        self._events(mirror, message.get("events"))
        self._publish(mirror, changed)
        self._refresh(graph=any(k.startswith("catalog/") or k == "host" for k in changed))

    def _events(self, mirror: _Mirror, events: Any) -> None:
        if not isinstance(events, list):
            return
        for event in events[-BATCH:]:
            if not _valid_event(event) or event["seq"] <= mirror.last_event:
                continue
            if self._events_of_system is not None and event["type"] != "ObserverFault":
                continue  # (the system's event stream brings it)
            mirror.last_event = event["seq"]
            self.hub.add_event({**event, "member": mirror.member, "host_seq": event["seq"]})

    def _publish(self, mirror: _Mirror, keys: set[str]) -> None:
        """Put sections `keys` of `mirror` into the page's hub (under `host/<member>/`)."""
        for key in sorted(keys):
            if key in ("host", "links"):
                continue  # (in "hosts" and "links")
            value = mirror.sections.get(key)
            self.hub.put(f"host/{mirror.member}/{key}", value)
            if value is None:
                mirror.published.discard(key)
            else:
                mirror.published.add(key)

    def _tick(self) -> None:
        try:
            for mirror in list(self._mirrors.values()):
                lagging = not mirror.synced or mirror.behind
                if mirror.here and lagging and not self._local(mirror.member):
                    self._ask(mirror)
            self._refresh(graph=False)
        except Exception:
            if not self._executor.closed:
                logger.exception("observer: following the hosts failed")

    # -- the page's sections across hosts ----------------------------------------------------

    def _report(self, reporter: str, about: str) -> dict[str, Any] | None:
        """What `reporter` last said of its link to `about` (its own links are fresh)."""
        if reporter == self.member:  # (this host's own: from its link watch, now)
            links = [self._link(m) for m in self._services.links()]
        else:
            mirror = self._mirrors.get(reporter)
            if mirror is None or not (mirror.here and mirror.synced):
                return None
            links = mirror.sections.get("links") or []
        return next((link for link in links if link["member"] == about), None)

    @staticmethod
    def _link(m: Any) -> dict[str, Any]:
        return {"member": m.member, "up": m.up, "since": m.since, "where": m.where, "why": m.why}

    def _why(self, member: str) -> str:
        mirror = self._mirrors.get(member)
        if mirror is not None and mirror.sections.get("ended"):
            return "its supervisor stopped"  # (it shared its final state first)
        own = self._report(self.member, member) if self.member else None
        if own is not None and not own["up"]:
            return str(own["why"])
        lease = self._services.lease
        return (
            f"its observer's token went: it stopped sharing, or nothing was heard from it "
            f"within the lease ({lease:g} s)"
        )

    def _hosts(self) -> dict[str, Any]:
        hosts = []
        for member in self._members():
            mirror = self._mirrors[member]
            info = mirror.sections.get("host") or {}
            if mirror.here and mirror.synced:
                state = "live"
            elif mirror.here:
                state = "joining"
            else:
                state = "stale"
            hosts.append(
                {
                    "member": member,
                    "state": state,
                    "since": mirror.since,
                    "why": mirror.why,
                    "allow_faults": bool(info.get("allow_faults", False)) and state == "live",
                    "title": info.get("title", ""),
                    "pid": info.get("pid"),
                    "here": member == self.member,
                }
            )
        return {"self": self.member, "lease": self._services.lease, "hosts": hosts}

    def _members(self) -> list[str]:
        members = sorted(self._mirrors)
        if self.member in self._mirrors:  # this host first
            members.remove(self.member)
            members.insert(0, self.member)
        return members

    def _links(self) -> list[dict[str, Any]]:
        members = set(self._mirrors)
        if self.member is not None:
            members.add(self.member)
        pairs = []
        for a in sorted(members):
            for b in sorted(members):
                if a >= b:
                    continue
                pairs.append(self._pair(a, b))
        return pairs

    def _pair(self, a: str, b: str) -> dict[str, Any]:
        reports = [(r, self._report(x, y)) for r, (x, y) in ((a, (a, b)), (b, (b, a)))]
        down = [(who, r) for who, r in reports if r is not None and not r["up"]]
        up = [(who, r) for who, r in reports if r is not None and r["up"]]
        pair: dict[str, Any] = {"id": f"{a}|{b}", "a": a, "b": b}
        if down:
            who, report = min(down, key=lambda d: d[1]["since"])
            return {**pair, "up": False, "since": report["since"], "why": f"{who}: {report['why']}"}
        if up:
            return {**pair, "up": True, "since": max(r["since"] for _, r in up), "why": ""}
        gone = [
            self._mirrors[m] for m in (a, b) if m in self._mirrors and not self._mirrors[m].here
        ]
        if gone:
            return {**pair, "up": False, "since": gone[0].since, "why": gone[0].why}
        return {**pair, "up": True, "since": None, "why": ""}

    def _refresh(self, *, graph: bool) -> None:
        for mirror in self._mirrors.values():  # a cut found by the link watch names its cause
            if not mirror.here and not self._local(mirror.member):
                mirror.why = self._why(mirror.member)
        self.hub.put("hosts", self._hosts())
        self.hub.put("links", self._links())
        if graph:
            self.hub.put("graph", self._graph())

    def _graph(self) -> dict[str, Any]:
        catalogs: dict[str, dict[str, Any] | None] = {}
        states: dict[str, str] = {}
        hosts: dict[str, str] = {}
        for mirror in self._mirrors.values():
            stale = not (mirror.here and mirror.synced) and not self._local(mirror.member)
            for key, section in mirror.sections.items():
                if not key.startswith("catalog/"):
                    continue
                name = section["registrar"]
                catalogs[name] = section["catalog"]
                states[name] = "stale" if stale else section["state"]
                hosts[name] = mirror.member
        return dependency_graph(catalogs, states, hosts=hosts)

    # -- a fault on another host ---------------------------------------------------------------

    def fault(self, member: str, kind: str, data: dict[str, Any]) -> str:
        """Ask host `member` to inject a fault into one of its managers; what it did.

        Runs on the calling thread (a worker thread of the server: it waits up to
        `FAULT_TIMEOUT` seconds for the answer).

        Raises:
            FaultRefused: that host refused (its reason), did not answer, or is not known.
        """
        if member not in self._mirrors or self._local(member):
            raise FaultRefused(f"no host {member!r} shares its tree with this page", 404)
        if self.member is None:
            raise FaultRefused("this page's host has no member name to send a command as", 403)
        command = {k: v for k, v in data.items() if k != "host"}
        command.update(kind=kind, by=self.member)
        key = self._keys.observer(ObserverKey(member, "fault"))
        replies = self._services.session.get(key, payload=_dumps(command), timeout=FAULT_TIMEOUT)
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                answer = json.loads(reply.ok.payload.to_bytes())
            except ValueError:
                break
            if not isinstance(answer, dict) or not _text(answer.get("message")):
                break
            if answer.get("ok") is True:
                return f"{member}: {answer['message']!s}"
            status = answer.get("status")
            code = status if isinstance(status, int) and 400 <= status < 600 else 409
            raise FaultRefused(f"{member} refused: {answer['message']}", code)
        raise FaultRefused(
            f"{member} did not answer within {FAULT_TIMEOUT:g} s (is the link to it up?)", 504
        )
