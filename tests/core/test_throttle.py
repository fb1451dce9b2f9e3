"""Rate-limited log lines (`rr_actors._core.throttle`): the first, then a count per interval."""

from __future__ import annotations

import logging

import pytest

from rr_actors._core.throttle import LogThrottle, short


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_a_repeated_warning_is_logged_once_then_as_a_count_per_interval(
    caplog: pytest.LogCaptureFixture,
) -> None:
    clock = Clock()
    throttle = LogThrottle(logging.getLogger("rr_actors"), 60.0, clock=clock)
    with caplog.at_level(logging.WARNING, logger="rr_actors"):
        for n in range(1000):
            clock.now = n * 0.1  # 100 s in all
            throttle.warning("trouble %d", n)

    assert ["trouble 0", "trouble 600 (599 more like it since the last such line)"] == [
        r.getMessage() for r in caplog.records
    ]


def test_a_short_repr_is_bounded_and_never_raises() -> None:
    class Broken:
        def __repr__(self) -> str:
            raise ValueError("no")

    assert len(short("x" * 100_000)) <= 256
    assert len(short(list(range(100_000)))) <= 256
    assert short(Broken()).startswith("<Broken")  # (reprlib names it instead)
