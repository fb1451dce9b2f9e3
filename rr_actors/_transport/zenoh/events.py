"""The system's event stream over Zenoh: every member process's events, as JSON, to members.

```
 each member process (router or manager process)     a process that subscribes (any member)
 events.everything() ─► Forwarder (while matched) ─► put rr/<s>/ev/<zid>  (JSON lines)
                                                                │
                          ZenohNetwork.subscribe_events ◄── subscriber rr/<s>/ev/*
                          (Zenoh's thread: queue the bytes) ─► merge thread: JSON lines
                          ─► events.from_dict ─► held `window` s, released in `hlc` order
                          ─► the subscription's own thread ─► callback(event)
```

- Each process sends the events published in it (`events.everything()`: once each, where
  it happened; a manager process's own, not those it forwards to its supervisor), in
  batches, only while some subscriber anywhere in the system matches its key (Zenoh's
  matching status): nobody listening costs nothing but the matching listener.
- What crosses is plain data: one `json.dumps(events.to_dict(event))` line per event
  (the `events.jsonl` form). The subscriber parses JSON and checks every field
  (`events.from_dict`); it never unpickles. A line that is not an event is dropped, with
  a WARNING (at most one a minute) naming the sender's key.
- Only members see the stream and only members put on it: the keys are under
  `rr/<system>/`, which the access control of a `ZenohNetwork` with `tls` admits for
  members' certificates and this host's own processes only (`config`).
- Merged by the hybrid logical clock: a process's own events arrive in order (one
  publisher, reliable puts); those of different processes are held `window` seconds
  after they arrived and released in `hlc` order, so an effect on one host never comes
  before its cause on another unless its cause arrived more than `window` later.
"""

from __future__ import annotations

import collections
import contextlib
import heapq
import itertools
import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from rr_actors import events
from rr_actors._core.bus import DEFAULT_MAXSIZE, Forwarder, Publisher, Subscription
from rr_actors._core.throttle import LogThrottle
from rr_actors._transport.zenoh.wire import Keys
from rr_actors.errors import ConfigError

__all__ = [
    "BATCHES_HELD",
    "CLOSE_GRACE",
    "DEFAULT_MAXSIZE",
    "MAX_BATCH_BYTES",
    "EventExport",
    "EventFeed",
    "check_window",
    "decode",
    "encode",
]

logger = logging.getLogger("rr_actors")

MAX_BATCH_BYTES = 16 * 1024 * 1024
"""A batch over this many bytes is dropped unread by a subscriber."""

CLOSE_GRACE = 0.5
"""Seconds a closing member gives its events' forwarder to send what it holds (its last
events, as a manager process stops); what is left then is dropped, counted and warned
of. Bounded: over a cut link a send may block."""

BATCHES_HELD = 1_024
"""Batches a subscriber holds before it decodes them; beyond, new ones are dropped (and
counted in an `EventsDropped`)."""


def encode(batch: list[events.Event]) -> bytes:
    """A batch of events as bytes: one JSON line per event (`events.to_dict`)."""
    return "\n".join(json.dumps(events.to_dict(event)) for event in batch).encode()


def decode(data: bytes) -> tuple[list[events.Event], int]:
    """The events of a batch `encode` made, and how many lines were not events.

    Only JSON is parsed (`json.loads`, `events.from_dict`): nothing is unpickled.
    """
    found: list[events.Event] = []
    bad = 0
    for line in data.split(b"\n"):
        if not line.strip():
            continue
        try:
            found.append(events.from_dict(json.loads(line)))
        except (ValueError, ConfigError, TypeError, RecursionError):
            bad += 1
    return found, bad


class EventExport:
    """One member process's side: its events to `rr/<system>/ev/<zid>` while anyone listens.

    Args:
        session: the process's open Zenoh session.
        keys: the system's key expressions.
        zid: this process's Zenoh id.
    """

    def __init__(self, session: zenoh.Session, keys: Keys, zid: str) -> None:
        self._lock = threading.Lock()
        self._closed = False
        self._forwarder: Forwarder[events.Event] | None = None
        self._sending = threading.Condition(self._lock)
        self._publisher = session.declare_publisher(
            keys.events(zid),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
            priority=zenoh.Priority.DATA_LOW,  # (registrars' messages go first)
        )
        self._listener = self._publisher.declare_matching_listener(self._matched)
        self._matched(self._publisher.matching_status)

    def _matched(self, status: Any) -> None:
        """A subscriber came or the last one went (Zenoh's thread): switch the sink."""
        with self._lock:
            if self._closed:
                return
            if status.matching and self._forwarder is None:
                self._forwarder = Forwarder(
                    self._send, notice=events.EventsDropped, name="system-events"
                )
                events.everything().add_sink(self._forwarder)
                self._sending.notify_all()
            elif not status.matching and self._forwarder is not None:
                events.everything().remove_sink(self._forwarder)
                forwarder, self._forwarder = self._forwarder, None
                threading.Thread(target=forwarder.close, name="rr-events-off", daemon=True).start()

    def wait_sending(self, timeout: float) -> bool:
        """Whether this process sends its events (a subscriber matched) within `timeout` s."""
        with self._lock:
            return self._sending.wait_for(lambda: self._forwarder is not None, timeout)

    def _send(self, batch: list[events.Event]) -> None:
        self._publisher.put(encode(batch))

    def close(self) -> None:
        """Stop sending: what is buffered is sent within `CLOSE_GRACE` seconds, the rest
        is lost (a WARNING says how much)."""
        with self._lock:
            self._closed = True
            forwarder, self._forwarder = self._forwarder, None
        if forwarder is not None:
            events.everything().remove_sink(forwarder)
            forwarder.close(timeout=CLOSE_GRACE)
        with contextlib.suppress(Exception):
            self._listener.undeclare()  # type: ignore[no-untyped-call]
        with contextlib.suppress(Exception):
            self._publisher.undeclare()  # type: ignore[no-untyped-call]


