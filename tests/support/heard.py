"""The events a subscription delivered (a tree's or a registrar's), for a test to read."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, TypeVar

from rr_actors import events

E = TypeVar("E", bound=events.Event)


def events_of(kind: type[E]) -> tuple[list[E], threading.Event, Callable[[events.Event], None]]:
    """The events of `kind` a subscription delivers, in order; an event set at the first;
    and the callback to subscribe (it may be called on any thread)."""
    heard: list[E] = []
    seen = threading.Event()

    def on_event(event: events.Event) -> None:
        if isinstance(event, kind):
            heard.append(event)
            seen.set()

    return heard, seen, on_event


class Heard:
    """The events a subscription delivers, in order: subscribe with it (it may be called on
    any thread); `lock` (a condition) guards `events`."""

    def __init__(self) -> None:
        self.events: list[events.Event] = []
        self.lock = threading.Condition()

    def __call__(self, event: events.Event) -> None:
        with self.lock:
            self.events.append(event)
            self.lock.notify_all()

    def kinds(self) -> list[str]:
        """The events' class names, in order."""
        with self.lock:
            return [type(e).__name__ for e in self.events]

    def of(self, kind: type[Any], **fields: Any) -> list[Any]:
        """The events of `kind` whose attributes equal `fields`, in order."""
        with self.lock:
            return [
                e
                for e in self.events
                if isinstance(e, kind) and all(getattr(e, k) == v for k, v in fields.items())
            ]

    def wait(self, match: Callable[[events.Event], bool], timeout: float = 30.0) -> bool:
        """Whether an event that `match`es was heard within `timeout` seconds (generous: the
        machine is loaded)."""
        with self.lock:
            return self.lock.wait_for(lambda: any(map(match, self.events)), timeout)
