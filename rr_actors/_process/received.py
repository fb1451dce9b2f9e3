"""What the parent received from one manager process: its events, in order, and those lost.

```
 manager process ── Events(batch) over the control pipe ──► Received.deliver ──► on_events
   ... it ends ──► Received.drain: what is still in the pipe
               ──► Received.count_lost: what its journal (`tally.Tally`) kept but it never
                   sent, then one EventsDropped(cause="killed") for what is still missing
```
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

from rr_actors._process.control import Events
from rr_actors._process.tally import Tally
from rr_actors.events import EventsDropped

__all__ = ["Received"]

logger = logging.getLogger("rr_actors")


class Received:
    """The events one manager process forwarded, to `on_events`; and those it lost.

    Keeps the number (`seq`) of the last event that arrived; after the exit, the
    process's `Tally` says how many it built, and the difference (the events a SIGKILL
    caught in its buffer) is published as one `EventsDropped(cause="killed")`.
    """

    def __init__(self, on_events: Callable[[list[Any]], None] | None, tally: Tally | None) -> None:
        self.on_events = on_events
        self.tally = tally
        self.last_seq = 0

    def deliver(self, name: str, batch: list[Any]) -> None:
        """Hand a batch to `on_events` (the watcher thread, or the starting thread)."""
        if self.on_events is None:
            return
        for event in reversed(batch):
            seq = getattr(event, "seq", 0)
            if seq:
                self.last_seq = max(self.last_seq, seq)
                break
        try:
            self.on_events(batch)
        except Exception:
            logger.exception("events of manager %s could not be delivered", name)

    def drain(self, name: str, conn: Connection) -> None:
        """Read what the process sent before it ended (still in the pipe): its last events.

        The exit can wake the watcher before the pipe's last messages are read.
        """
        for _ in range(10_000):  # bounded: the pipe holds what a dead process wrote
            try:
                if not conn.poll(0):
                    return
                message = conn.recv()
            except (EOFError, OSError, ValueError):
                return
            if isinstance(message, Events):
                self.deliver(name, message.batch)

    def close(self) -> None:
        """Remove the tally unread (a start given up): its events are not counted."""
        tally, self.tally = self.tally, None
        if tally is not None:
            tally.close()

    def count_lost(self, name: str, pid: int) -> None:
        """After the exit: deliver what its journal kept but it never sent; publish what
        is still missing (`EventsDropped(cause="killed")`); remove the tally."""
        tally = self.tally
        if tally is None:
            return
        self.tally = None
        try:
            arrived = self.last_seq
            kept = tally.after(arrived) if self.on_events is not None else []
            if kept:
                self.deliver(name, kept)
            # (a record written just before the kill may be newer than the number stored)
            last = max([tally.built(), *(getattr(e, "seq", 0) for e in kept)])
            lost = last - arrived - len(kept)
        finally:
            tally.close()
        if lost > 0 and self.on_events is not None:
            logger.warning("manager %s (pid %d) died with %d events unsent", name, pid, lost)
            self.deliver(name, [EventsDropped(lost, pid=pid, cause="killed")])
