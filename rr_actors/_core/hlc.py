"""A hybrid logical clock (Kulkarni et al., 2014): one per process, stamps events and messages.

Wall clocks of two machines differ, so a stream of events of several hosts ordered by
wall time can put an effect before its cause. A hybrid logical clock keeps a stamp
`(l, c)`: `l` is the greatest physical time this process has heard of (its own clock,
or a stamp a message brought), `c` a counter that orders what happens while `l` stays
the same. Then whenever event `e` happened before event `f` (in the same process, or
`e` before a message whose receipt came before `f`), `stamp(e) < stamp(f)`; and `l` is
the physical time wherever the clocks are consistent, never further ahead of the
fastest clock of the system than that clock is of the others.

A stamp is one int of 64 bits, so that it is one sort key, one JSON number, 8 bytes on
the wire:

```
 stamp = l << COUNTER_BITS | c        l: microseconds since the epoch (52 bits: until 2112)
                                      c: the counter (COUNTER_BITS = 12 bits)
```

In this packed form the paper's rules are two lines: a local event (or a send) takes
`max(last + 1, physical << COUNTER_BITS)`, a receipt `max(last + 1, stamp + 1,
physical << COUNTER_BITS)`. A counter past its 12 bits carries into `l` (4,096 events
within one microsecond of `l`: `l` gets one microsecond ahead), which keeps every stamp
of the process greater than the one before.

Processes of one host read one physical clock; a message between two of them takes
more than a microsecond, so their stamps order cause before effect without carrying
the stamp (the AF_UNIX carrier does not). Across hosts the Zenoh carrier carries the
sender's stamp on every message and answer (`zenoh.wire`), and the receiver's clock
takes it in (`receive`) before the message is handled.

`CLOCK` is this process's clock. Its physical clock is `time.time_ns`, unless the
environment variable `RR_ACTORS_CLOCK_SKEW` (seconds, a float) is set when this module
is imported: then this process (and the manager processes it starts, which inherit the
environment) reads a physical clock that many seconds off. That, and assigning
`CLOCK.physical`, are seams for tests that skew one host's clock; events' `at`
(`CLOCK.wall()`) reads the same physical clock as their stamps.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable

__all__ = [
    "CLOCK",
    "COUNTER_BITS",
    "SKEW_ENV",
    "HybridClock",
    "from_seconds",
    "pack",
    "seconds",
    "unpack",
]

logger = logging.getLogger("rr_actors")

COUNTER_BITS = 12
"""Bits of the counter `c` at the bottom of a stamp; `l` (microseconds) is above them."""

_MASK = (1 << COUNTER_BITS) - 1
_MAX = (1 << 64) - 1

SKEW_ENV = "RR_ACTORS_CLOCK_SKEW"
"""Environment variable: seconds this process's physical clock is off (tests only)."""

AHEAD_WARNING = 60.0
"""Seconds a received stamp may be ahead of this process's physical clock before a
WARNING says so (once per minute): the clocks of the system's hosts differ by that
much, and every stamp of this process stays that far ahead until its clock catches up."""


def pack(l_us: int, c: int) -> int:
    """The stamp of physical part `l_us` (microseconds since the epoch) and counter `c`."""
    return (l_us << COUNTER_BITS) | (c & _MASK)


def unpack(stamp: int) -> tuple[int, int]:
    """`(l, c)` of `stamp`: microseconds since the epoch, and the counter."""
    return stamp >> COUNTER_BITS, stamp & _MASK


def seconds(stamp: int) -> float:
    """The physical part of `stamp`, in seconds since the epoch (as `time.time()`)."""
    return (stamp >> COUNTER_BITS) / 1e6


def from_seconds(at: float) -> int:
    """The stamp with physical part `at` (seconds since the epoch) and counter 0: what an
    event written before events had stamps is ordered by (its `at`)."""
    return pack(int(at * 1e6), 0)


def _skew() -> float:
    text = os.environ.get(SKEW_ENV, "")
    if not text:
        return 0.0
    try:
        return float(text)
    except ValueError:
        logger.warning("%s=%r is not a number of seconds; ignored", SKEW_ENV, text)
        return 0.0


_SKEW_NS = int(_skew() * 1e9)


def _skewed_ns() -> int:
    return time.time_ns() + _SKEW_NS


class HybridClock:
    """A hybrid logical clock (see the module docstring). Thread-safe.

    Args:
        physical: the physical clock, nanoseconds since the epoch (`time.time_ns`);
            injected by tests.
        ahead_warning: seconds a received stamp may be ahead of `physical` before a
            WARNING (at most one a minute) says so.
    """

    __slots__ = ("_ahead", "_last", "_lock", "_warned", "physical")

    def __init__(
        self,
        physical: Callable[[], int] = time.time_ns,
        *,
        ahead_warning: float = AHEAD_WARNING,
    ) -> None:
        self.physical = physical
        self._ahead = int(ahead_warning * 1e6) << COUNTER_BITS
        self._last = 0
        self._lock = threading.Lock()
        self._warned = -1e18

    def wall(self) -> float:
        """The physical clock in seconds since the epoch (as `time.time()`): events' `at`."""
        return self.physical() / 1e9

    @property
    def last(self) -> int:
        """The latest stamp given (0 before the first)."""
        return self._last

    def now(self) -> int:
        """The stamp of a local event or of a message sent now: greater than every stamp
        this clock gave or took in before."""
        pt = (self.physical() // 1000) << COUNTER_BITS
        with self._lock:
            last = self._last + 1
            self._last = stamp = pt if pt > last else last
        return stamp

    send = now

    def receive(self, stamp: int) -> int:
        """Take in the stamp a message brought (before the message is handled); returns
        the stamp of the receipt, greater than both `stamp` and every stamp before.

        A stamp that is not an int in 0..2**64-1 is ignored (the clock ticks as for a
        local event).
        """
        if not isinstance(stamp, int) or not 0 <= stamp <= _MAX:
            return self.now()
        pt = (self.physical() // 1000) << COUNTER_BITS
        with self._lock:
            last = max(self._last, stamp) + 1
            self._last = new = pt if pt > last else last
        if stamp - pt > self._ahead:
            self._ahead_of_us(stamp, pt)
        return new

    def _ahead_of_us(self, stamp: int, pt: int) -> None:
        now = time.monotonic()
        if now - self._warned < 60.0:
            return
        self._warned = now
        logger.warning(
            "a message came with a clock stamp %.3f s ahead of this host's clock: the "
            "hosts' clocks differ by that much (events are stamped that far ahead until "
            "this clock catches up; synchronise the clocks, e.g. with NTP)",
            seconds(stamp - pt),
        )


CLOCK = HybridClock(_skewed_ns if _SKEW_NS else time.time_ns)
"""This process's clock: every event is stamped by it, every message across hosts
carries its stamp."""
