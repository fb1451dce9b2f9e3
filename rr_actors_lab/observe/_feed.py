"""The system's event stream over Zenoh, and what the observer runs beside a Zenoh session.

`Across` runs beside every session of a `ZenohNetwork` and of the processes that attach
through it (`rr_actors._transport.zenoh.net.Beside`, attached when this module is
imported): the process's events to the system (`EventExport`), the system's to a
`subscribe_events` (`EventFeed`), and on a router the link watch (`_links`).

```
 each member process (router or manager process)     a process that subscribes (any member)
 events.everything() ─► Forwarder (while matched) ─► put rr/<s>/ev/<zid>  (JSON lines)
                                                                │
                          ZenohNetwork.subscribe_events ◄── subscriber rr/<s>/ev/*
                          (Zenoh's thread: queue the bytes) ─► merge thread: JSON lines
                          ─► events.from_dict ─► held `window` s, released in `hlc` order
                          ─► the subscription's own thread ─► callback(event)
```

What crosses (plain JSON, never pickles), to whom (members only), the bounds in bytes and
the merge by `hlc`: docs/reference/events.md. With `tls`, each batch is sealed by its host
(`seal`) and an event's `host` is its sealer, never what the event says; a batch no member
sealed is dropped.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import heapq
import itertools
import json
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any, NamedTuple

import zenoh

from rr_actors import events
from rr_actors._core.bus import DEFAULT_MAXSIZE, Forwarder, Publisher, Subscription
from rr_actors._core.throttle import LogThrottle, short
from rr_actors._transport.zenoh import callbacks
from rr_actors._transport.zenoh.callbacks import tracked
from rr_actors._transport.zenoh.net import MemberLink, Opened, attach_beside
from rr_actors._transport.zenoh.ops.config import PROBE_TIMEOUT
from rr_actors._transport.zenoh.presence import ASK_TIMEOUT
from rr_actors._transport.zenoh.wire import Keys
from rr_actors.errors import ConfigError
from rr_actors_lab.observe._links import LinkWatch, plain_unlinked

if TYPE_CHECKING:
    from rr_actors_lab.observe._seal import Seal

__all__ = [
    "BATCHES_HELD",
    "CLOSE_GRACE",
    "DEFAULT_MAXSIZE",
    "DROPPED_EVERY",
    "EVENT_BYTES",
    "HELD_BYTES",
    "MAX_BATCH_BYTES",
    "QUEUED_BYTES",
    "Across",
    "EventExport",
    "EventFeed",
    "decode",
    "encode",
    "weight",
]

logger = logging.getLogger("rr_actors")

MAX_BATCH_BYTES = 16 * 1024 * 1024
"""A batch over this many bytes is dropped unread by a subscriber."""

HELD_BYTES = (16 * 1024 * 1024, 64 * 1024 * 1024)
"""Bytes a subscriber holds of one sending process's events, and of all together, until they
go to the subscription's queue (an event weighs `weight`); a batch past either is dropped."""

QUEUED_BYTES = 32 * 1024 * 1024
"""Bytes of events (`weight`) a system-wide subscription queues for its callback, besides
its `maxsize` events; past either, new events are dropped (then one `EventsDropped`)."""

EVENT_BYTES = 384
"""What an event counts for besides its text: about what a decoded event costs in memory
beyond its strings' characters (the dataclass, its numbers, each string's header; 130 to
410 bytes, measured with `tracemalloc` for `InDoubt`, `ResourceLoaded` and `StatusSent`)."""

DROPPED_EVERY = 60.0
"""Seconds between two WARNINGs about batches a subscriber dropped (what comes between is
counted in the next one)."""

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
    """The events of a batch `encode` made (JSON only, nothing unpickled), and how many lines were
    not."""
    found: list[events.Event] = []
    bad = 0
    for line, _ in _lines(data):
        event = _event(line)
        if event is None:
            bad += 1
        else:
            found.append(event)
    return found, bad


def _lines(data: bytes) -> Iterator[tuple[bytes, int]]:
    """The lines of `data` that are not blank, each with where the next one starts (one at
    a time: a big batch is not copied whole)."""
    start, size = 0, len(data)
    while start < size:
        end = data.find(b"\n", start)
        end = size if end < 0 else end
        line = data[start:end]
        start = end + 1
        if line.strip():
            yield line, start


def _event(line: bytes) -> events.Event | None:
    """The event of one JSON line, or `None` if it is not one (nothing is unpickled; a
    number that is not finite makes it none: a page's `JSON.parse` refuses `NaN`)."""
    try:
        return events.from_dict(
            json.loads(line, parse_constant=_not_finite, parse_float=_finite_float)
        )
    except (ValueError, ConfigError, TypeError, RecursionError):
        return None


