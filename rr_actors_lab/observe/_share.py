"""This host's share: its observer state, published to the system's other hosts.

```
 host B (sharing)                                          other hosts (SystemView)
 LiveSource ─► local Hub ─► listen: wake ─► Share's thread (a pass every change, COALESCE
                                             s after it, or every LINKS_EVERY s):
                  ├─ hub.put("links", this host's links: up, or cut since when, why)
                  ├─ _send: what changed ── delta (JSON put, numbered seq) ──────────► all
                  └─ _answer_state: the queued asks ── state (queryable, JSON) ◄─── one ──┘
                 here (liveliness token): this host is live ──────────────────────► all
                 FaultDesk (_faults_across.py): the fault queryable
```

Each message is made under one lock, so a state is consistent with the delta numbered its
`seq`. One thread (`rr-observe-share-<member>`); Zenoh's callbacks only queue.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import threading
import time
import uuid
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rr_actors._transport.zenoh.callbacks import tracked
from rr_actors._transport.zenoh.wire import ObserverKey
from rr_actors_lab.observe._crossing import VERSION, dumps, link_row, shared
from rr_actors_lab.observe._delta import diff
from rr_actors_lab.observe._faults import Faults
from rr_actors_lab.observe._faults_across import FaultDesk
from rr_actors_lab.observe._hub import RING, Hub

if TYPE_CHECKING:
    import zenoh

    from rr_actors._transport.zenoh.net import Services

__all__ = ["COALESCE", "FLUSH_TIMEOUT", "LINKS_EVERY", "Share"]

logger = logging.getLogger("rr_actors")

COALESCE = 0.01
"""Seconds the share waits after a change, so that changes close together go as one."""

LINKS_EVERY = 0.5
"""Seconds between two looks at this host's links (and at hosts that owe a state)."""

FLUSH_TIMEOUT = 2.0
"""Seconds a stopping supervisor's observer waits for its final state to be shared."""


class Share:
    """Publishes this host's observer state (its hub's sections and events) to the system.

    Args:
        hub: the host's own hub (what its `LiveSource` keeps up to date).
        services: the router's session and what goes with it.
        member: this host's member name.
        host: what the page says of this host (title, pid).
        faults: the teaching mode's faults (`None`: every fault command is refused).
        all_events: share every event of the hub; `False`: only the observer's own, when
            pages get every host's events from the system's event stream.
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
        self._passes = threading.Condition()
        self._started = self._done = 0  # the thread's passes: begun, and ended
        self.sent_bytes = 0
        self.sent_messages = 0
        hub.put("host", {**host, "member": member, "allow_faults": faults is not None})
        self._unlisten = hub.listen(self._wake.set)
        session = services.session
        self._publisher = session.declare_publisher(self._key("delta"))
        self._state = session.declare_queryable(
            self._key("state"), tracked(session, self._on_state)
        )
        self._desk = FaultDesk(hub, services, member, faults)
        self._thread = threading.Thread(
            target=self._run, name=f"rr-observe-share-{member}", daemon=True
        )
        self._thread.start()
        self._token = session.liveliness().declare_token(self._key("here"))
        # (a network that left already closes it inside `on_leave`: its `close` ends by
        # calling `_forget`, set before)
        self._forget: Callable[[], None] = lambda: None
        self._forget = services.on_leave(self.close)  # (its thread puts: ended before the
        # session closes, even if the observer stays open: `keep_serving`)

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
        """Wait until what the hub holds now was shared; whether within `timeout` seconds (calling
        thread, never the share's own; a stopping supervisor's final state)."""
        with self._passes:
            begun = self._started
            self._wake.set()
            return self._passes.wait_for(
                lambda: self._done > begun or self._closing.is_set(), timeout
            )

    def close(self, timeout: float = 5.0) -> None:
        """Stop sharing: the token goes first (pages show this host stale), then the rest;
        its threads (and fault commands running) end within `timeout` s each. Its network
        closes it too, before its session closes (`Services.on_leave`)."""
        if self._closing.is_set():
            return
        self._closing.set()
        self._wake.set()
        with self._passes:
            self._passes.notify_all()  # (a flush waits no more)
        self._unlisten()
        for declared in (self._token, self._state, self._desk, self._publisher):
            with contextlib.suppress(Exception):
                if isinstance(declared, FaultDesk):
                    declared.close(timeout)
                else:
                    declared.undeclare()  # type: ignore[no-untyped-call]
        self._thread.join(timeout)
        with contextlib.suppress(Exception):
            while self._queries:
                self._queries.popleft().drop()  # type: ignore[no-untyped-call]
        self._forget()

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
        return [link_row(m) for m in sorted(self._services.links()) if m.member != self.member]

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
                if not shared(key):
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
            data = dumps(message)
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
                    data = dumps(self._state_now())
                query.reply(query.key_expr, data)
                self.sent_bytes += len(data)
            finally:
                query.drop()  # type: ignore[no-untyped-call]
