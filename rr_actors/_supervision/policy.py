"""The restart policy: pure decisions over data, no threads, no processes.

After OTP's `supervisor`: the restart type of a child and how it exited decide whether it
is restarted (`restarts_after`); the strategy decides which siblings go down and come
back with it (`affected`); the restart intensity decides when the supervisor gives up
(`RestartIntensity`, on an injectable clock).
"""

from __future__ import annotations

import collections
from collections.abc import Callable, Sequence

from rr_actors._core import runtime
from rr_actors.config import RestartType, Strategy

__all__ = ["Clock", "RestartIntensity", "affected", "restarts_after", "restarts_with_group"]

Clock = Callable[[], float]
"""A monotonic clock in seconds."""


class RestartIntensity:
    """OTP's restart intensity: at most `max_restarts` restarts within `period` seconds.

    Pure logic over an injectable clock (no threads).
    """

    def __init__(self, max_restarts: int, period: float, clock: Clock | None = None) -> None:
        self.max_restarts = max_restarts
        self.period = period
        self.clock = runtime.monotonic if clock is None else clock
        self._times: collections.deque[float] = collections.deque()

    def add(self) -> bool:
        """Count one restart now; return `False` if that exceeds the intensity (give up)."""
        now = self.clock()
        self._times.append(now)
        while self._times and now - self._times[0] >= self.period:
            self._times.popleft()
        return len(self._times) <= self.max_restarts

    @property
    def recent(self) -> int:
        """Restarts counted within the current window (this one included, after `add`)."""
        return len(self._times)


def restarts_after(restart: RestartType, *, normal: bool) -> bool:
    """Whether a child that exited on its own is restarted (OTP's restart types).

    Args:
        restart: `"permanent"` (always), `"transient"` (only after an abnormal exit: not
            after `normal` or `shutdown`) or `"temporary"` (never).
        normal: whether the exit was normal (`ManagerExit.normal`).
    """
    return restart == "permanent" or (restart == "transient" and not normal)


def restarts_with_group(restart: RestartType) -> bool:
    """Whether a sibling comes back when a crash restarts its group (one_for_all, rest_for_one).

    As in OTP, every child but a `temporary` one: a `transient` child that had exited
    normally is restarted with the group too (OTP keeps it in the child list; only
    temporary children are removed when they end).
    """
    return restart != "temporary"


def affected(strategy: Strategy, names: Sequence[str], crashed: str) -> tuple[str, ...]:
    """The children a crash of `crashed` takes down with it, in start order, itself included.

    Args:
        strategy: `"one_for_one"` (itself), `"one_for_all"` (every child) or
            `"rest_for_one"` (itself and the children started after it).
        names: every child's name, in start order.
        crashed: the child that crashed.
    """
    if strategy == "one_for_one":
        return (crashed,)
    if strategy == "one_for_all":
        return tuple(names)
    return tuple(names[names.index(crashed) :])
