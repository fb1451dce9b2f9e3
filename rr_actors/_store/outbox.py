"""The outbox: the events that tell of a change, written in the change's own transaction.

```
 registrar: a change, and the events that tell of it (`Shared.commit(*told)`)
   ──► Saver ──► SqliteStore.write: ONE transaction: the change's rows, and one `outbox`
       row per numbered event (`plan_told`: a ring of `SLOTS` rows, by the event's seq)
   ──► committed ──► the events are published (journal, forwarder: `_process/tally.py`)
 SIGKILL between the commit and the publish: the journal never had them, and no later
 event shows a gap ──► after the exit, the supervisor's side (`_process/tally.py`, `Received`):
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

An event is stored as JSON text, `[schema, type, field values...]` (`to_dict`'s values
by position: a third of its cost), read back with `from_dict`, which checks every
field: the supervisor's process reads the file, and nothing read from a file runs code
there (no unpickling).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import operator
import sqlite3
import typing
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from rr_actors import events
from rr_actors._store.files import read_only, validate
from rr_actors.errors import RrError
from rr_actors.events.lines import SCHEMA

__all__ = ["SLOTS", "clear", "plan_told", "read_told"]

logger = logging.getLogger("rr_actors")

SLOTS = 256
"""Rows in the ring: an event's row is slot `seq % SLOTS`. A kill loses at most the events
of one commit; a commit that tells more than this many (a load answered to that many
waiters at once) keeps its last `SLOTS`, and a kill in its publishing counts the others
lost (`EventsDropped`), never silently."""

_INSERT = "INSERT OR REPLACE INTO outbox (slot, pid, seq, event) VALUES (?, ?, ?, ?)"

_encode = json.JSONEncoder(
    separators=(",", ":"), check_circular=False, default=lambda status: status.name
).encode
"""A row's JSON text (a `Status`, the one value JSON lacks, by its name, as `to_dict`)."""

_KINDS: dict[str, type[events.Event]] = {k.__name__: k for k in typing.get_args(events.Event)}


_FIELDS: dict[type[Any], tuple[tuple[str, ...], Callable[[Any], Any]]] = {}


def _fields(kind: type[Any]) -> tuple[tuple[str, ...], Callable[[Any], Any]]:
    """The field names of an event class, and a getter of their values (one C call)."""
    found = _FIELDS.get(kind)
    if found is None:
        names = tuple(field.name for field in dataclasses.fields(kind))
        found = _FIELDS[kind] = (names, operator.attrgetter(*names))
    return found


def _row(event: events.Event) -> str:
    """An event as its row: `[schema, type, field values...]` (issue 40: `to_dict` and
    its JSON took 13 us an event, twice the SQL of its row, on a loaded 2-core machine)."""
    _, values = _fields(type(event))
    return _encode([SCHEMA, type(event).__name__, *values(event)])


def _event(row: Any) -> events.Event:
    """The event of a row `_row` wrote; `ConfigError` (through `from_dict`) or
    `ValueError` if it is not one of this version."""
    if not isinstance(row, list) or len(row) < 2 or row[0] not in _ROWS_READ:
        raise ValueError("not a row of this version")
    kind = _KINDS.get(row[1]) if isinstance(row[1], str) else None
    if kind is None:
        raise ValueError(f"no event type {row[1]!r}")
    names, _ = _fields(kind)
    for schema, kinds in _ADDED.items():  # (without the fields added since: their defaults)
        if row[0] < schema and row[1] in kinds:
            names = tuple(name for name in names if name not in kinds[row[1]])
    if len(row) != len(names) + 2:
        raise ValueError(f"{len(row) - 2} values for the {len(names)} fields of {row[1]}")
    return events.from_dict(
        {"type": row[1], "schema": row[0], **dict(zip(names, row[2:], strict=True))}
    )


_ROWS_READ = (3, 4, 5, 6, 7, SCHEMA)
"""The event schemas of the rows read back (4 and 6 changed no event a registrar writes
here; 5, 7 and 8 added fields: `_ADDED`)."""

_CALL_ENDS = ("started", "trace", "caller_span")
_ADDED: dict[int, dict[str, tuple[str, ...]]] = {
    5: {"QueryForgotten": ("unload_sent", "reconciled")},
    7: {
        "QueryForgotten": ("trace", "caller_span"),
        "ConsumerAdded": ("trace",),
        "ConsumerReleased": ("trace",),
        "LoadFailed": ("trace",),
        "CallAnswered": _CALL_ENDS,
        "CallFailed": _CALL_ENDS,
        "CallWithdrawn": _CALL_ENDS,
    },
    8: {"ResourceLoaded": ("trace",)},
}
"""The fields each schema added to the events a registrar writes here, by their type: a
row of an older schema has no value for them."""


_VERSION = 7
"""The first schema version with an outbox (`schema._upgrade_v7`)."""


def plan_told(told: Iterable[events.Event], ops: list[tuple[str, tuple[Any, ...]]]) -> None:
    """Append the statements that write the numbered events of `told` to `ops`."""
    for event in told:
        seq = getattr(event, "seq", 0)
        if seq:
            line = _row(event)
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
            event = _event(json.loads(line))
        except (TypeError, ValueError, RecursionError, RrError) as exc:
            logger.debug("outbox row %s of %s is not an event: %s", seq, file, exc)
            continue
        if getattr(event, "seq", 0) == seq and event.pid == pid:
            found.append(event)
    return found
