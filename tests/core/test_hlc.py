"""The hybrid logical clock (`rr_actors._core.hlc`, Kulkarni et al. 2014): send, receive,
monotonic, the bounds on how far `l` runs ahead of the physical clocks, and `max_offset`
(a stamp further ahead is refused; the clock never leaves its 64 bits: issue 40).

Each clock's physical clock is injected (nanoseconds), so the tests set the time.
"""

from __future__ import annotations

import logging
import os
import random
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest

from rr_actors._core import hlc
from rr_actors._core.hlc import COUNTER_BITS, HybridClock
from rr_actors.errors import ConfigError

US = 1_000  # nanoseconds in a microsecond
S = 1_000_000_000  # nanoseconds in a second


class Physical:
    """A physical clock the test sets (nanoseconds since the epoch)."""

    def __init__(self, ns: int) -> None:
        self.ns = ns

    def __call__(self) -> int:
        return self.ns


def test_a_stamp_packs_microseconds_and_a_counter_into_64_bits() -> None:
    stamp = hlc.pack(1_700_000_000_000_000, 5)
    assert (1_700_000_000_000_000, 5) == hlc.unpack(stamp)
    assert stamp < 2**64
    assert 1_700_000_000.0 == hlc.seconds(stamp)
    assert hlc.pack(1_700_000_000_000_000, 0) == hlc.from_seconds(1_700_000_000.0)


def test_local_events_take_the_physical_time_when_it_moves_and_count_when_it_does_not() -> None:
    physical = Physical(1_000 * S)
    clock = HybridClock(physical)
    first = clock.now()
    assert (1_000_000_000, 0) == hlc.unpack(first)
    assert (1_000_000_000, 1) == hlc.unpack(clock.now())  # same microsecond: the counter
    physical.ns += 7 * US
    assert (1_000_000_007, 0) == hlc.unpack(clock.now())  # it moved: back to 0


def test_stamps_never_go_back_when_the_physical_clock_does() -> None:
    physical = Physical(1_000 * S)
    clock = HybridClock(physical)
    before = clock.now()
    physical.ns -= 5 * S  # NTP stepped the clock back
    after = clock.now()
    assert after > before
    assert hlc.unpack(after) == (hlc.unpack(before)[0], 1)


def test_a_counter_past_its_bits_carries_into_l_and_stays_monotonic() -> None:
    clock = HybridClock(Physical(1_000 * S))
    stamps = [clock.now() for _ in range(3 * (1 << COUNTER_BITS))]
    assert stamps == sorted(set(stamps))
    assert hlc.unpack(stamps[-1])[0] == 1_000_000_000 + 2  # two carries


def test_a_receipt_comes_after_the_message_and_after_everything_before_it() -> None:
    behind = HybridClock(Physical(1_000 * S))  # this host's clock is 3 s behind
    ahead = HybridClock(Physical(1_003 * S))
    local = behind.now()
    sent = ahead.send()
    received = behind.receive(sent)
    assert received > sent > local
    assert hlc.unpack(received) == (hlc.unpack(sent)[0], 1)  # l from the message, c + 1
    assert behind.now() > received  # and what happens next here too


def test_a_receipt_from_a_clock_behind_keeps_the_local_time() -> None:
    fast = HybridClock(Physical(1_003 * S))
    slow = HybridClock(Physical(1_000 * S))
    before = fast.now()
    received = fast.receive(slow.send())
    assert received > before
    assert hlc.unpack(received) == (hlc.unpack(before)[0], 1)


def test_a_stamp_that_is_not_one_is_ignored() -> None:
    clock = HybridClock(Physical(1_000 * S))
    before = clock.now()
    for bad in (-1, 2**64, "7", None):
        assert clock.receive(bad) > before  # type: ignore[arg-type]
        assert hlc.unpack(clock.last)[0] == 1_000_000_000


def test_causality_holds_and_l_stays_within_the_skew_of_the_fastest_clock() -> None:
    """Three processes, clocks skewed by up to 5 s and drifting, exchanging messages at
    random: every receipt is after its send (cause before effect), every clock's `l` is
    at most the fastest physical clock (plus the microseconds counter carries can add),
    and never behind its own physical clock; `c` stays small (the paper's bound: it
    resets whenever `l` moves)."""
    rng = random.Random(7)  # noqa: S311 - a seeded schedule, not a secret
    skews = [0, 5 * S, 2 * S]
    physicals = [Physical(1_000 * S + skew) for skew in skews]
    clocks = [HybridClock(p) for p in physicals]
    in_flight: list[tuple[int, int]] = []  # (to, stamp)
    last = [0, 0, 0]
    for _step in range(20_000):
        for p in physicals:
            p.ns += rng.randrange(0, 3 * US)  # time passes, unevenly
        i = rng.randrange(3)
        roll = rng.random()
        if roll < 0.3 and in_flight:
            to, stamp = in_flight.pop(rng.randrange(len(in_flight)))
            got = clocks[to].receive(stamp)
            assert got > stamp
            i = to
        elif roll < 0.6:
            in_flight.append((rng.randrange(3), clocks[i].send()))
            got = clocks[i].last
        else:
            got = clocks[i].now()
        assert got > last[i]
        last[i] = got
        fastest = max(p.ns for p in physicals) // US
        l_us, c = hlc.unpack(got)
        assert physicals[i].ns // US <= l_us <= fastest + 1
        assert c < 1 << COUNTER_BITS


