"""What the page shows, kept once for every open page: sections, and the recent events.

```
 source threads ── put(key, value) / add_event(e) ──► Hub ── listeners() ──► each page's
 (tree watcher, catalog refresher,                          │       (call_soon_threadsafe)  stream
  event subscription, backup poller)                        └── changes(seen, last_seq) ◄── wakes
```

A section holds one JSON-able value and a version; a page's stream asks for what changed
since the versions it sent, so a slow page skips intermediate values (its cost bounded).
Messages are encoded once and shared (`messages`: a patch, `_delta.diff`, for a page at
the previous version). Events are kept in a ring of `RING`, converted to JSON only when a
page first asks, at most `BATCH` at a time; a page that fell behind is told how many it
missed. At most `MAX_STREAMS` streams are open at once.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import math
import threading
import time
import uuid
from collections.abc import Callable
from typing import Any

from rr_actors._core.throttle import LogThrottle, short
from rr_actors_lab.observe._delta import diff

__all__ = ["BATCH", "MAX_STREAMS", "RING", "Changes", "Hub", "sse"]

logger = logging.getLogger("rr_actors")

RING = 500
"""Events the hub keeps for pages that connect or reconnect."""

BATCH = 200
"""Events a page gets at most in one look (the older ones of a burst count as missed)."""

MAX_STREAMS = 32
"""Pages (event streams) open at once; one more is refused (503) until one closes."""


def sse(event: str, data: str) -> bytes:
    """One server-sent event: its name and its data (one line of JSON)."""
    return f"event: {event}\ndata: {data}\n\n".encode()


def _refused(event: dict[str, Any], seq: int, log: LogThrottle) -> dict[str, Any]:
    """What a page gets in place of `event`, which holds a number that is not finite
    (said on `log`)."""
    kind, at = event.get("type"), event.get("at")
    log.warning(
        "observer: a %s event holds a number that is not finite (NaN or infinity); the pages "
        "get a line that says so instead",
        short(kind),
    )
    return {
        "type": "Refused",
        "seq": seq,
        "at": at if isinstance(at, int | float) and math.isfinite(at) else time.time(),
        "member": event.get("member") if isinstance(event.get("member"), str) else None,
        "text": "an event with a number that is not finite (NaN or infinity) was dropped",
    }


@dataclasses.dataclass
class _Section:
    """A section's value and version, the one before, and their encodings (made once)."""

    version: int
    value: Any
    before: int = 0  # the previous version (0: none)
    old: Any = None  # its value (kept until the patch from it is made)
    full: bytes | None = None
    patch: bytes | None = None


@dataclasses.dataclass(frozen=True)
class Changes:
    """What a page has not seen yet.

    Attributes:
        sections: `(key, version, value)` of each section that changed (`value` is
            `None` for a section that was removed).
        events: the events after the page's last one, oldest first.
        missed: events that fell out of the ring before the page saw them.
    """

    sections: list[tuple[str, int, Any]]
    events: list[dict[str, Any]]
    missed: int


