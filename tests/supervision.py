"""A clock and a timer that supervisor tests drive by hand (injected into `Supervisor`)."""

from __future__ import annotations

import threading
from collections.abc import Callable


class FakeClock:
    """A monotonic clock that moves only when the test says so."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class _Handle:
    def __init__(self) -> None:
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True


class ManualTimer:
    """A `timer` that records delays and fires only when the test calls `fire()`."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.pending: list[tuple[float, Callable[[], None], _Handle]] = []
        self.delays: list[float] = []

    def __call__(self, delay: float, fn: Callable[[], None]) -> _Handle:
        handle = _Handle()
        with self.cond:
            self.pending.append((delay, fn, handle))
            self.delays.append(delay)
            self.cond.notify_all()
        return handle

    def wait_scheduled(self, count: int, timeout: float = 5.0) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: len(self.delays) >= count, timeout)

    def fire(self) -> None:
        with self.cond:
            pending, self.pending = self.pending, []
        for _, fn, handle in pending:
            if not handle.cancelled:
                fn()