def _not_finite(name: str) -> float:
    raise ValueError(f"{name} is not a finite number")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):  # (1e999)
        raise ValueError(f"{text} is not a finite number")
    return value


_FIELDS: dict[type, tuple[str, ...]] = {}  # each kind's field names (`weight`)


def _text(value: object) -> int:
    """The characters of a field's value (and a row's cells), as `weight` counts them."""
    if isinstance(value, str):
        return len(value)
    total = 0
    if isinstance(value, tuple):  # (a catalog event's rows)
        for cell in value:
            total += _text(cell) + 8
    return total


def weight(event: events.Event) -> int:
    """The bytes `event` counts for while a subscriber holds it: `EVENT_BYTES` and its
    text."""
    kind = type(event)
    names = _FIELDS.get(kind)
    if names is None:
        names = _FIELDS[kind] = tuple(field.name for field in dataclasses.fields(event))
    total = EVENT_BYTES
    for name in names:
        total += _text(getattr(event, name))
    return total


class EventExport:
    """One member process's side: its events to `rr/<system>/ev/<zid>` while anyone listens.

    Args:
        session: the process's open Zenoh session.
        keys: the system's key expressions.
        zid: this process's Zenoh id.
        seal: seals each batch with this host's certificate (`None`: without TLS).
    """

    def __init__(
        self, session: zenoh.Session, keys: Keys, zid: str, seal: Seal | None = None
    ) -> None:
        self._seal = seal
        self._session = session
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
        self._listener = self._publisher.declare_matching_listener(tracked(session, self._matched))
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
                callbacks.worker(self._session, self._forwarder.executor)  # (it puts)
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
        data = encode(batch)
        if self._seal is None:
            self._publisher.put(data)
        else:
            self._publisher.put(data, attachment=self._seal.seal(data))

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


class _Batch(NamedTuple):
    """A batch as it came: its sender's key, its bytes, its seal (Zenoh's attachment)."""

    key: str
    data: bytes
    seal: bytes | None


