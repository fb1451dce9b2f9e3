"""The faults that wait for an event of the run (`after = { event, match, nth }`).

```
 the run's subscriber thread ── on_event ──► matched(event): each waiting fault whose
   event and fields match counts it; at its n-th ──► (fault, event time + delay) ──►
   Injector schedules it
 Injector.stop / the loop failed ──► take(): those whose trigger never came
```

Its own state: the waiting faults with the matches seen so far, under its lock.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable
from typing import Any

from rr_actors import events
from rr_actors.experiments.schedule import ScheduledFault

__all__ = ["Triggered"]


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