def test_the_clock_is_safe_to_use_from_many_threads() -> None:
    clock = HybridClock(Physical(1_000 * S))
    stamps: list[list[int]] = [[] for _ in range(4)]

    def tick(into: list[int]) -> None:
        into.extend(clock.now() for _ in range(5_000))

    threads = [threading.Thread(target=tick, args=(into,)) for into in stamps]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    every = [s for into in stamps for s in into]
    assert len(set(every)) == len(every)  # no stamp given twice
    assert all(into == sorted(into) for into in stamps)


def test_a_stamp_within_max_offset_ahead_is_taken_in() -> None:
    clock = HybridClock(Physical(1_000 * S), max_offset=60.0)
    ahead = hlc.pack((1_000 + 59) * 1_000_000, 3)
    assert hlc.unpack(clock.receive(ahead, "a1")) == (hlc.unpack(ahead)[0], 4)
    assert 0 == clock.refused


@pytest.mark.parametrize(
    "stamp",
    [
        pytest.param(2**64 - 1, id="the-last-stamp"),
        pytest.param(hlc.from_seconds(4_102_444_800.0), id="the-year-2100"),
        pytest.param(hlc.pack((1_000 + 61) * 1_000_000, 0), id="61-s-ahead"),
    ],
)
def test_a_stamp_more_than_max_offset_ahead_is_refused_counted_and_warned_naming_the_sender(
    caplog: pytest.LogCaptureFixture, stamp: int
) -> None:
    clock = HybridClock(Physical(1_000 * S), max_offset=60.0)
    before = clock.now()
    with caplog.at_level(logging.WARNING, logger="rr_actors"):
        received = clock.receive(stamp, "5eed")
        again = clock.receive(stamp, "5eed")

    assert before < received < again  # the receipt still ticks, as a local event
    assert (1_000_000_000, 2) == hlc.unpack(again)  # the physical time: not taken in
    assert 2 == clock.refused
    warned = [r.getMessage() for r in caplog.records]
    assert 1 == len(warned)  # at most one a minute
    assert "a message from process 5eed came with a clock stamp" in warned[0]
    assert "more than max_offset (60 s)" in warned[0]


def test_a_stamp_from_the_year_2100_does_not_spread_from_the_process_that_got_it() -> None:
    """The bug it guards against: one stamp carried every clock it reached, and every
    stamp after, into 2100, one message a hop."""
    physicals = [Physical(1_000 * S + skew) for skew in (0, 2 * S, 5 * S)]
    clocks = [HybridClock(p) for p in physicals]
    clocks[0].receive(hlc.from_seconds(4_102_444_800.0))
    stamp = clocks[0].send()
    for clock in clocks[1:]:
        stamp = clock.receive(stamp)
        stamp = clock.send()

    fastest = max(p.ns for p in physicals) // US
    assert all(hlc.unpack(clock.last)[0] <= fastest + 1 for clock in clocks)


def test_the_clock_never_leaves_its_64_bits_and_says_so_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    physical = Physical(1_000 * S)
    clock = HybridClock(physical, max_offset=60.0)
    clock.receive(hlc.pack(1_000_000_000 + 59_000_000, 0))
    physical.ns = ((2**64 - 1) >> COUNTER_BITS) * US - 30 * S  # 30 s before the end
    with caplog.at_level(logging.ERROR, logger="rr_actors"):
        taken = clock.receive(2**64 - 1)  # 30 s ahead: taken in, at the end of the range
        stamps = [clock.now(), clock.send(), clock.receive(2**64 - 1)]
        physical.ns += 3_600 * S  # the physical clock past the end itself
        stamps += [clock.now(), clock.now()]

    assert [2**64 - 1] * 6 == [taken, *stamps]
    assert 1 == len(caplog.records)
    assert "reached the end of its 64 bits" in caplog.records[0].getMessage()


@pytest.mark.parametrize(
    "bad", [0, -1.0, float("nan"), float("inf"), True, "60", None, 366 * 24 * 3600.0]
)
def test_a_max_offset_that_is_not_seconds_up_to_a_year_is_a_config_error_naming_it(
    bad: Any,
) -> None:
    with pytest.raises(ConfigError, match="max_offset"):
        HybridClock(max_offset=bad)
    clock = HybridClock()
    with pytest.raises(ConfigError, match="max_offset"):
        clock.max_offset = bad
    assert hlc.MAX_OFFSET == clock.max_offset  # unchanged


def test_the_skew_variable_skews_the_process_clock_and_the_events_wall_time(
    tmp_path: Path,
) -> None:
    code = (
        "import time; from rr_actors import events; from rr_actors._core import hlc\n"
        "e = events.InDoubt('erm', 'q')\n"
        "print(e.at - time.time(), hlc.seconds(e.hlc) - time.time())\n"
    )
    env = {**os.environ, hlc.SKEW_ENV: "-7.5"}
    done = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    at_off, stamp_off = (float(x) for x in done.stdout.split())
    assert -8.0 < at_off < -7.0
    assert -8.0 < stamp_off < -7.0
