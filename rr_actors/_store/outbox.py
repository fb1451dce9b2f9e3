"""The outbox: the events that tell of a change, written in the change's own transaction.

```
 registrar: a change, and the events that tell of it (`Shared.commit(*told)`)
   ──► Saver ──► SqliteStore.write: ONE transaction: the change's rows, and one `outbox`
       row per numbered event (`plan_told`: a ring of `SLOTS` rows, by the event's seq)
   ──► committed ──► the events are published (journal, forwarder: `_process/tally.py`)
 SIGKILL between the commit and the publish: the journal never had them, and no later
 event shows a gap ──► after the exit, the supervisor's side (`_process/received.py`):
   read_told(backup, pid) ──► the dead process's events it never received, delivered
   before its `ChildExited`
 the registrar's next start (`SqliteStore.open`) ──► `clear`: the outbox emptied
```

The transactional outbox pattern (C. Richardson, "Pattern: Transactional outbox",
microservices.io): a change and the message about it are committed together, and a
relay sends the message later. Here the relay is the journal for every event that was
published, and this table only for the ones a kill caught between commit and publish:
a row is never deleted when its event is sent (that would cost a write per event); the
ring overwrites it, and the reader skips what arrived by the event's number (`seq`).

Only numbered events are written (`seq` > 0: those of a manager process, whose
supervisor's side reads this table after its exit). A registrar in the caller's process
numbers none: it writes nothing here, and a kill of its process kills its subscribers too.

An event is stored as its JSON line (`rr_actors.events.to_dict`), read back with
`from_dict`: the supervisor's process reads the file, and nothing read from a file
runs code there (no unpickling).
"""

from __future__ import annotations

import json
import logging
import sqlite3
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from rr_actors import events
from rr_actors._store.files import read_only, validate
from rr_actors.errors import RrError

__all__ = ["SLOTS", "clear", "plan_told", "read_told"]

logger = logging.getLogger("rr_actors")

SLOTS = 256
"""Rows in the ring: an event's row is slot `seq % SLOTS`. A kill loses at most the events
of one commit; a commit that tells more than this many (a load answered to that many
waiters at once) keeps its last `SLOTS`, and a kill in its publishing counts the others
lost (`EventsDropped`), never silently."""

_INSERT = "INSERT OR REPLACE INTO outbox (slot, pid, seq, event) VALUES (?, ?, ?, ?)"

_VERSION = 7
"""The first schema version with an outbox (`schema._upgrade_v7`)."""


def plan_told(told: Iterable[events.Event], ops: list[tuple[str, tuple[Any, ...]]]) -> None:
    """Append the statements that write the numbered events of `told` to `ops`."""
    for event in told:
        seq = getattr(event, "seq", 0)
        if seq:
            line = json.dumps(events.to_dict(event), separators=(",", ":"))
            ops.append((_INSERT, (seq % SLOTS, event.pid, seq, line)))


def clear(db: sqlite3.Connection) -> None:
    """Empty the outbox (a registrar starts: its last run's rows were read at its exit).

    Raises:
        sqlite3.Error: the file cannot be written (the caller's to translate).
    """
    if db.execute("SELECT EXISTS (SELECT 1 FROM outbox)").fetchone()[0]:
        db.execute("DELETE FROM outbox")


def read_told(path: str | Path, pid: int) -> list[events.Event]:
    """The events process `pid` wrote in the outbox of backup `path`, by their `seq`.

    Read through a read-only connection after that process ended (its supervisor's side,
    before anything restarts it). Never raises: a file that cannot be read, one of a
    schema without an outbox, or a row that is not an event of this version, yields
    nothing for it (with a DEBUG line).
    """
    file = Path(path)
    try:
        if not file.is_file() or validate(file, tidy=True) < _VERSION:
            return []
        with read_only(file, tidy=True) as db:
            rows = db.execute(
                "SELECT seq, event FROM outbox WHERE pid = ? ORDER BY seq LIMIT ?", (pid, SLOTS)
            ).fetchall()
    except (OSError, sqlite3.Error, RrError) as exc:
        logger.debug("the outbox of %s cannot be read: %s", file, exc)
        return []
    found: list[events.Event] = []
    for seq, line in rows:
        try:
            event = events.from_dict(json.loads(line))
        except (TypeError, ValueError, RecursionError, RrError) as exc:
            logger.debug("outbox row %s of %s is not an event: %s", seq, file, exc)
            continue
        if getattr(event, "seq", 0) == seq and event.pid == pid:
            found.append(event)
    return found
