"""The damage a `corrupt_backup` fault does to a killed manager's backup, before its restart.

```
 corrupt_backup: SIGKILL the manager ──► damage(<state_dir>/<manager>.db, how, noise)
   (but delete: its -wal written into it first, its side files gone, as a clean close)
   delete    the file and its companions (-wal, -shm, -journal) removed
   truncate  the file cut to a length drawn below its size
   flip      the header's application id (bytes 68-71) XORed with a drawn nonzero mask
   foreign   a view added to its schema (an object rr_actors never creates)
   digests   its digests made another scheme's (`DIGEST_SCHEME`: another Python's), as a
             backup moved from another machine: not damage, its restart restores it whole
 the restart: digests ──► it restores every row, each digest recomputed (`kept`);
   delete ──► it starts empty; the others ──► refused, `CatalogCorruptError`
   naming the file ──► the lab quarantines it (`quarantine_backup`), as the docs tell an
   operator ──► the next restart starts empty
```

What the product promises of each: "What the backup survives" and "Who may see a backup",
docs/explanation/failure-semantics.md; the rule that judges it: `damaged-backup`
(`_supervision_rules.damaged_backup`). The draws are the caller's `noise` (the simulation's
`runtime.urandom`: the same seed damages the same bytes).
"""

from __future__ import annotations

import re
import sqlite3
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from rr_actors._store.files import SIDE_FILES, remove_files

if TYPE_CHECKING:
    from rr_actors_lab.experiments.plan import Plan
    from rr_actors_lab.experiments.results import FaultRecord

__all__ = ["CORRUPT", "KEPT", "NOISE_BYTES", "REFUSED", "damage", "damaged"]

CORRUPT = "cannot be used: "
"""What a `CatalogCorruptError`'s message says (`catalog backup '<path>' cannot be used: ...`),
as a refused start's `ChildExited.reason` carries it."""

NOISE_BYTES = 8
"""The drawn bytes `damage` takes."""

REFUSED = frozenset({"truncate", "flip", "foreign"})
"""The damage a restart must refuse with `CatalogCorruptError` (a deleted file: it starts
empty)."""

KEPT = frozenset({"digests"})
"""What a restart must restore whole (`kept` judges it: no `damaged-backup` rule)."""

_KILLED = re.compile(r"SIGKILL pid (\d+), then ")  # a record of a fault that damaged a file

_APPLICATION_ID = slice(68, 72)  # of an SQLite header: `PRAGMA application_id`


def damage(file: Path, how: str, noise: bytes) -> str:
    """Damage the backup `file` (closed: its process was killed) as `how` says; what was
    done, for people. `noise`: `NOISE_BYTES` drawn bytes. Raises `OSError`,
    `sqlite3.Error`."""
    if how == "delete":
        remove_files(file)
        return f"deleted {file.name} and its companions"
    _checkpoint(file)  # (the log's pages in the file: SQLite would read page 1 from it)
    if how == "truncate":
        size = file.stat().st_size
        cut = int.from_bytes(noise, "big") % max(size, 1)
        with file.open("r+b") as opened:
            opened.truncate(cut)
        return f"cut {file.name} from {size} to {cut} bytes"
    if how == "flip":
        mask = int.from_bytes(noise[:4], "big") or 1
        with file.open("r+b") as opened:
            opened.seek(_APPLICATION_ID.start)
            was = int.from_bytes(opened.read(4), "big")
            opened.seek(_APPLICATION_ID.start)
            opened.write((was ^ mask).to_bytes(4, "big"))
        return f"flipped {file.name}'s application id (mask {mask:#010x})"
    if how == "digests":
        older = "rr4-aa" if noise[4] % 2 else "rr4-zz"  # (sorting before or after this one's)
        db = sqlite3.connect(file, isolation_level=None)
        try:
            db.execute("UPDATE rr_actors_schema SET digest_scheme = ?", (older,))
            db.execute("UPDATE resources SET digest = ~digest")
        finally:
            db.close()
        return f"made {file.name}'s digests another scheme's ({older!r})"
    assert how == "foreign", how
    db = sqlite3.connect(file, isolation_level=None)
    try:
        db.execute("CREATE VIEW rr_lab_foreign AS SELECT 1")
    finally:
        db.close()
    return f"added a view to {file.name}'s schema"


def _checkpoint(file: Path) -> None:
    """Write the file's -wal into it and remove its side files (the last connection's
    close checkpoints)."""
    db = sqlite3.connect(file, isolation_level=None)
    try:
        db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    finally:
        db.close()
    remove_files(file, SIDE_FILES)


def damaged(plan: Plan, records: Iterable[FaultRecord]) -> dict[int, str]:
    """The run's damaged backups for `check` (`damaged-backup`): the pid each
    `corrupt_backup` killed -> its `how` (those that damaged a file only)."""
    found: dict[int, str] = {}
    for record in records:
        killed = _KILLED.match(record.detail) if record.kind == "corrupt_backup" else None
        how = plan.faults[record.fault].how
        if killed is not None and not record.skipped and how not in KEPT:
            found[int(killed.group(1))] = how
    return found
