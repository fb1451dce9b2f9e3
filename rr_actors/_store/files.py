"""Where a backup lives: the path's checks, creating, validating and opening the file.

```
 backup_path --check_location--> (no file) --create: temporary name, linked into place-->
   --validate: header, read-only connection, schema--> --prepare: WAL, durability, migrate-->
   a writable connection (`SqliteStore`)
 read_backup: validate, then read every row through a read-only connection (inspection)
 quarantine_backup: rename the file and its companions aside (the one way to give one up)
```

A new file is built under a temporary name and linked into place complete, so the backup
path either does not exist or holds a whole catalog. An existing file is validated
through a read-only connection before anything writes to it; whatever is wrong raises
`CatalogCorruptError` (or `ConfigError` for an unusable path) and leaves it untouched.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import os
import sqlite3
import uuid
from collections.abc import Iterator
from pathlib import Path

from rr_actors._catalog import ClientRecord, Resource
from rr_actors._store import schema
from rr_actors._store.codec import as_corrupt, lenient_decode
from rr_actors._store.restore import gc_paused, read_rows
from rr_actors.errors import CatalogCorruptError, ConfigError

__all__ = [
    "SIDE_FILES",
    "SYNCHRONOUS",
    "Backup",
    "check_location",
    "connect",
    "create",
    "prepare",
    "quarantine_backup",
    "read_backup",
    "validate",
]

_HEADER = b"SQLite format 3\x00"

SIDE_FILES = ("-wal", "-shm", "-journal")
"""The suffixes of the files SQLite keeps next to a database."""

SYNCHRONOUS = {"process": "NORMAL", "power": "FULL"}
"""SQLite's `synchronous` level for each `RegistrarConfig.durability`."""


def check_location(path: Path) -> None:
    """Raise `ConfigError` if `path` cannot hold a backup."""
    if path.is_dir():
        raise ConfigError(f"backup_path {str(path)!r} is a directory, not a file")
    parent = path.parent
    if not parent.is_dir():
        raise ConfigError(f"backup_path {str(path)!r}: directory {str(parent)!r} does not exist")
    if path.exists() and not os.access(path, os.R_OK | os.W_OK):
        raise ConfigError(f"backup_path {str(path)!r} is not readable and writable")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(
            f"backup_path {str(path)!r}: directory {str(parent)!r} is not writable "
            f"(SQLite needs to create its -wal and -shm files there)"
        )


def connect(path: Path, *, read_only: bool) -> sqlite3.Connection:
    if read_only:
        uri = f"{path.resolve().as_uri()}?mode=ro"
        db = sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=False)
    else:
        db = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
    return db


def _file_problem(path: Path) -> str | None:
    """What is wrong with the file itself, judged from its header (or `None`)."""
    size = path.stat().st_size
    if size == 0:
        return "the file is empty (an rr_actors catalog is never empty)"
    with path.open("rb") as file:
        header = file.read(100)
    if not header.startswith(_HEADER):
        return f"not an SQLite database (starts with {header[:16]!r})"
    if len(header) < 100:
        return f"truncated: {size} bytes, shorter than an SQLite header"
    page_size = int.from_bytes(header[16:18], "big")
    page_size = 65536 if page_size == 1 else page_size
    pages = int.from_bytes(header[28:32], "big")
    change_counter, valid_for = header[24:28], header[92:96]
    if change_counter == valid_for and pages and pages * page_size > size and not _has_log(path):
        return f"truncated: {size} bytes, its header says {pages} pages of {page_size} bytes"
    return None


def _has_log(path: Path) -> bool:
    """Whether a non-empty WAL lies next to `path`.

    A checkpoint copies the log's pages in page order, page 1 (the header, with the new
    page count) first: a process killed during one that grows the file leaves it shorter
    than its header says, and SQLite completes it from the log when it is next opened.
    """
    try:
        return Path(f"{path}-wal").stat().st_size > 0
    except OSError:
        return False


def create(path: Path) -> None:
    """Build an empty catalog under a temporary name, then link it into place.

    The backup path therefore never holds a half-created file. If another process
    created it first, that file wins (and is validated like any existing file).
    """
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.creating")
    try:
        db = sqlite3.connect(tmp, isolation_level=None)
    except sqlite3.Error as exc:
        raise ConfigError(f"backup_path {str(path)!r} cannot be created: {exc}") from exc
    try:
        db.execute(f"PRAGMA application_id = {schema.APPLICATION_ID}")
        schema.migrate(db, 0)
        db.execute("PRAGMA journal_mode = WAL")
        db.close()
        with contextlib.suppress(FileExistsError):
            os.link(tmp, path)
    except (sqlite3.Error, OSError) as exc:
        raise ConfigError(f"backup_path {str(path)!r} cannot be created: {exc}") from exc
    finally:
        db.close()
        for suffix in ("", *SIDE_FILES):
            with contextlib.suppress(FileNotFoundError):
                Path(f"{tmp}{suffix}").unlink()


