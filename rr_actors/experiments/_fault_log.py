"""The injector's record of what each fault did: fired (when, at what), or skipped (why).

```
 ManagerFaults, HostFaults, Injector (skips) ── record(fault, scheduled, injected, detail)
                                                  └─► records (FaultRecord, in order)
```

Written from several threads (the injector's, the trigger process's reader, a load
error's); its own state is the list and its lock.
"""

from __future__ import annotations

import logging
import threading

from rr_actors.experiments.results import FaultRecord
from rr_actors.experiments.schedule import ScheduledFault

__all__ = ["FaultLog"]

logger = logging.getLogger("rr_actors.experiments")


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
        """Record `fault` (any thread).

        Args:
            fault: the scheduled fault.
            scheduled: when it was due, seconds from the run's t0 (`None`: its trigger
                never came).
            injected: when it was fired, seconds from t0 (`None`: it was not).
            detail: what was done, or why not.
            target: what it struck, when not the fault's own target.
            skipped: it was not fired.
        """
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
