"""What the page shows, kept once for every open page: sections, and the recent events.

```
 source threads ── put(key, value) / add_event(e) ──► Hub ── listeners() ──► each page's
 (tree watcher, catalog refresher,                          │       (call_soon_threadsafe)  stream
  event subscription, backup poller)                        └── changes(seen, last_seq) ◄── wakes
```

A section (`"tree"`, `"graph"`, `"catalog/<registrar>"`, ...) holds one JSON-able value
and a version; a page's stream remembers the versions it sent and asks for what changed
since, so a slow page skips intermediate values instead of queueing them: what a page
costs is bounded whatever happens. Events are kept in a ring of the last `RING` events,
each with a sequence number; a page that fell further behind is told how many it missed.
An event is turned into its JSON-able dict (`convert`) only when a page first asks for
it, and a page gets at most `BATCH` events at a time: with no page open, keeping an
event costs an append, and a flood of events costs a page a bounded amount.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import threading
import uuid
from collections.abc import Callable, Iterator
from typing import Any

__all__ = ["BATCH", "RING", "Changes", "Hub"]

RING = 500
"""Events the hub keeps for pages that connect or reconnect."""

BATCH = 200
"""Events a page gets at most in one look (the older ones of a burst count as missed)."""


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
        self._sections: dict[str, tuple[int, Any]] = {}
        self._version = 0
        self._events: collections.deque[list[Any]] = collections.deque(maxlen=ring)  # [seq, e]
        self._convert = convert or dict
        self._seq = 0
        self._listeners: list[Callable[[], None]] = []
        self._streams = threading.Condition(self._lock)
        self._open_streams = 0
        self.closed = False

    def put(self, key: str, value: Any) -> bool:
        """Set section `key` to `value` (a JSON-able value); tell the listeners if it changed.

        Returns:
            Whether it changed.
        """
        with self._lock:
            current = self._sections.get(key)
            if current is not None and current[1] == value:
                return False
            self._version += 1
            self._sections[key] = (self._version, value)
        self._notify()
        return True

    def remove(self, key: str) -> None:
        """Remove section `key` (pages are told: its value becomes `None`)."""
        self.put(key, None)

    def get(self, key: str) -> Any:
        """The current value of section `key` (`None` if there is none)."""
        with self._lock:
            current = self._sections.get(key)
        return None if current is None else current[1]

    def keys(self, prefix: str = "") -> list[str]:
        """The keys of the sections that have a value, starting with `prefix`."""
        with self._lock:
            return [
                k for k, (_, v) in self._sections.items() if k.startswith(prefix) and v is not None
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
        """What changed since a page saw the versions `seen` and the event `last_seq`.

        `seen` is updated to the versions returned. With `with_events=False` only the sections
        are looked at (the events wait for a later look).
        """
        with self._lock:
            sections = []
            for key, (version, value) in self._sections.items():
                if seen.get(key, 0) < version and (value is not None or key in seen):
                    sections.append((key, version, value))
                    seen[key] = version
            entries = [e for e in self._events if e[0] > last_seq][-BATCH:] if with_events else []
            first = entries[0][0] if entries else self._seq + 1
            missed = max(0, first - last_seq - 1) if with_events and last_seq < self._seq else 0
        events = []
        for entry in entries:  # (converting twice at once, for two pages, does no harm)
            if not isinstance(entry[1], dict):
                converted = self._convert(entry[1])
                converted["seq"] = entry[0]
                entry[1] = converted
            events.append(entry[1])
        return Changes(sections, events, missed)

    def listen(self, listener: Callable[[], None]) -> Callable[[], None]:
        """Call `listener()` (on the changing thread; it must not block) after each change.

        Returns:
            A function that removes the listener.
        """
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
        """Mark the hub closed, wake every listener, wait for the pages' streams to end.

        Returns:
            Whether every stream ended within `timeout` seconds (ended cleanly, a page
            sees a finished response rather than a cut connection).
        """
        self.closed = True
        self._notify()
        with self._streams:
            return self._streams.wait_for(lambda: self._open_streams == 0, timeout)

    @contextlib.contextmanager
    def stream(self) -> Iterator[None]:
        """Count an open page stream while the block runs (`close` waits for them)."""
        with self._streams:
            self._open_streams += 1
        try:
            yield
        finally:
            with self._streams:
                self._open_streams -= 1
                self._streams.notify_all()

    def _notify(self) -> None:
        with self._lock:
            listeners = list(self._listeners)
        for listener in listeners:
            listener()
