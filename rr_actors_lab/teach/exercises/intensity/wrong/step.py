"""A wrong answer a student may write (the tests check that it fails): the window is
right, but this restart is left out of the count (one too few: it gives up too late)."""

from collections.abc import Sequence


def recent(times: Sequence[float], now: float, period: float) -> int:
    return sum(1 for t in times[:-1] if now - t < period)