class EventFeed:
    """One system-wide subscription's side: the Zenoh subscriber and the merge thread.

    What it holds is bounded in bytes, per sending process and in all (`HELD_BYTES`, then
    `QUEUED_BYTES` in the subscription's queue): a batch past a bound is dropped whole,
    counted in the next `EventsDropped` and warned of (once a minute). With a `seal`, an
    event's `host` is the member that sealed its batch.

    Args:
        session: the process's open Zenoh session.
        keys: the system's key expressions.
        window: seconds an event is held for those of other processes to overtake it
            (see `ZenohNetwork.subscribe_events`).
        seal: opens each batch's seal (`None`: without TLS, `host` is what the sender wrote).
    """

    def __init__(
        self, session: zenoh.Session, keys: Keys, window: float, seal: Seal | None = None
    ) -> None:
        self._session = session
        self._keys = keys
        self._window = window
        self._seal = seal
        self.publisher: Publisher[events.Event] = Publisher(notice=events.EventsDropped)
        self._raw: queue.SimpleQueue[_Batch | None] = queue.SimpleQueue()
        self._lock = threading.Lock()  # the counts below (Zenoh's threads and the merge's)
        self._batches = 0  # batches in `_raw`
        self._held: dict[str, int] = {}  # bytes held of each sender (its key), not 0
        self._held_all = 0  # ... of all senders
        self._lost = 0  # events in batches dropped for a bound since the last notice
        self._refused = 0  # ... in batches no member sealed
        self._bad = LogThrottle(logger, 60.0)
        self._dropping = LogThrottle(logger, DROPPED_EVERY)
        self._claiming = LogThrottle(logger, 60.0)
        self._subscriber: Any = None
        self._thread: threading.Thread | None = None
        self._switching = threading.Lock()  # (`_switch` and `leave`)
        self._left = False
        self.forget: Callable[[], None] = lambda: None  # (`leave` forgotten by the network)
        self.publisher.watch_listeners(self._switch)

    def subscribe(
        self, callback: Callable[[events.Event], object], maxsize: int
    ) -> Subscription[events.Event]:
        """The subscription of `callback` (its close ends the feed)."""
        return self.publisher.subscribe(
            callback, maxsize=maxsize, name="system-events", maxbytes=QUEUED_BYTES, weigh=weight
        )

    def leave(self) -> None:
        """The network leaves (before its session closes): the subscriber goes and the
        merge thread ends; the subscription gets no event more, and its close then calls
        no Zenoh."""
        with self._switching:
            self._left = True
            self._off()

    def _switch(self, listened: bool) -> None:
        with self._switching:
            if listened and self._subscriber is None and not self._left:
                self._thread = threading.Thread(
                    target=self._merge, name="rr-events-merge", daemon=True
                )
                self._thread.start()
                self._subscriber = self._session.declare_subscriber(
                    self._keys.all_events(), tracked(self._session, self._on_sample)
                )
            elif not listened:
                self._off()
                self.forget()

    def _off(self) -> None:
        """Undeclare the subscriber, end the merge thread (hold `_switching`)."""
        if self._subscriber is not None:
            with contextlib.suppress(Exception):
                self._subscriber.undeclare()
            self._subscriber = None
            self._raw.put(None)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """A batch came (Zenoh's thread): queue it within the bounds, never read it here."""
        data = sample.payload.to_bytes()
        key = str(sample.key_expr)
        seal = sample.attachment
        with self._lock:
            why = self._admit(key, len(data) + (0 if seal is None else len(seal)))
        if why:
            self._drop(key, data.count(b"\n") + 1, len(data), why)  # (its events: a line each)
        else:
            self._raw.put(_Batch(key, data, None if seal is None else seal.to_bytes()))

    def _admit(self, key: str, size: int) -> str:
        """Count a batch of `size` bytes from sender `key` as held; or why it cannot be
        (hold `_lock`)."""
        held = self._held.get(key, 0)
        if size > MAX_BATCH_BYTES:
            return f"it is over MAX_BATCH_BYTES ({MAX_BATCH_BYTES} bytes)"
        if held + size > HELD_BYTES[0]:
            return (
                f"{held} bytes of that process's events are held already (HELD_BYTES: at "
                f"most {HELD_BYTES[0]} of one process)"
            )
        if self._held_all + size > HELD_BYTES[1]:
            return (
                f"{self._held_all} bytes of events are held already (HELD_BYTES: at most "
                f"{HELD_BYTES[1]} of all processes)"
            )
        if self._batches >= BATCHES_HELD:
            return f"{self._batches} batches wait to be read already (BATCHES_HELD)"
        self._batches += 1
        self._held[key] = held + size
        self._held_all += size
        return ""

    def _exchange(self, key: str, raw: int, size: int) -> bool:
        """Count an event of `size` bytes held of sender `key` in place of the `raw` bytes
        of its line, if both bounds allow it (the merge thread)."""
        with self._lock:
            held = self._held.get(key, 0) - raw + size
            if held > HELD_BYTES[0] or self._held_all - raw + size > HELD_BYTES[1]:
                return False
            self._held[key] = held
            self._held_all += size - raw
            return True

    def _weigh_out(self, key: str, size: int) -> None:
        """`size` bytes of sender `key` are held no more."""
        with self._lock:
            held = self._held.get(key, 0) - size
            if held > 0:
                self._held[key] = held
            else:
                self._held.pop(key, None)
            self._held_all -= size

    def _read(self, batch: _Batch) -> list[tuple[events.Event, int]]:
        """The events of `batch`, each with its `weight`, counted as held in place of its
        line as it is read; what would pass a bound is dropped (counted for the next
        notice, warned of), as is a batch no member sealed (with a `seal`)."""
        key, data = batch.key, batch.data
        left = len(data) + len(batch.seal or b"")  # (its bytes still counted as held)
        found: list[tuple[events.Event, int]] = []
        try:
            member = None
            if self._seal is not None:
                member = self._seal.open(data, batch.seal)
                if member is None:
                    lost = data.count(b"\n") + 1
                    why = "no member's certificate sealed it"
                    self._drop(key, lost, len(data), why, refused=True)
                    return found
            bad = claimed = 0
            for line, after in _lines(data):
                event = _event(line)
                if event is None:
                    bad += 1
                    continue
                if member is not None and event.host != member:  # (its sealer's, whatever)
                    claimed += 1
                    if claimed == 1:
                        self._claiming.warning(
                            "events from %s, sealed by member %s, say they happened on host "
                            "%s: they are delivered as %s's",
                            key,
                            member,
                            short(event.host),
                            member,
                        )
                    event = dataclasses.replace(event, host=member)
                size, raw = weight(event), min(left, len(line) + 1)
                if not self._exchange(key, raw, size):
                    lost = 1 + data.count(b"\n", after) + (after < len(data))
                    why = "its events would pass HELD_BYTES once read"
                    self._drop(key, lost, len(data), why)
                    break
                left -= raw
                found.append((event, size))
            if bad:
                self._bad.warning(
                    "dropped %d lines of the event stream from %s: not events of this "
                    "rr_actors version, or with a number that is not finite (plain JSON is "
                    "all that is read)",
                    bad,
                    key,
                )
        finally:
            self._weigh_out(key, left)
        return found

    def _drop(self, key: str, lost: int, size: int, why: str, *, refused: bool = False) -> None:
        """`lost` events of a batch of `size` bytes from sender `key` were dropped (for a
        bound, or `refused`: no member sealed them): counted for the next notice, warned
        of (at most once a minute)."""
        with self._lock:
            if refused:
                self._refused += lost
            else:
                self._lost += lost
        self._dropping.warning(
            "a system-wide event subscriber dropped %d events of a batch of %d bytes from %s: "
            "%s; they are counted in an EventsDropped",
            lost,
            size,
            key,
            why,
        )

    def _merge(self) -> None:
        """Read batches; release events in `hlc` order, each at most `window` s late."""
        window = self._window
        held: list[tuple[int, int, events.Event, str, int]] = []  # a heap by stamp, arrival
        due: collections.deque[tuple[float, int]] = collections.deque()  # (deadline, stamp)
        arrivals = itertools.count()
        deliver = self.publisher.deliver
        while True:
            timeout = None if not due else max(0.0, due[0][0] - time.monotonic())
            try:
                item = self._raw.get(timeout=timeout)
            except queue.Empty:
                item = _Batch("", b"", None)
            if item is None:
                return
            if item.key:
                with self._lock:
                    self._batches -= 1
                found = self._read(item)
                with self._lock:
                    (lost, refused), self._lost, self._refused = (self._lost, self._refused), 0, 0
                if lost:
                    deliver(events.EventsDropped(lost, cause="full"))
                if refused:
                    deliver(events.EventsDropped(refused, cause="refused"))
                now = time.monotonic()
                for event, size in found:
                    if window <= 0:
                        deliver(event)
                        self._weigh_out(item.key, size)
                        continue
                    heapq.heappush(held, (event.hlc, next(arrivals), event, item.key, size))
                    due.append((now + window, event.hlc))
            now = time.monotonic()
            top = -1
            while due and due[0][0] <= now:
                top = max(top, due.popleft()[1])
            while held and held[0][0] <= top:
                _, _, event, sender, size = heapq.heappop(held)
                deliver(event)
                self._weigh_out(sender, size)


