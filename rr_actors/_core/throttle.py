"""Rate-limited log lines: a trouble that repeats is logged the first time, then counted.

```
 trouble ─► Throttle.due() ─ the first: log it in full
                           ─ again within `every` s: counted only
                           ─ again after `every` s: log it with the count since the last line
```

A trouble a peer can cause once per message must cost a bounded number of log lines, each
of bounded length (`short`): else the log is a way to fill a disk.
"""

from __future__ import annotations

import logging
import reprlib
from collections.abc import Callable
from typing import Any

from rr_actors._core import runtime

EVERY = 60.0
"""Seconds between two log lines about the same trouble caused by a peer."""


class Throttle:
    """When a repeated trouble may be logged again (first, then every `every` s on `clock`), and
    how many happened meanwhile (`unlogged`). Not locked: its owner locks."""

    __slots__ = ("clock", "every", "logged", "next_at", "unlogged")

    def __init__(self, every: float = EVERY, *, clock: Callable[[], float] | None = None):
        self.every = every
        self.clock = runtime.monotonic if clock is None else clock
        self.next_at = float("-inf")
        self.logged = False  # whether the first one was logged (in full)
        self.unlogged = 0  # how many happened since the last log line

    def due(self) -> bool:
        """Count one more; whether a line may be logged now."""
        self.unlogged += 1
        now = self.clock()
        if now < self.next_at:
            return False
        self.next_at = now + self.every
        return True


class LogThrottle:
    """One kind of repeated WARNING to `logger`, thread-safe: the first in full, later ones at
    most every `every` seconds with the count since the previous line."""

    def __init__(
        self,
        logger: logging.Logger,
        every: float = EVERY,
        *,
        clock: Callable[[], float] | None = None,
    ) -> None:
        self._logger = logger
        self._lock = runtime.Lock()
        self._throttle = Throttle(every, clock=clock)

    def warning(self, message: str, *args: Any) -> None:
        """Log `message % args` at WARNING if due, else only count it."""
        throttle = self._throttle
        with self._lock:
            if not throttle.due():
                return
            more, throttle.unlogged = throttle.unlogged - 1, 0
        if more:
            self._logger.warning(
                message + " (%d more like it since the last such line)", *args, more
            )
        else:
            self._logger.warning(message, *args)


_SHORT = reprlib.Repr()  # (Python 3.11 takes no keyword arguments here)
_SHORT.maxlevel = 2
_SHORT.maxstring = 240  # (a well-formed key expression of rr_actors' fits whole)
_SHORT.maxother = 80
_SHORT.maxdict = _SHORT.maxlist = _SHORT.maxtuple = _SHORT.maxset = 4
_SHORT_WIDTH = 256


def short(value: Any) -> str:
    """A bounded `repr` (at most 256 characters) for a log line; never raises. Only for values
    whose `repr` runs no user code (builtin data, what a peer sent)."""
    try:
        text = _SHORT.repr(value)
    except Exception as exc:  # noqa: BLE001 - a log line must not fail
        return f"<repr failed: {type(exc).__name__}>"
    return text if len(text) <= _SHORT_WIDTH else text[: _SHORT_WIDTH - 3] + "..."
