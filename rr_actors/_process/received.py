"""What the parent received from one manager process: its events, in order, and those lost.

```
 manager process ── Events(batch) over the control pipe ──► Received.deliver ──► on_events
   ... it ends ──► Received.drain: what is still in the pipe
               ──► Received.count_lost: what it never sent, from what outlives it:
                   its journal (`tally.Tally`: every event it published) and its
                   registrar's backup (`_store/outbox.py`: the events of its last
                   commits, written with them, which a kill before their publishing
                   kept from the journal); then one EventsDropped(cause="killed") for
                   what is still missing
```
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

from rr_actors._process.control import Events
from rr_actors._process.tally import Tally
from rr_actors._store.outbox import read_told
from rr_actors.events import EventsDropped

__all__ = ["HOLES", "Received"]

logger = logging.getLogger("rr_actors")

HOLES = 4096
"""Numbers below the last one that arrived and are still missing, kept at most (events
built on two threads may be sent out of order; one its outbox holds is delivered)."""


class Received:
    """The events one manager process forwarded, to `on_events`; and those it lost.

    Keeps the number (`seq`) of the last event that arrived and the numbers below it
    still missing; after the exit, the process's `Tally` and its registrar's outbox
    give back what it never sent, and the rest (the events a SIGKILL caught in its
    buffer) is published as one `EventsDropped(cause="killed")`.

    Args:
        on_events: where the batches go (`None`: nowhere; nothing is counted).
        tally: the process's journal (`None`: none could be made).
        backup: its registrar's backup file (`None`: it has none), an absolute path.
    """

    def __init__(
        self,
        on_events: Callable[[list[Any]], None] | None,
        tally: Tally | None,
        backup: str | None = None,
    ) -> None:
        self.on_events = on_events
        self.tally = tally
        self.backup = backup
        self.last_seq = 0
        self.holes: set[int] = set()

    def deliver(self, name: str, batch: list[Any]) -> None:
        """Hand a batch to `on_events` (the watcher thread, or the starting thread)."""
        if self.on_events is None:
            return
        last, holes = self.last_seq, self.holes
        for event in batch:
            seq = _seq(event)
            if seq > last:
                if seq > last + 1 and len(holes) < HOLES:
                    holes.update(range(last + 1, min(seq, last + 1 + HOLES - len(holes))))
                last = seq
            elif seq:
                holes.discard(seq)
        self.last_seq = last
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
        """After the exit: deliver what its journal and its outbox kept but it never sent;
        publish what is still missing (`EventsDropped(cause="killed")`); remove the tally.

        Call it before anything restarts the manager (its next start empties the outbox).
        """
        tally = self.tally
        if tally is None or self.on_events is None:
            self.close()
            return
        self.tally = None
        try:
            arrived = self.last_seq
            kept = tally.after(arrived)
            # (a record written just before the kill may be newer than the number stored)
            last = max([tally.built(), *(_seq(e) for e in kept)])
        finally:
            tally.close()
        seen = {_seq(e) for e in kept}
        told = [
            event
            for event in (read_told(self.backup, pid) if self.backup is not None else ())
            if (_seq(event) > arrived or _seq(event) in self.holes) and _seq(event) not in seen
        ]
        if told:  # committed, then killed before their publishing: the journal lacks them
            last = max(last, *(_seq(e) for e in told))
            kept = sorted([*kept, *told], key=_seq)
        if kept:
            self.deliver(name, kept)
        lost = last - arrived - sum(1 for e in kept if _seq(e) > arrived)
        if lost > 0:
            logger.warning("manager %s (pid %d) died with %d events unsent", name, pid, lost)
            self.deliver(name, [EventsDropped(lost, pid=pid, cause="killed")])


def _seq(event: Any) -> int:
    """An event's number in its process (0: it has none)."""
    seq: int = getattr(event, "seq", 0)
    return seq