@contextlib.contextmanager
def _read_only(path: Path, *, tidy: bool) -> Iterator[sqlite3.Connection]:
    """A read-only connection; with `tidy`, remove the `-wal`/`-shm` files it created.

    A read-only connection to a WAL-mode file creates those files but cannot delete
    them; an empty `-wal` holds nothing, so removing what we created changes nothing.
    """
    existed = {suffix: Path(f"{path}{suffix}").exists() for suffix in ("-wal", "-shm")}
    db = connect(path, read_only=True)
    try:
        yield db
    finally:
        db.close()
        wal = Path(f"{path}-wal")
        if tidy and not existed["-wal"] and wal.exists() and wal.stat().st_size == 0:
            for suffix in ("-wal", "-shm"):
                if not existed[suffix]:
                    with contextlib.suppress(FileNotFoundError):
                        Path(f"{path}{suffix}").unlink()


def validate(path: Path, *, tidy: bool) -> int:
    """Check an existing file without writing to it; return its schema version."""
    name = str(path)
    problem = _file_problem(path)
    if problem is not None:
        raise CatalogCorruptError(name, problem)
    with as_corrupt(name), _read_only(path, tidy=tidy) as db:
        return schema.schema_version(db, name)


def prepare(db: sqlite3.Connection, name: str, durability: str, version: int) -> None:
    """Check that `db` is writable, switch on WAL and the durability, migrate it."""
    try:
        db.execute("BEGIN IMMEDIATE")  # can we write here at all?
        db.execute("ROLLBACK")
    except sqlite3.OperationalError as exc:
        raise ConfigError(f"backup_path {name!r} is not writable: {exc}") from exc
    with as_corrupt(name):
        mode = db.execute("PRAGMA journal_mode = WAL").fetchone()[0]
    if mode != "wal":  # before anything is written: an older file stays as it was
        raise ConfigError(f"backup_path {name!r}: SQLite cannot use WAL mode there ({mode})")
    with as_corrupt(name):
        db.execute(f"PRAGMA synchronous = {SYNCHRONOUS[durability]}")
        schema.migrate(db, version)
    schema.refresh_digests(db, name)


@dataclasses.dataclass(frozen=True)
class Backup:
    """The content of a catalog backup, as `read_backup` returns it.

    Attributes:
        path: the file.
        schema_version: its schema version.
        resources: served resources, oldest first (consumers in arrival order).
        clients: client records, oldest first.
    """

    path: str
    schema_version: int
    resources: list[Resource]
    clients: list[ClientRecord]


def read_backup(path: str | os.PathLike[str]) -> Backup:
    """Read a catalog backup without changing it (it may belong to a running registrar).

    A file of an older schema version is copied into memory and migrated there; the file
    itself is never migrated by reading it.

    Stored requests and responses that cannot be unpickled in this process (their
    classes are not importable here) come back as `Unreadable` placeholders. Unpickling
    runs code from the file: only read backups you trust.

    Args:
        path: the backup file.

    Returns:
        Its rows and schema version.

    Raises:
        ConfigError: `path` does not exist or is not a file.
        CatalogCorruptError: the file is not a readable rr_actors catalog.
    """
    file = Path(os.fspath(path))
    if not file.is_file():
        raise ConfigError(f"no catalog backup at {str(file)!r}")
    version = validate(file, tidy=True)
    name = str(file)
    with as_corrupt(name), _read_only(file, tidy=True) as db:
        check = db.execute("PRAGMA quick_check").fetchall()
        if check != [("ok",)]:
            raise CatalogCorruptError(name, f"integrity check failed: {check[:5]!r}")
        with _migrated_copy(db, version) as current, gc_paused():
            rows = read_rows(current, lenient_decode, lenient=True)
    return Backup(name, version, rows.resources, rows.clients)


@contextlib.contextmanager
def _migrated_copy(db: sqlite3.Connection, version: int) -> Iterator[sqlite3.Connection]:
    """`db` itself if it has the current schema, else a migrated copy in memory.

    An older file is read as the code reads a current one, without writing to it.
    """
    if version == schema.SCHEMA_VERSION:
        yield db
        return
    copy = sqlite3.connect(":memory:", isolation_level=None)
    try:
        db.backup(copy)
        schema.migrate(copy, version)
        yield copy
    finally:
        copy.close()


def quarantine_backup(path: str | os.PathLike[str]) -> Path:
    """Move a catalog backup that cannot be used out of the way, keeping it for analysis.

    The file (and its `-wal`/`-shm` companions) is renamed to
    `<path>.corrupt-<UTC timestamp>`; a registrar started on `path` afterwards starts with
    an empty catalog. This is the one explicit way to give up a backup: rr_actors never
    does it on its own. Only call it while no registrar uses the file.

    Args:
        path: the backup file, as in `RegistrarConfig.backup_path`.

    Returns:
        The new path of the quarantined file.

    Raises:
        ConfigError: there is no file at `path`.
    """
    file = Path(os.fspath(path))
    if not file.is_file():
        raise ConfigError(f"no catalog backup to quarantine at {str(file)!r}")
    stamp = datetime.datetime.now(datetime.UTC).strftime("%Y%m%dT%H%M%S.%fZ")
    target = file.with_name(f"{file.name}.corrupt-{stamp}")
    for suffix in SIDE_FILES:  # companions first: the main file's name is the anchor
        side = Path(f"{file}{suffix}")
        if side.exists():
            side.rename(f"{target}{suffix}")
    file.rename(target)
    return target
