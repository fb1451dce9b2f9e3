"""Watching: what a supervisor does when one of its children's watchers reports an end.

```
 ThreadManager watcher: its registrar actor stopped ──────────────────────────┐
 ManagerProcess watcher (_process/manager.py): the process ended; or no       │
   heartbeat answer within `hang_after` (hung) / unhealthy ─► killed ─────────┼─► Exited(name,
 a nested Node gave up (Starting: escalate) ──────────────────────────────────┤   incarnation,
 a restart failed to start (Restarts.on_restart) ─────────────────────────────┘   exit)
   ──► mailbox ──► on_exited: stale (an older incarnation, or this one gave up)? dropped
                   else: the exit noted (ChildExited) ──► Restarts.after_exit
```

An incarnation stopped on purpose was bumped by `Stopping.stop_child` first, so its
watcher's report is stale here. Runs on the supervisor's thread; it holds no state of
its own: what it changes is the crashed child's record.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from rr_actors._supervision.children import NestedSupervisor
from rr_actors._supervision.record import Exited, pid_of

if TYPE_CHECKING:
    from rr_actors._supervision.record import Record
    from rr_actors._supervision.restarting import Restarts
    from rr_actors._supervision.stopping import Stopping

__all__ = ["Exits"]

logger = logging.getLogger("rr_actors")


class Exits:
    """Takes a child's reported end: drops a stale one, notes it, hands it to `Restarts`.

    Args:
        record: the supervisor whose children it watches.
        restarts: decides what comes next (and knows whether this supervisor gave up).
        stopping: notes the exit (`ChildExited`).
    """

    def __init__(self, record: Record, restarts: Restarts, stopping: Stopping) -> None:
        self.record = record
        self.restarts = restarts
        self.stopping = stopping

    def on_exited(self, event: Exited) -> None:
        """Child `event.name`'s incarnation `event.incarnation` ended with `event.exit`."""
        record = self.record
        child = next((c for c in record.children if c.name == event.name), None)
        if child is None or child.incarnation != event.incarnation or self.restarts.gave_up:
            return  # a stale event: that incarnation was stopped on purpose
        if isinstance(child.running, NestedSupervisor):
            nested = child.running.node
            child.gave_up = nested.gave_up
            nested.stop()  # it gave up: end its mailbox thread
        pid = pid_of(child)
        child.running = None
        child.last_exit = event.exit.reason
        self.stopping.note_exit(child, pid, event.exit.reason)
        logger.warning(
            "supervisor %s: child %s exited: %s", record.name, child.name, event.exit.reason
        )
        self.restarts.after_exit(child, event.exit)