class Hub:
    """Thread-safe store of the page's sections and recent events, with change listeners.

    Args:
        ring: how many recent events to keep.
        convert: turns a kept event into its JSON-able dict (once, when first needed).
    """

    def __init__(
        self, *, ring: int = RING, convert: Callable[[Any], dict[str, Any]] | None = None
    ) -> None:
        self.instance = uuid.uuid4().hex[:12]  # a page that reconnects to another hub resets
        self._lock = threading.Lock()
        self._sections: dict[str, _Section] = {}
        self._version = 0
        self._events: collections.deque[list[Any]] = collections.deque(maxlen=ring)  # [seq, e]
        self._convert = convert or dict
        self._seq = 0
        self._listeners: list[Callable[[], None]] = []
        self._streams = threading.Condition(self._lock)
        self._open_streams = 0
        self._refusals = LogThrottle(logger)  # (events refused: a line a minute at most)
        self.closed = False

    def put(self, key: str, value: Any) -> bool:
        """Set section `key` to a JSON-able `value`; tell the listeners and return True if it
        changed."""
        with self._lock:
            current = self._sections.get(key)
            if current is not None and current.value == value:
                return False
            self._version += 1
            if current is None:
                self._sections[key] = _Section(self._version, value)
            else:
                self._sections[key] = _Section(self._version, value, current.version, current.value)
        self._notify()
        return True

    def remove(self, key: str) -> None:
        """Remove section `key` (pages are told: its value becomes `None`)."""
        self.put(key, None)

    def get(self, key: str) -> Any:
        """The current value of section `key` (`None` if there is none)."""
        with self._lock:
            current = self._sections.get(key)
        return None if current is None else current.value

    def keys(self, prefix: str = "") -> list[str]:
        """The keys of the sections that have a value, starting with `prefix`."""
        with self._lock:
            return [
                k
                for k, section in self._sections.items()
                if k.startswith(prefix) and section.value is not None
            ]

    def add_event(self, event: Any) -> None:
        """Append an event (anything `convert` takes); it gets the next sequence number."""
        with self._lock:
            self._seq += 1
            if isinstance(event, dict):  # already JSON-able: numbered now
                event = {**event, "seq": self._seq}
            self._events.append([self._seq, event])
        self._notify()

    def changes(self, seen: dict[str, int], last_seq: int, *, with_events: bool = True) -> Changes:
        """What changed since a page saw the versions `seen` (updated) and the event `last_seq`
        (`with_events=False`: the sections only)."""
        with self._lock:
            sections = []
            for key, section in self._sections.items():
                if seen.get(key, 0) < section.version and (
                    section.value is not None or key in seen
                ):
                    sections.append((key, section.version, section.value))
                    seen[key] = section.version
            entries, missed = self._new_events(last_seq, with_events)
        return Changes(sections, [self._event(entry)[0] for entry in entries], missed)

    def _new_events(self, last_seq: int, with_events: bool) -> tuple[list[list[Any]], int]:
        """The ring's entries after `last_seq` (at most `BATCH`), and how many were missed."""
        if not with_events:
            return [], 0
        entries = [e for e in self._events if e[0] > last_seq][-BATCH:]
        first = entries[0][0] if entries else self._seq + 1
        return entries, max(0, first - last_seq - 1) if last_seq < self._seq else 0

    def _event(self, entry: list[Any]) -> tuple[dict[str, Any], str]:
        """A ring entry `[seq, event]` as a dict and as JSON, made once; one with a non-finite
        number
        goes as a `Refused` event (a page's `JSON.parse` would refuse the whole message)."""
        if len(entry) == 2:  # (converting twice at once, for two pages, does no harm)
            event = entry[1]
            if not isinstance(event, dict):
                event = self._convert(event)
                event["seq"] = entry[0]
            try:
                encoded = json.dumps(event, allow_nan=False)
            except ValueError:
                event = _refused(event, entry[0], self._refusals)
                encoded = json.dumps(event)
            entry[1:] = [event, encoded]
        return entry[1], entry[2]

    def messages(
        self, seen: dict[str, int], last_seq: int, *, with_events: bool = True
    ) -> tuple[list[bytes], int]:
        """What a page's stream sends next, encoded once and shared: changed sections (a `patch` for
        a page at the previous version), then new events; `seen` is updated as in `changes`.

        Returns:
            The messages, and the sequence number of their last event (else `last_seq`).
        """
        out = []
        with self._lock:
            for key, section in self._sections.items():
                had = seen.get(key, 0)
                if had >= section.version or (section.value is None and key not in seen):
                    continue
                out.append(self._encoded(key, section, patch=had == section.before and had > 0))
                seen[key] = section.version
            entries, missed = self._new_events(last_seq, with_events)
        if entries or missed:
            events = ",".join(self._event(entry)[1] for entry in entries)
            out.append(sse("events", f'{{"events":[{events}],"missed":{missed}}}'))
            last_seq = entries[-1][0] if entries else self._seq
        return out, last_seq

    def _encoded(self, key: str, section: _Section, *, patch: bool) -> bytes:
        """Section `key` as its whole value or the patch from the version before, encoded on first
        need."""
        if patch:
            if section.patch is None:
                change = diff(section.old, section.value)
                data = {"key": key, "version": section.version, "patch": change}
                section.patch = sse("patch", json.dumps(data))
                section.old = None  # (the patch is made: the old value is not needed any more)
            return section.patch
        if section.full is None:
            data = {"key": key, "version": section.version, "value": section.value}
            section.full = sse("section", json.dumps(data))
        return section.full

    def listen(self, listener: Callable[[], None]) -> Callable[[], None]:
        """Call `listener()` after each change (on the changing thread: it must not block); the
        remover."""
        with self._lock:
            self._listeners.append(listener)

        def unlisten() -> None:
            with self._lock:
                if listener in self._listeners:
                    self._listeners.remove(listener)

        return unlisten

    @property
    def last_seq(self) -> int:
        """The sequence number of the newest event."""
        return self._seq

    def close(self, *, timeout: float = 2.0) -> bool:
        """Mark the hub closed, wake every listener; whether every page's stream ended within
        `timeout` seconds (a page then sees a finished response, not a cut)."""
        self.closed = True
        self._notify()
        with self._streams:
            return self._streams.wait_for(lambda: self._open_streams == 0, timeout)

    def open_stream(self, limit: int = MAX_STREAMS) -> bool:
        """Count one more open stream unless `limit` are open; if counted (True), `close_stream()`
        follows."""
        with self._streams:
            if self._open_streams >= limit:
                return False
            self._open_streams += 1
            return True

    def close_stream(self) -> None:
        """A stream counted by `open_stream` ended."""
        with self._streams:
            self._open_streams -= 1
            self._streams.notify_all()

    @property
    def open_streams(self) -> int:
        """How many page streams are open."""
        return self._open_streams

    def _notify(self) -> None:
        with self._lock:
            listeners = list(self._listeners)
        for listener in listeners:
            listener()
