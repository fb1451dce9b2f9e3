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
 the registrar's next start (`files.open_backup`) ──► the outbox emptied
```

The transactional outbox pattern (C. Richardson, "Pattern: Transactional outbox",
microservices.io); why: "What a SIGKILL can and cannot lose of the event stream",
docs/explanation/failure-semantics.md. A row is never deleted when its event is sent (the
ring overwrites it); only numbered events (a manager process's) are written, as JSON
`[schema, type, field values...]`, read back with `from_dict` (nothing read from a file
runs code: no unpickling).
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
from rr_actors._store.files import read_only
from rr_actors.errors import RrError
from rr_actors.events.lines import SCHEMA

logger = logging.getLogger("rr_actors")

SLOTS = 256
"""Rows in the ring (slot `seq % SLOTS`); a commit that tells more keeps its last `SLOTS`."""

_INSERT = "INSERT OR REPLACE INTO outbox (slot, pid, seq, event) VALUES (?, ?, ?, ?)"

_encode = json.JSONEncoder(
    separators=(",", ":"), check_circular=False, default=lambda status: status.name
).encode  # (a `Status`, the one value JSON lacks, by its name, as `to_dict`)

_KINDS: dict[str, type[events.Event]] = {k.__name__: k for k in typing.get_args(events.Event)}


_FIELDS: dict[type[Any], tuple[tuple[str, ...], Callable[[Any], Any]]] = {}


def _fields(kind: type[Any]) -> tuple[tuple[str, ...], Callable[[Any], Any]]:
    found = _FIELDS.get(kind)
    if found is None:
        names = tuple(field.name for field in dataclasses.fields(kind))
        found = _FIELDS[kind] = (names, operator.attrgetter(*names))
    return found


def _row(event: events.Event) -> str:
    _, values = _fields(type(event))
    return _encode([SCHEMA, type(event).__name__, *values(event)])


def _event(row: Any) -> events.Event:
    """The event of a row `_row` wrote (`ConfigError`, `ValueError`: not of this version)."""
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


_ROWS_READ = (3, 4, 5, 6, 7, 8, SCHEMA)  # the event schemas read back

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
    9: {"ShareRefused": ("since", "waiting", "firsts")},
}  # the fields each event schema added (an older row has no value for them)


def plan_told(told: Iterable[events.Event], ops: list[tuple[str, tuple[Any, ...]]]) -> None:
    for event in told:
        seq = getattr(event, "seq", 0)
        if seq:
            line = _row(event)
            ops.append((_INSERT, (seq % SLOTS, event.pid, seq, line)))


def read_told(path: str | Path, pid: int) -> list[events.Event]:
    """The events process `pid` wrote in the outbox of backup `path`, by their `seq` (read
    only, after it ended, on one connection and with no schema check: on the exit's path;
    never raises: what cannot be read, a backup older than the outbox too, yields nothing)."""
    file = Path(path)
    try:
        if not file.is_file():
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
