"""The injector's thread: actions kept in a heap by their monotonic time, run when due.

```
 push(at, action, fires) ──► heap of _Due(at, seq, action, fires) ──► the "rr-injector"
   (any thread; refused once stopped)                                  thread: timed wait
 wait_until(due): a timed wait, then a short spin (the last SPIN s)     to the earliest,
 stop() ──► the thread ends; the faults still in the heap are returned  then runs it
 the loop fails (a bug, an OverflowError) ──► on_failure(exc, faults still in the heap)
```

An action is a fault's preparation (`fires`: the fault and its due time from the run's
t0, so that what never ran can be recorded) or an undo (a hung manager resumed, a cut
healed). Its own state: the heap, the stopped flag and the thread.
"""

from __future__ import annotations

import dataclasses
import heapq
import itertools
import logging
import threading
import time
from collections.abc import Callable

from rr_actors.experiments.schedule import ScheduledFault

__all__ = ["SPIN", "Agenda", "Fires"]

logger = logging.getLogger("rr_actors.experiments")

SPIN = 0.0003
"""The last seconds before a fault fired from this process (a thread manager's crash, a
load error's switch) are waited by spinning, not by a timed wait."""

Fires = tuple[ScheduledFault, float]
"""A fault's firing: the fault, and its due time in seconds from the run's t0."""


@dataclasses.dataclass(order=True)
class _Due:
    at: float  # monotonic
    seq: int
    action: Callable[[], None] = dataclasses.field(compare=False)
    # A fault's firing (not a hung manager's resumption): `(fault, due time from t0)`.
    fires: Fires | None = dataclasses.field(default=None, compare=False)


class Agenda:
    """Runs actions at their monotonic times, one at a time, on a thread of its own.

    Args:
        on_failure: called on the agenda's thread if its loop fails, with the error and
            the firings still due (in time order); the thread then ends.
    """

    def __init__(self, on_failure: Callable[[Exception, list[Fires]], None]) -> None:
        self._on_failure = on_failure
        self._cond = threading.Condition(threading.Lock())
        self._heap: list[_Due] = []
        self._seq = itertools.count()
        self._stopped = False
        self._thread = threading.Thread(target=self._loop, name="rr-injector", daemon=True)

    def start(self) -> None:
        """Start the thread."""
        self._thread.start()

    def stop(self, timeout: float) -> list[Fires]:
        """Stop running actions; the firings that did not run. Waits up to `timeout`
        seconds for the thread (an action under way ends first)."""
        with self._cond:
            self._stopped = True
            self._cond.notify_all()
            unfired = [due.fires for due in self._heap if due.fires is not None]
            self._heap = []
        if self._thread.ident is not None:
            self._thread.join(timeout)
        return unfired

    def push(self, at: float, action: Callable[[], None], fires: Fires | None = None) -> bool:
        """Run `action` at monotonic time `at` (any thread); `False`: stopped, it won't."""
        with self._cond:
            if self._stopped:
                return False
            heapq.heappush(self._heap, _Due(at, next(self._seq), action, fires))
            self._cond.notify_all()
        return True

    def wait_until(self, due: float) -> None:
        """Return at monotonic time `due` (a timed wait, then a short spin), or at once
        when stopped."""
        while True:
            left = due - time.monotonic()
            if left <= 0:
                return
            if left > SPIN:
                with self._cond:
                    if self._stopped:
                        return
                    self._cond.wait(left - SPIN)

    def _loop(self) -> None:
        try:
            self._run_when_due()
        except Exception as exc:  # a bug, or a wait too long for `threading` (OverflowError)
            with self._cond:
                left, self._heap = sorted(self._heap), []
            # (a hang's resume is not a fault: stop() resumes every hung manager)
            self._on_failure(exc, [due.fires for due in left if due.fires is not None])
            logger.exception("the injector stopped")

    def _run_when_due(self) -> None:
        while True:
            with self._cond:
                while not self._stopped:
                    if self._heap:
                        wait = self._heap[0].at - time.monotonic()
                        if wait <= 0:
                            break
                        self._cond.wait(wait)
                    else:
                        self._cond.wait()
                if self._stopped:
                    return
                due = heapq.heappop(self._heap)
            try:
                due.action()
            except Exception:
                logger.exception("the injector failed to fire a fault")