class Across:
    """What runs beside one process's Zenoh session (`net.Beside`): see the module docstring.

    Args:
        opened: the session, as it opened (`net.Opened`; `connect` is `None` in a process
            that attached through its router, which watches no link).
    """

    def __init__(self, opened: Opened) -> None:
        self._opened = opened
        tls = opened.tls
        self._seal: Seal | None = None
        if tls is not None:  # each batch sealed with this host's certificate
            from rr_actors_lab.observe._seal import Seal  # noqa: PLC0415 - cryptography

            self._seal = Seal(tls, opened.system)
        session = opened.session
        self._export = EventExport(session, opened.keys, str(session.zid()), self._seal)
        self._watch: LinkWatch | None = None
        self._feeds: set[EventFeed] = set()  # (ended first at `close`, while the session is open)
        self._closed = False
        if tls is not None and opened.connect is not None:  # a router: who links, and why
            try:  # a connect endpoint is not (the reason in its WARNING)
                self._watch = LinkWatch(opened.system, session, tls, opened.connect)
            except BaseException:
                self._export.close()
                raise

    def subscribe_events(
        self, callback: Callable[[events.Event], object], window: float, maxsize: int
    ) -> Subscription[events.Event]:
        """`ZenohNetwork.subscribe_events`: a feed of its own, this process's events
        sent from the return on (at most `ASK_TIMEOUT` s)."""
        feed = EventFeed(self._opened.session, self._opened.keys, window, self._seal)
        subscription = feed.subscribe(callback, maxsize)
        self._feeds.add(feed)
        feed.forget = lambda: self._feeds.discard(feed)  # (its last listener went)
        if self._closed:  # (the network left meanwhile: its subscriber goes at once)
            feed.leave()
        self._export.wait_sending(ASK_TIMEOUT)
        return subscription

    def unlinked(self) -> list[tuple[str, str]]:
        """A router's `connect` endpoints with no link now, each with why: the link
        watch's (TLS: the handshake's verdict), or a TCP connect's for plain TCP."""
        connect = self._opened.connect
        if self._watch is not None:
            return self._watch.unlinked()
        if connect is None or self._opened.tls is not None:
            return []
        return plain_unlinked(self._opened.session, connect, timeout=PROBE_TIMEOUT)

    def member_links(self) -> list[MemberLink]:
        """Each member a TLS router has been linked to, as last seen (none without)."""
        return [] if self._watch is None else self._watch.member_links()

    def close(self) -> None:
        """End each feed's subscriber, stop watching, then sending (idempotent): before
        the session closes, so that no thread of theirs calls Zenoh after it."""
        self._closed = True
        for feed in list(self._feeds):
            feed.leave()
        if self._watch is not None:
            self._watch.close()
        self._export.close()


attach_beside(Across)
