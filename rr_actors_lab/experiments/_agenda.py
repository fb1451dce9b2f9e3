"""The injector's timetable: when each fault fires (at a time, or after the n-th matching
event of the run), and what each did.

```
 timed faults (the Injector, at its start) ───────────────┐
 on_event (the run's subscriber thread) ──► Triggered:    │
   each waiting fault whose event and fields match        ├──► Agenda.push(at, action, fires)
   counts it; at its n-th ──► (fault, event time + delay) ┘    (any thread; refused once
                                                                stopped): a heap of _Due
   the "rr-injector" thread: a timed wait to the earliest, then runs it ◄────────────┘
 ManagerFaults, HostFaults, Injector (skips) ── FaultLog.record ──► records (in order)
 stop ──► Agenda.stop: the firings still due; Triggered.take: the faults whose trigger
          never came ──► the Injector records both as skipped
 the loop fails (a bug, an OverflowError) ──► on_failure(exc, the firings still due)
```

An action is a fault's preparation (`fires`) or an undo; `wait_until(due)` is a timed wait,
then a spin of the last `SPIN` s. A simulated run keeps its own agenda in virtual time and
uses `Triggered` and `FaultLog` as they are. Each class keeps its state under its own lock.
"""

from __future__ import annotations

import dataclasses
import heapq
import itertools
import logging
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

from rr_actors import events
from rr_actors_lab.experiments.results import FaultRecord
from rr_actors_lab.experiments.schedule import ScheduledFault

__all__ = ["SPIN", "Agenda", "FaultLog", "Fires", "Triggered"]

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


class Triggered:
    """Counts the run's events for the faults that wait for one.

    Args:
        faults: the faults that wait for an event (their `at` is `None`).
        wall_t0: the wall-clock time (`time.time()`) of the run's t0.
    """

    def __init__(self, faults: Iterable[ScheduledFault], wall_t0: float) -> None:
        self._lock = threading.Lock()
        self._wall_t0 = wall_t0
        self._waiting: list[list[Any]] = [[fault, 0] for fault in faults]  # [fault, seen]

    def matched(self, event: events.Event) -> list[tuple[ScheduledFault, float]]:
        """The faults `event` triggers, each with its due time in seconds from t0; they
        wait no more (any thread)."""
        if not self._waiting:  # no trigger left: the common case, without the lock
            return []
        name = type(event).__name__
        due: list[tuple[ScheduledFault, float]] = []
        with self._lock:
            for entry in self._waiting:
                fault, seen = entry
                trigger = fault.trigger
                if trigger.event != name or any(
                    getattr(event, key, None) != value for key, value in trigger.match.items()
                ):
                    continue
                entry[1] = seen + 1
                if entry[1] == trigger.nth:
                    # The event's own time, not its arrival: events of manager processes
                    # arrive in batches, a little after they happened.
                    due.append((fault, event.at - self._wall_t0 + fault.delay))
            fired = {id(f) for f, _ in due}
            self._waiting = [e for e in self._waiting if id(e[0]) not in fired]
        return due

    def take(self) -> list[ScheduledFault]:
        """The faults still waiting, which wait no more."""
        with self._lock:
            waiting, self._waiting = self._waiting, []
        return [fault for fault, _ in waiting]


class FaultLog:
    """Every fault fired or skipped so far, in the order they were recorded."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.records: list[FaultRecord] = []
        """Every fault fired or skipped so far (appended by several threads)."""

    def record(
        self,
        fault: ScheduledFault,
        scheduled: float | None,
        injected: float | None,
        detail: str,
        *,
        target: str | None = None,
        skipped: bool = False,
    ) -> None:
        """Record `fault` (any thread): `scheduled` and `injected` in seconds from the run's t0
        (`None`: its trigger never came / it was not fired), `detail` what was done or why not,
        `target` what it struck when not the fault's own."""
        record = FaultRecord(
            fault=fault.fault,
            n=fault.n,
            kind=fault.kind,
            target=target if target is not None else fault.target,
            scheduled_s=scheduled,
            injected_s=injected,
            detail=detail,
            skipped=skipped,
        )
        with self._lock:
            self.records.append(record)
        logger.info("fault %s: %s", fault.kind, detail)