class EventFeed:
    """One system-wide subscription's side: the Zenoh subscriber and the merge thread.

    Args:
        session: the process's open Zenoh session.
        keys: the system's key expressions.
        window: seconds an event is held for those of other processes to overtake it
            (see `ZenohNetwork.subscribe_events`).
    """

    def __init__(self, session: zenoh.Session, keys: Keys, window: float) -> None:
        self._session = session
        self._keys = keys
        self._window = window
        self.publisher: Publisher[events.Event] = Publisher(notice=events.EventsDropped)
        self._raw: queue.SimpleQueue[tuple[str, bytes] | None] = queue.SimpleQueue()
        self._held = 0  # batches in `_raw` (Zenoh's threads add, the merge thread takes)
        self._lost = 0  # batches dropped since the last notice
        self._lock = threading.Lock()
        self._bad = LogThrottle(logger, 60.0)
        self._subscriber: Any = None
        self._thread: threading.Thread | None = None
        self.publisher.watch_listeners(self._switch)

    def subscribe(
        self, callback: Callable[[events.Event], object], maxsize: int
    ) -> Subscription[events.Event]:
        """The subscription of `callback` (its close ends the feed)."""
        return self.publisher.subscribe(callback, maxsize=maxsize, name="system-events")

    def _switch(self, listened: bool) -> None:
        if listened and self._subscriber is None:
            self._thread = threading.Thread(target=self._merge, name="rr-events-merge", daemon=True)
            self._thread.start()
            self._subscriber = self._session.declare_subscriber(
                self._keys.all_events(), self._on_sample
            )
        elif not listened and self._subscriber is not None:
            with contextlib.suppress(Exception):
                self._subscriber.undeclare()
            self._subscriber = None
            self._raw.put(None)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """A batch came (Zenoh's thread): queue it, never decode here."""
        data = sample.payload.to_bytes()
        with self._lock:
            if len(data) > MAX_BATCH_BYTES or self._held >= BATCHES_HELD:
                self._lost += data.count(b"\n") + 1  # (its events: one a line)
                return
            self._held += 1
        self._raw.put((str(sample.key_expr), data))

    def _merge(self) -> None:
        """Decode batches; release events in `hlc` order, each at most `window` s late."""
        window = self._window
        held: list[tuple[int, int, events.Event]] = []  # a heap by stamp, then arrival
        due: collections.deque[tuple[float, int]] = collections.deque()  # (deadline, stamp)
        arrivals = itertools.count()
        deliver = self.publisher.deliver
        while True:
            timeout = None if not due else max(0.0, due[0][0] - time.monotonic())
            try:
                item = self._raw.get(timeout=timeout)
            except queue.Empty:
                item = ("", b"")
            if item is None:
                return
            key, data = item
            if key:
                with self._lock:
                    self._held -= 1
                    lost, self._lost = self._lost, 0
                if lost:
                    deliver(events.EventsDropped(lost, cause="full"))
                found, bad = decode(data)
                if bad:
                    self._bad.warning(
                        "dropped %d lines of the event stream from %s: not events of this "
                        "rr_actors version (plain JSON is all that is read)",
                        bad,
                        key,
                    )
                now = time.monotonic()
                for event in found:
                    if window <= 0:
                        deliver(event)
                        continue
                    heapq.heappush(held, (event.hlc, next(arrivals), event))
                    due.append((now + window, event.hlc))
            now = time.monotonic()
            top = -1
            while due and due[0][0] <= now:
                top = max(top, due.popleft()[1])
            while held and held[0][0] <= top:
                deliver(heapq.heappop(held)[2])


def check_window(window: object) -> float:
    """`window` as seconds, or a `ConfigError` naming it."""
    if isinstance(window, bool) or not isinstance(window, int | float) or not 0 <= window <= 60:
        raise ConfigError(f"window must be seconds from 0 to 60, not {window!r}")
    return float(window)
