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

Bounded, as the paper's and CockroachDB's `max-offset`: a received stamp more than
`max_offset` seconds (`MAX_OFFSET` by default) ahead of this process's physical clock is
not taken in. The message is handled as always, and the clock ticks as for a local
event; the stamp is counted (`refused`) and a WARNING (at most one a minute) names the
process it came from. So one stamp from a buggy member or a host whose clock is in the
year 2100 does not carry every clock it reaches (and every stamp after) into its
future, and `l` is never more than `max_offset` ahead of the fastest physical clock of
the system. A clock never leaves its 64 bits: at their end (a physical clock past the
year 2112) it stays at the last stamp (an ERROR says so, once), and it never raises.

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
import math
import os
from collections.abc import Callable

from rr_actors._core import runtime
from rr_actors._core.throttle import Throttle
from rr_actors.errors import ConfigError

__all__ = [
    "CLOCK",
    "COUNTER_BITS",
    "MAX_OFFSET",
    "MAX_OFFSET_LIMIT",
    "REFUSED_EVERY",
    "SKEW_ENV",
    "HybridClock",
    "check_max_offset",
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

MAX_OFFSET = 60.0
"""Seconds a received stamp may be ahead of this process's physical clock and still be
taken in (`HybridClock.max_offset`; `ZenohNetwork(max_offset=...)` sets it).

CockroachDB's `max-offset` is 0.5 s: its stamps order transactions, and a node whose
clock is further off stops itself. Here stamps order an event timeline, and a robot may
run without NTP (a clock without a battery starts where it stopped, and drifts seconds
a day): a minute keeps cause before effect between hosts whose clocks differ by less,
refuses a stamp from a clock that is plainly wrong (the year 2100, the last stamp of
the range), and keeps every clock at most a minute ahead of the fastest host's."""

MAX_OFFSET_LIMIT = 365 * 24 * 3600.0
"""The largest `max_offset` allowed (one year): with any larger, a stamp could carry a
clock past the end of its range before the physical clocks get near it."""

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
    return runtime.wall_ns() + _SKEW_NS


class HybridClock:
    """A hybrid logical clock (see the module docstring). Thread-safe; it never raises.

    Args:
        physical: the physical clock, nanoseconds since the epoch (`None`:
            `runtime.wall_ns`, the stdlib's `time.time_ns` in a real run); injected by
            tests.
        max_offset: seconds a received stamp may be ahead of `physical` and be taken in
            (see `MAX_OFFSET`); one further ahead is refused.

    Attributes:
        refused: how many received stamps were refused so far (further ahead than
            `max_offset`).

    Raises:
        ConfigError: `max_offset` is not seconds above 0 and at most a year.
    """

    # (no `__slots__`: a simulation keeps a clock per simulated process, and swaps an
    # instance's `__dict__` whole at a switch between processes, where a slotted one's
    # fields are copied out and back, one by one: `simulation/_processes.py`)

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
        """Seconds a received stamp may be ahead of the physical clock and be taken in."""
        return (self._max_ahead >> COUNTER_BITS) / 1e6

    @max_offset.setter
    def max_offset(self, seconds: float) -> None:
        self._max_ahead = int(check_max_offset(seconds) * 1e6) << COUNTER_BITS

    def wall(self) -> float:
        """The physical clock in seconds since the epoch (as `time.time()`): events' `at`."""
        return self.physical() / 1e9

    @property
    def last(self) -> int:
        """The latest stamp given (0 before the first)."""
        return self._last

    def now(self) -> int:
        """The stamp of a local event or of a message sent now: greater than every stamp
        this clock gave or took in before (at the end of the range: equal to the last)."""
        pt = (self.physical() // 1000) << COUNTER_BITS
        with self._lock:
            last = self._last + 1
            stamp = pt if pt > last else last
            self._last = stamp = stamp if stamp <= _MAX else self._end()
        return stamp

    send = now

    def receive(self, stamp: int, sender: str = "") -> int:
        """Take in the stamp a message brought (before the message is handled); returns
        the stamp of the receipt, greater than both `stamp` and every stamp before.

        A stamp that is not an int in 0..2**64-1 is ignored, and one more than
        `max_offset` ahead of the physical clock is refused (counted in `refused`; a
        WARNING at most once a minute names `sender`, the process it came from): then
        the clock ticks as for a local event.
        """
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
"""This process's clock: every event is stamped by it, every message across hosts
carries its stamp."""
