"""One-shot timers: the default runs on a daemon thread; tests inject their own."""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from rr_actors._core import runtime

__all__ = ["Cancellable", "Timer", "thread_timer"]


class Cancellable(Protocol):
    """A started timer (`threading.Timer` is one)."""

    def cancel(self) -> None:
        """Stop the timer if it has not fired yet."""


Timer = Callable[[float, Callable[[], None]], Cancellable]
"""`timer(delay, fn)`: run `fn()` once after `delay` seconds on some thread."""


def thread_timer(delay: float, fn: Callable[[], None]) -> Cancellable:
    """Run `fn()` on a daemon thread after `delay` seconds (the default `Timer`)."""
    timer = runtime.Timer(delay, fn)
    timer.daemon = True
    timer.start()
    return timer
