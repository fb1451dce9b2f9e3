"""A hybrid logical clock (Kulkarni et al., 2014): one per process, stamps events and messages.

A stamp orders cause before effect across hosts, whatever their clocks say, and is the physical time
wherever the clocks agree. It is one 64-bit int (one sort key, one JSON number, 8 bytes):

```
 stamp = l << COUNTER_BITS | c        l: microseconds since the epoch (52 bits: until 2112)
                                      c: the counter (COUNTER_BITS = 12 bits)
```

A local event takes `max(last + 1, physical << COUNTER_BITS)`, a receipt also `stamp + 1`. A stamp
more than `max_offset` ahead is refused, and the clock never leaves its 64 bits: why, in
docs/explanation/failure-semantics.md ("Its clock stamps"). The Zenoh carrier carries stamps
(`receive`); one host's processes share a clock. `RR_ACTORS_CLOCK_SKEW` (seconds, at import) or
`CLOCK.physical` skews it for tests.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable

from rr_actors._core import runtime
from rr_actors._core.throttle import Throttle
from rr_actors.errors import ConfigError

logger = logging.getLogger("rr_actors")

COUNTER_BITS = 12
"""Bits of the counter `c` at the bottom of a stamp; `l` (microseconds) is above them."""

_MASK = (1 << COUNTER_BITS) - 1
_MAX = (1 << 64) - 1

SKEW_ENV = "RR_ACTORS_CLOCK_SKEW"
"""Environment variable: seconds this process's physical clock is off (tests only)."""

MAX_OFFSET = 60.0
"""Seconds a received stamp may be ahead of this process's physical clock and still be
taken in (`ZenohNetwork(max_offset=...)` sets it).
"""

MAX_OFFSET_LIMIT = 365 * 24 * 3600.0
"""The largest `max_offset` allowed (one year): a larger one could carry a clock past its range."""

REFUSED_EVERY = 60.0
"""Seconds between two WARNINGs about refused stamps (what comes between is counted)."""


def check_max_offset(value: object) -> float:
    """`value` as seconds for `max_offset`, or a `ConfigError` naming it."""
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or not 0 < value <= MAX_OFFSET_LIMIT
    ):
        raise ConfigError(
            f"max_offset must be seconds above 0 and at most {MAX_OFFSET_LIMIT:g} (a year), "
            f"not {value!r}"
        )
    return float(value)


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
    """The stamp of `at` (epoch seconds), counter 0: where an event older than stamps sorts."""
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
    return runtime.wall_ns() + _SKEW_NS


class HybridClock:
    """A hybrid logical clock (module docstring), thread-safe, never raising: `physical` in ns
    (`None`: `runtime.wall_ns`); `refused` counts stamps over `max_offset` s ahead (`ConfigError`
    unless above 0 and at most a year)."""

    # (no `__slots__`: a simulation swaps a clock's `__dict__` whole per simulated process)

    def __init__(
        self,
        physical: Callable[[], int] | None = None,
        *,
        max_offset: float = MAX_OFFSET,
    ) -> None:
        self.physical = runtime.wall_ns if physical is None else physical
        self._max_ahead = 0
        self.max_offset = max_offset
        self._last = 0
        self._lock = runtime.Lock()
        self.refused = 0
        self._refusals = Throttle(REFUSED_EVERY)
        self._ended = False

    @property
    def max_offset(self) -> float:
        return (self._max_ahead >> COUNTER_BITS) / 1e6

    @max_offset.setter
    def max_offset(self, seconds: float) -> None:
        self._max_ahead = int(check_max_offset(seconds) * 1e6) << COUNTER_BITS

    def wall(self) -> float:
        """The physical clock in seconds since the epoch: events' `at`."""
        return self.physical() / 1e9

    @property
    def last(self) -> int:
        """The latest stamp given (0 before the first)."""
        return self._last

    def now(self) -> int:
        """A local event's or a send's stamp: above every one before (at the range's end, equal)."""
        pt = (self.physical() // 1000) << COUNTER_BITS
        with self._lock:
            last = self._last + 1
            stamp = pt if pt > last else last
            self._last = stamp = stamp if stamp <= _MAX else self._end()
        return stamp

    send = now

    def receive(self, stamp: int, sender: str = "") -> int:
        """Take in a message's stamp before it is handled; the receipt's stamp. Not an int in
        0..2**64-1: ignored; too far ahead: refused, counted (WARNING a minute, naming `sender`)."""
        if not isinstance(stamp, int) or not 0 <= stamp <= _MAX:
            return self.now()
        pt = (self.physical() // 1000) << COUNTER_BITS
        if stamp - pt > self._max_ahead:
            self._refuse(stamp, pt, sender)
            return self.now()
        with self._lock:
            last = max(self._last, stamp) + 1
            new = pt if pt > last else last
            self._last = new = new if new <= _MAX else self._end()
        return new

    def _refuse(self, stamp: int, pt: int, sender: str) -> None:
        with self._lock:
            self.refused += 1
            if not self._refusals.due():
                return
            since, self._refusals.unlogged = self._refusals.unlogged, 0  # (this one too)
        logger.warning(
            "a message from %s came with a clock stamp %.3f s ahead of this host's clock, "
            "more than max_offset (%g s): the message was handled, its stamp not taken in "
            "(%d refused since the last such line). That host's clock is wrong (synchronise "
            "the clocks, e.g. with NTP) or its process is buggy; ZenohNetwork(max_offset=...) "
            "sets the bound",
            f"process {sender}" if sender else "another process",
            seconds(stamp - pt),
            self.max_offset,
            since,
        )

    def _end(self) -> int:
        """The last stamp of the range, where the clock stays (hold `_lock`)."""
        if not self._ended:
            self._ended = True
            logger.error(
                "this process's hybrid clock reached the end of its 64 bits (physical time "
                "%.0f s since the epoch, after the year 2112): its stamps stay at the last one, "
                "so events after it are no longer ordered by their stamps; set this "
                "host's clock right",
                self.physical() / 1e9,
            )
        return _MAX


CLOCK = runtime.process_state(HybridClock(_skewed_ns if _SKEW_NS else None), HybridClock)
"""This process's clock: it stamps every event and every message across hosts."""
