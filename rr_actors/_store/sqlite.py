"""The catalog backup: an embedded SQLite database (DESIGN.md rules 13-16).

One file per registrar, in WAL mode. Every `write` is one transaction, so a crash at any
instant leaves the old or the new catalog, never a torn one. A write touches only the
rows that changed (the store keeps a small mirror of what it wrote to compute the
difference), so its cost does not grow with the catalog.

Layout (schema version 3):

* `rr_actors_schema(version, digest_scheme)`: one row, the schema version and the
  `DIGEST_SCHEME` of the stored digests; `PRAGMA application_id` marks the file as an
  rr_actors catalog.
* `resources(seq, id, server, state, digest, request, response)`: served resources, `seq`
  being the insertion order, `state` 0/1/2 (loading/loaded/unloading), `digest` the
  request's `request_digest` (`NULL` if it has none). Indexed by `id` (unique), by
  `(server, digest)`, and (partial index) the rows not loaded or without a digest.
* `consumers(resource, seq, query_id, origin_rr)`: consumer ids, `resource` being the `seq`
  of their resource; clustered by `(resource, seq)` (`WITHOUT ROWID`), so a scan yields
  each resource's consumers together, in arrival order, and adding or removing one
  writes one page.
* `clients(seq, query_id, server, serving_rr, origin_rr, request, response, parent,
  loaded)`: outbound queries (`parent` set for dependencies).

Restoring does not read every row (`SqliteStore.restore`): the consumer ids are read as
four column strings by one aggregate query, the resources in doubt (or without a digest,
or owning a dependency) and the client records as rows; every other resource is read
when the catalog first looks it up, through the indexes. So a restart costs a fraction of
a full read, and an index is written only when a resource is added or removed, never
when a consumer id is.

Requests and responses are stored with cloudpickle (`NULL` for `None`). The stored digest
is deterministic (BLAKE2b of strings, numbers' own `hash()`), never the per-process
`hash()` of a string, so a restore indexes every resource from its digest alone and
leaves its request and response encoded until first used. A file whose digests were
written under another `DIGEST_SCHEME` (another Python version or word size) has them
recomputed, in one transaction, when it is opened.

Reading validates cheaply what it does not decode: every stored value must look like a
whole pickle (protocol header, final STOP opcode), every state code must be known, and no
resource id, consumer query id or client query id may appear twice. A resource row is
validated when it is read, so a damaged row a restore left on disk raises
`CatalogCorruptError` (naming the file and the resource) when it is first used, as does a
value that passes and still cannot be decoded (its class is not importable here).

A new file is built under a temporary name and linked into place complete, so the backup
path either does not exist or holds a whole catalog. An existing file is validated
through a read-only connection before anything writes to it; whatever is wrong raises
`CatalogCorruptError` (or `ConfigError` for an unusable path) and leaves it untouched.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import functools
import gc
import logging
import os
import pickle
import sqlite3
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Literal

import cloudpickle

from rr_actors._catalog import (
    DIGEST_SCHEME,
    NO_DIGEST,
    Changes,
    ClientRecord,
    Resource,
    ResourceState,
    request_digest,
)
from rr_actors._platform import PLATFORM
from rr_actors._types import Query
from rr_actors.errors import CatalogCorruptError, ConfigError, RegistrarStoppedError

__all__ = [
    "APPLICATION_ID",
    "SCHEMA_VERSION",
    "Backup",
    "SqliteStore",
    "Unreadable",
    "gc_paused",
    "quarantine_backup",
    "read_backup",
]

logger = logging.getLogger("rr_actors")


@contextlib.contextmanager
def gc_paused() -> Iterator[None]:
    """Pause the cyclic garbage collector while a catalog is built (restores twice as fast).

    Building 100k rows allocates many containers and no cycles; each allocation burst
    would otherwise trigger collections that rescan every object built so far.
    """
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


APPLICATION_ID = 0x72724163  # "rrAc"
"""`PRAGMA application_id` of every rr_actors catalog file."""

SCHEMA_VERSION = 3
"""The schema version this code writes; older files are migrated, newer ones refused."""

_HEADER = b"SQLite format 3\x00"
_SIDE_FILES = ("-wal", "-shm", "-journal")

_SYNCHRONOUS = {"process": "NORMAL", "power": "FULL"}


def _create_v1(db: sqlite3.Connection) -> None:
    db.execute("CREATE TABLE rr_actors_schema (version INTEGER NOT NULL)")
    db.execute("INSERT INTO rr_actors_schema (version) VALUES (0)")
    db.execute(
        "CREATE TABLE resources (seq INTEGER PRIMARY KEY, id TEXT NOT NULL, "
        "server TEXT NOT NULL, state TEXT NOT NULL, request BLOB, response BLOB)"
    )
    db.execute(
        "CREATE TABLE consumers (seq INTEGER PRIMARY KEY, query_id TEXT NOT NULL, "
        "resource_id TEXT NOT NULL, origin_rr TEXT NOT NULL)"
    )
    db.execute(
        "CREATE TABLE clients (seq INTEGER PRIMARY KEY, query_id TEXT NOT NULL, "
        "server TEXT NOT NULL, serving_rr TEXT NOT NULL, origin_rr TEXT NOT NULL, "
        "request BLOB, response BLOB, parent TEXT, loaded INTEGER NOT NULL)"
    )


_STATE_CODES = {ResourceState.LOADING: 0, ResourceState.LOADED: 1, ResourceState.UNLOADING: 2}
_STATES_BY_CODE = tuple(_STATE_CODES)


def _upgrade_v2(db: sqlite3.Connection) -> None:
    """v1 -> v2: a digest column, integer states, consumers keyed by their resource's row.

    The digests are filled in by `_refresh_digests` (the scheme is still `NULL`). A row
    with an unknown state or a consumer of a missing resource violates `NOT NULL`.
    """
    db.execute("ALTER TABLE rr_actors_schema ADD COLUMN digest_scheme TEXT")
    db.execute(
        "CREATE TABLE resources_v2 (seq INTEGER PRIMARY KEY, id TEXT NOT NULL, "
        "server TEXT NOT NULL, state INTEGER NOT NULL, digest INTEGER, request BLOB, "
        "response BLOB)"
    )
    db.execute(
        "INSERT INTO resources_v2 (seq, id, server, state, request, response) "
        "SELECT seq, id, server, CASE state WHEN 'loading' THEN 0 WHEN 'loaded' THEN 1 "
        "WHEN 'unloading' THEN 2 END, request, response FROM resources"
    )
    db.execute(
        "CREATE TABLE consumers_v2 (seq INTEGER PRIMARY KEY, query_id TEXT NOT NULL, "
        "resource INTEGER NOT NULL, origin_rr TEXT NOT NULL)"
    )
    db.execute(
        "INSERT INTO consumers_v2 (seq, query_id, resource, origin_rr) "
        "SELECT c.seq, c.query_id, (SELECT r.seq FROM resources_v2 r WHERE r.id = c.resource_id), "
        "c.origin_rr FROM consumers c"
    )
    for table in ("resources", "consumers"):
        db.execute(f"DROP TABLE {table}")
        db.execute(f"ALTER TABLE {table}_v2 RENAME TO {table}")


def _upgrade_v3(db: sqlite3.Connection) -> None:
    """v2 -> v3: indexes that let a restore leave served resources on disk until used.

    Consumers are clustered by their resource (`WITHOUT ROWID`, key `(resource, seq)`),
    so one table scan yields each resource's consumer ids together and in arrival order;
    resources get a unique index on their id, one on `(server, digest)` (dedup of a
    resource not read yet) and a partial one on the rows a restore reads at once. A file
    with a resource id stored twice fails here (`UNIQUE constraint failed`).
    """
    db.execute(
        "CREATE TABLE consumers_v3 (resource INTEGER NOT NULL, seq INTEGER NOT NULL, "
        "query_id TEXT NOT NULL, origin_rr TEXT NOT NULL, PRIMARY KEY (resource, seq)) "
        "WITHOUT ROWID"
    )
    db.execute(
        "INSERT INTO consumers_v3 (resource, seq, query_id, origin_rr) "
        "SELECT resource, seq, query_id, origin_rr FROM consumers"
    )
    db.execute("DROP TABLE consumers")
    db.execute("ALTER TABLE consumers_v3 RENAME TO consumers")
    db.execute("CREATE UNIQUE INDEX resources_by_id ON resources (id)")
    db.execute("CREATE INDEX resources_by_request ON resources (server, digest)")
    db.execute(f"CREATE INDEX resources_unsettled ON resources (seq) WHERE {_UNSETTLED}")


_INDEXES = ("resources_by_id", "resources_by_request", "resources_unsettled")
"""The indexes of a current file: a restore relies on them (unique ids, dedup, doubt)."""

_UNSETTLED = "state != 1 OR digest IS NULL"
"""Resources a restore reads at once: in doubt (not loaded), or indexed by their value."""

_MIGRATIONS: tuple[Callable[[sqlite3.Connection], None], ...] = (
    _create_v1,
    _upgrade_v2,
    _upgrade_v3,
)
"""`_MIGRATIONS[v]` brings a version-`v` file to version `v + 1` (0 is an empty file).

To change the schema: append a migration, bump `SCHEMA_VERSION`, add a test that opens a
file written by the previous version. Never edit a released migration.
"""
assert len(_MIGRATIONS) == SCHEMA_VERSION


def _rollback(db: sqlite3.Connection) -> None:
    """Roll back after a failure without hiding it (a failed COMMIT may have ended it)."""
    if db.in_transaction:
        with contextlib.suppress(sqlite3.Error):
            db.execute("ROLLBACK")


def _dumps(value: Any) -> bytes | None:
    if value is None:
        return None
    return cloudpickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)  # type: ignore[no-any-return]


def _loads(blob: bytes | None) -> Any:
    return None if blob is None else pickle.loads(blob)


def _decode(path: str, rid: str, field: str, blob: bytes | None) -> Any:
    """Decode a restored resource's stored value on first use (see `Resource.encoded`)."""
    try:
        return _loads(blob)
    except Exception as exc:
        raise CatalogCorruptError(
            path,
            f"the stored {field} of resource {rid} cannot be read: {type(exc).__name__}: {exc}",
        ) from exc


def _not_a_pickle(blob: bytes | None) -> bool:
    """Whether a stored value cannot be a whole binary pickle (protocol header ... STOP)."""
    return blob is not None and (
        type(blob) is not bytes or blob[:1] != b"\x80" or blob[-1:] != b"."
    )


def _check_values(row: Any) -> None:
    """Raise `ValueError` if a resource row's request or response cannot be a pickle.

    A cheap check of what a restore leaves encoded (about 0.3 us a row).
    """
    if _not_a_pickle(row[5]) or _not_a_pickle(row[6]):
        raise ValueError(f"the stored request or response of resource {row[1]} is not a pickle")


def _check_state(row: Any) -> None:
    """Raise `ValueError` if a resource row's state code is unknown."""
    state = row[3]
    if type(state) is not int or not 0 <= state < len(_STATES_BY_CODE):
        raise ValueError(f"resource {row[1]} has an unknown state {state!r}")


def _check_row(row: Any) -> None:
    """Raise `ValueError` if a resource row has an unknown state or a value is no pickle."""
    _check_state(row)
    _check_values(row)


def _check_keys(rows: list[Any], consumer_rows: list[Any], client_rows: list[Any]) -> None:
    """Raise `ValueError` for a duplicate id or an unknown state code.

    A resource id, a consumer query id and a client query id each name one row; a second
    row with the same id would silently replace the first in the catalog.
    """
    for row in rows:
        _check_state(row)
    for what, ids in (
        ("resource id", [row[1] for row in rows]),
        ("consumer query id", [row[1] for row in consumer_rows]),
        ("client query id", [row[1] for row in client_rows]),
    ):
        if len(set(ids)) != len(ids):
            raise ValueError(f"{what} {_first_duplicate(ids)} is stored twice")


def _refresh_digests(db: sqlite3.Connection, name: str) -> None:
    """Recompute every stored digest if they were written under another `DIGEST_SCHEME`.

    One transaction; a request that cannot be decoded here keeps a `NULL` digest (the
    restore then decodes it, and reports it as `CatalogCorruptError`).
    """
    with _as_corrupt(name):
        scheme = db.execute("SELECT digest_scheme FROM rr_actors_schema").fetchone()[0]
        if scheme == DIGEST_SCHEME:
            return
        db.execute("BEGIN IMMEDIATE")
        try:
            updates = []
            for seq, blob in db.execute("SELECT seq, request FROM resources").fetchall():
                try:
                    digest = request_digest(_loads(blob))
                except Exception:  # noqa: BLE001 - reported when the row is restored
                    digest = None
                updates.append((digest, seq))
            db.executemany("UPDATE resources SET digest = ? WHERE seq = ?", updates)
            db.execute("UPDATE rr_actors_schema SET digest_scheme = ?", (DIGEST_SCHEME,))
        except BaseException:
            _rollback(db)
            raise
        db.execute("COMMIT")


@dataclasses.dataclass(frozen=True)
class Unreadable:
    """Stands for a stored request or response that cannot be unpickled here (inspection).

    Attributes:
        error: why, e.g. `"ModuleNotFoundError: No module named 'drivers'"`.
        size: length of the pickle, in bytes.
    """

    error: str
    size: int

    def __repr__(self) -> str:
        return f"<unreadable, {self.size} bytes: {self.error}>"


def _lenient_decode(_rid: str, _field: str, blob: bytes | None) -> Any:
    try:
        return _loads(blob)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is shown, not raised
        return Unreadable(f"{type(exc).__name__}: {exc}", len(blob or b""))


class _Mirror:
    """What the store last wrote for one resource (to write only the difference)."""

    __slots__ = ("consumers", "response_version", "seq", "state")

    def __init__(
        self, seq: int, state: ResourceState, response_version: int, consumers: dict[str, int]
    ) -> None:
        self.seq = seq  # the row's key
        self.state = state
        # The catalog bumps `Resource.response_version` on every response it sets (also
        # the same object again, mutated); decoding a restored one does not.
        self.response_version = response_version
        self.consumers = consumers  # consumer query id -> its row's key


_Op = tuple[str, tuple[Any, ...]]
"""One planned SQL statement and its parameters."""

_GONE = object()
"""Marks a mirror entry to delete once a write committed."""


@dataclasses.dataclass
class _Rows:
    """Rows read from a backup, with the row keys the store needs to update them."""

    resources: list[Resource]
    clients: list[ClientRecord]
    mirror: dict[str, _Mirror]
    client_seqs: dict[str, int]
    max_seq: int


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


# -- opening and validating ---------------------------------------------------------------


def _check_location(path: Path) -> None:
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


def _connect(path: Path, *, read_only: bool) -> sqlite3.Connection:
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


def _schema_version(db: sqlite3.Connection, path: str) -> int:
    """Validate that `db` is an rr_actors catalog and return its schema version."""
    application_id = db.execute("PRAGMA application_id").fetchone()[0]
    tables = sorted(
        row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")
    )
    if application_id != APPLICATION_ID or "rr_actors_schema" not in tables:
        raise CatalogCorruptError(
            path,
            f"not an rr_actors catalog (application_id {application_id:#x}, tables {tables})",
        )
    rows = db.execute("SELECT version FROM rr_actors_schema").fetchall()
    if len(rows) != 1 or not isinstance(rows[0][0], int):
        raise CatalogCorruptError(path, f"bad schema version rows {rows!r}")
    version: int = rows[0][0]
    if version > SCHEMA_VERSION:
        raise CatalogCorruptError(
            path,
            f"schema version {version} is newer than this rr_actors supports "
            f"({SCHEMA_VERSION}); upgrade rr_actors to read it",
        )
    if version < 1:
        raise CatalogCorruptError(path, f"bad schema version {version}")
    if version == SCHEMA_VERSION:
        indexes = {
            row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type = 'index'")
        }
        for index in _INDEXES:
            if index not in indexes:
                raise CatalogCorruptError(path, f"index {index} is missing")
    return version


def _migrate(db: sqlite3.Connection, version: int) -> None:
    """Bring `db` from `version` to `SCHEMA_VERSION`, each step one transaction."""
    for step in range(version, SCHEMA_VERSION):
        db.execute("BEGIN IMMEDIATE")
        try:
            _MIGRATIONS[step](db)
            db.execute("UPDATE rr_actors_schema SET version = ?", (step + 1,))
        except BaseException:
            _rollback(db)
            raise
        db.execute("COMMIT")


def _create(path: Path) -> None:
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
        db.execute(f"PRAGMA application_id = {APPLICATION_ID}")
        _migrate(db, 0)
        db.execute("PRAGMA journal_mode = WAL")
        db.close()
        with contextlib.suppress(FileExistsError):
            os.link(tmp, path)
    except (sqlite3.Error, OSError) as exc:
        raise ConfigError(f"backup_path {str(path)!r} cannot be created: {exc}") from exc
    finally:
        db.close()
        for suffix in ("", *_SIDE_FILES):
            with contextlib.suppress(FileNotFoundError):
                Path(f"{tmp}{suffix}").unlink()


@contextlib.contextmanager
def _as_corrupt(path: str) -> Iterator[None]:
    """Translate what SQLite or unpickling raises about a bad file."""
    try:
        yield
    except sqlite3.DatabaseError as exc:
        raise CatalogCorruptError(path, f"{type(exc).__name__}: {exc}") from exc
    except (
        pickle.UnpicklingError,
        EOFError,
        AttributeError,
        ImportError,
        ValueError,
        TypeError,
        KeyError,
        IndexError,
    ) as exc:
        raise CatalogCorruptError(
            path, f"a stored row cannot be read: {type(exc).__name__}: {exc}"
        ) from exc


@contextlib.contextmanager
def _read_only(path: Path, *, tidy: bool) -> Iterator[sqlite3.Connection]:
    """A read-only connection; with `tidy`, remove the `-wal`/`-shm` files it created.

    A read-only connection to a WAL-mode file creates those files but cannot delete
    them; an empty `-wal` holds nothing, so removing what we created changes nothing.
    """
    existed = {suffix: Path(f"{path}{suffix}").exists() for suffix in ("-wal", "-shm")}
    db = _connect(path, read_only=True)
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


def _validate(path: Path, *, tidy: bool) -> int:
    """Check an existing file without writing to it; return its schema version."""
    name = str(path)
    problem = _file_problem(path)
    if problem is not None:
        raise CatalogCorruptError(name, problem)
    with _as_corrupt(name), _read_only(path, tidy=tidy) as db:
        return _schema_version(db, name)


def _prepare(db: sqlite3.Connection, name: str, durability: str, version: int) -> None:
    """Check that `db` is writable, switch on WAL and the durability, migrate it."""
    try:
        db.execute("BEGIN IMMEDIATE")  # can we write here at all?
        db.execute("ROLLBACK")
    except sqlite3.OperationalError as exc:
        raise ConfigError(f"backup_path {name!r} is not writable: {exc}") from exc
    with _as_corrupt(name):
        mode = db.execute("PRAGMA journal_mode = WAL").fetchone()[0]
    if mode != "wal":  # before anything is written: an older file stays as it was
        raise ConfigError(f"backup_path {name!r}: SQLite cannot use WAL mode there ({mode})")
    with _as_corrupt(name):
        db.execute(f"PRAGMA synchronous = {_SYNCHRONOUS[durability]}")
        _migrate(db, version)
    _refresh_digests(db, name)


def _read_rows(
    db: sqlite3.Connection, decode: Callable[[str, str, bytes | None], Any], *, lenient: bool
) -> _Rows:
    """Read every row in one read transaction (a consistent snapshot, also of a live file).

    Restored resources keep their request and response encoded: `decode` runs on first
    access. Requests without a stored digest are decoded at once (the catalog indexes
    them by `hash()`, which only the value can give). With `lenient` (inspection) every
    value is decoded at once and the cheap pickle check is skipped (`decode` is lenient).
    """
    db.execute("BEGIN")
    try:
        rows = db.execute(
            "SELECT seq, id, server, state, digest, request, response FROM resources ORDER BY seq"
        ).fetchall()
        consumer_rows = db.execute(
            "SELECT seq, query_id, resource, origin_rr FROM consumers ORDER BY seq"
        ).fetchall()
        client_rows = db.execute(
            "SELECT seq, query_id, server, serving_rr, origin_rr, request, response, parent, "
            "loaded FROM clients ORDER BY seq"
        ).fetchall()
    finally:
        db.execute("COMMIT")
    if not lenient:
        for row in rows:
            _check_values(row)
    _check_keys(rows, consumer_rows, client_rows)
    encoded = Resource.encoded
    states = _STATES_BY_CODE
    resources = [
        encoded(
            rid,
            server,
            states[state],
            NO_DIGEST if digest is None else digest,
            (request, response),
            decode,
        )
        for _, rid, server, state, digest, request, response in rows
    ]
    for resource in resources:
        if lenient:
            _ = resource.request, resource.response
        if resource.digest == NO_DIGEST:
            resource.digest = None  # the catalog indexes it from its (decoded) request
            _ = resource.request
    mirrors = [
        _Mirror(row[0], r.state, r.response_version, {})
        for row, r in zip(rows, resources, strict=True)
    ]
    by_seq = {row[0]: (r, m) for row, r, m in zip(rows, resources, mirrors, strict=True)}
    max_seq = rows[-1][0] if rows else 0
    for seq, query_id, resource_seq, origin in consumer_rows:
        owner = by_seq.get(resource_seq)
        if owner is None:
            raise ValueError(f"consumer {query_id} belongs to a missing resource")
        owner[0].consumers[query_id] = origin
        owner[1].consumers[query_id] = seq
    if consumer_rows:
        max_seq = max(max_seq, consumer_rows[-1][0])
    clients, client_seqs = _client_records(client_rows, decode)
    max_seq = max([max_seq, *client_seqs.values()])
    mirror = {r.id: m for r, m in zip(resources, mirrors, strict=True)}
    return _Rows(resources, clients, mirror, client_seqs, max_seq)


def _client_records(
    client_rows: list[Any], decode: Callable[[str, str, bytes | None], Any]
) -> tuple[list[ClientRecord], dict[str, int]]:
    """Client records from their rows (oldest first), with each record's row key."""
    clients = []
    seqs = {}
    for seq, qid, server, serving, origin, request, response, parent, loaded in client_rows:
        query = Query(
            qid,
            server,
            serving,
            origin,
            decode(qid, "request", request),
            decode(qid, "response", response),
        )
        clients.append(ClientRecord(query, parent, bool(loaded)))
        seqs[qid] = seq
    return clients, seqs


_RESOURCE_BY_SEQ = (
    "SELECT seq, id, server, state, digest, request, response FROM resources WHERE seq = ?"
)
_RESOURCES_AT_ONCE = (  # what a restore reads as rows: in doubt, no digest, or a parent
    "SELECT seq, id, server, state, digest, request, response FROM resources "
    "WHERE state != 1 OR digest IS NULL "  # == _UNSETTLED: the partial index serves it
    "UNION SELECT seq, id, server, state, digest, request, response FROM resources "
    "WHERE id IN (SELECT parent FROM clients WHERE parent IS NOT NULL) ORDER BY seq"
)
_CONSUMERS_OF = (  # one key range of the (resource, seq) key: in arrival order
    "SELECT seq, query_id, origin_rr FROM consumers WHERE resource = ?"
)
_CLIENTS = (
    "SELECT seq, query_id, server, serving_rr, origin_rr, request, response, parent, loaded "
    "FROM clients ORDER BY seq"
)
_SEP = "\x1f"  # joins the consumer ids in one string (checked: a collision reads rows)


class _Consumers:
    """Which resource row holds each stored consumer id, read as two column strings.

    One aggregate query returns every query id and resource key joined in a string each
    (no row tuples: a fraction of the cost of reading 100k rows); `index` maps a query
    id straight to its resource key as read (parsed when that consumer is looked up), so
    no list of places or place numbers is kept. The joined strings and the index's
    outgrown tables are freed once it is built, and the pages they leave are handed back
    to the system (`PLATFORM.release_free_memory`): 100k ids then cost the process 19 MB, not 27.
    Every page a manager process still maps when it is killed is freed by the kernel
    before its supervisor can see it exit (about 0.12 ms a MB).
    """

    def __init__(self, db: sqlite3.Connection) -> None:
        count, max_seq, resources, query_ids = db.execute(
            "SELECT count(*), ifnull(max(seq), 0), group_concat(resource), "
            "group_concat(query_id, char(31)) FROM consumers"
        ).fetchone()
        self.max_seq: int = max_seq
        keys: list[str] = query_ids.split(_SEP) if count else []
        values: list[str | int] = resources.split(",") if count else []
        del resources, query_ids
        if len(keys) != count:  # a query id holds the separator: read the rows instead
            rows = db.execute("SELECT resource, query_id FROM consumers").fetchall()
            values = [resource for resource, _ in rows]
            keys = [query_id for _, query_id in rows]
            del rows
        self.index: dict[str, str | int] = dict(zip(keys, values, strict=True))
        if len(self.index) != count:
            raise ValueError(f"consumer query id {_first_duplicate(keys)} is stored twice")
        del keys, values
        if count >= _TRIM_AFTER:
            PLATFORM.release_free_memory()

    def resource_of(self, query_id: str) -> int | None:
        """The resource row key of consumer `query_id`, if it is stored."""
        resource = self.index.get(query_id)
        return None if resource is None else int(resource)


_TRIM_AFTER = 10_000
"""Consumer ids from which building `_Consumers` frees enough (MBs) to hand it back."""


def _first_duplicate(values: list[Any]) -> Any:
    seen: set[Any] = set()
    for value in values:
        if value in seen:
            return value
        seen.add(value)
    return None


class _Unread:
    """The served resources of a restored backup that are not in memory yet (`UnreadRows`).

    A restore reads the consumer ids, the resources in doubt and the clients; the other
    resources stay in the file until the catalog asks for one (by request digest, by
    consumer id, by server, ...). Reading one builds it with its consumers, records its
    mirror in the store and never returns it again: from then on memory is the truth.
    Rows written after the restore (`seq > last`) are the catalog's own and never read.
    """

    def __init__(
        self, store: SqliteStore, consumers: _Consumers, count: int, last: int, read: set[int]
    ) -> None:
        self._store = store
        self._consumers = consumers
        self._last = last
        self._read = read  # row keys of restored resources already in memory
        self.remaining = count - len(read)

    def by_request(self, server: str, digest: int) -> list[Resource]:
        """Unread resources of `server` whose request digest is `digest`."""
        return self._fetch(
            "SELECT seq FROM resources WHERE server = ? AND digest = ? AND seq <= ?",
            (server, digest, self._last),
        )

    def by_consumer(self, query_id: str) -> Resource | None:
        """The unread resource that has consumer `query_id`, if any."""
        with _as_corrupt(self._store.path):
            seq = self._consumers.resource_of(query_id)
        if seq is None:
            return None
        if seq in self._read:
            return None  # in memory: released since (memory is the truth)
        self._check_open()
        resources = self._take([seq])
        if not resources:
            raise CatalogCorruptError(
                self._store.path, f"consumer {query_id} belongs to a missing resource"
            )
        return resources[0]

    def of_server(self, server: str) -> list[Resource]:
        """Every unread resource of `server`, oldest first."""
        return self._fetch(
            "SELECT seq FROM resources WHERE server = ? AND seq <= ? ORDER BY seq",
            (server, self._last),
        )

    def with_origin(self, origin_rr: str) -> list[Resource]:
        """Every unread resource with a consumer from registrar `origin_rr`."""
        return self._fetch(
            "SELECT DISTINCT resource FROM consumers WHERE origin_rr = ? AND resource <= ? "
            "ORDER BY resource",
            (origin_rr, self._last),
        )

    def every(self) -> list[Resource]:
        """Every unread resource, oldest first."""
        return self._fetch("SELECT seq FROM resources WHERE seq <= ? ORDER BY seq", (self._last,))

    def _fetch(self, sql: str, args: tuple[Any, ...]) -> list[Resource]:
        if not self.remaining:
            return []
        self._check_open()
        with _as_corrupt(self._store.path):
            seqs = [seq for (seq,) in self._store._db.execute(sql, args) if seq not in self._read]
        return self._take(seqs)

    def _take(self, seqs: list[int]) -> list[Resource]:
        """Read resource rows `seqs` with their consumers; hand over all of them or none.

        Every row is read and checked before any is adopted, so a damaged one fails the
        lookup without marking its healthy neighbours read (they stay on disk, whole).
        """
        store = self._store
        db = store._db
        read = []
        with _as_corrupt(store.path):
            for seq in seqs:
                row = db.execute(_RESOURCE_BY_SEQ, (seq,)).fetchone()
                if row is None:
                    continue
                _check_row(row)
                read.append((row, db.execute(_CONSUMERS_OF, (seq,)).fetchall()))
        resources = [store._adopt(row, consumers) for row, consumers in read]
        self._read.update(row[0] for row, _ in read)
        self.remaining -= len(read)
        return resources

    def _check_open(self) -> None:
        if self._store.closed:
            raise RegistrarStoppedError(
                f"the catalog backup {self._store.path!r} was closed (its registrar stopped)"
            )


@dataclasses.dataclass
class Restored:
    """What `SqliteStore.restore` read: enough to serve, the rest on first use.

    Attributes:
        resources: resources read at once (in doubt, without a digest, or owning a
            dependency), oldest first.
        clients: every client record, oldest first.
        unread: the other served resources, read when the catalog first needs them.
    """

    resources: list[Resource]
    clients: list[ClientRecord]
    unread: _Unread


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
    version = _validate(file, tidy=True)
    name = str(file)
    with _as_corrupt(name), _read_only(file, tidy=True) as db:
        check = db.execute("PRAGMA quick_check").fetchall()
        if check != [("ok",)]:
            raise CatalogCorruptError(name, f"integrity check failed: {check[:5]!r}")
        with _migrated_copy(db, version) as current, gc_paused():
            rows = _read_rows(current, _lenient_decode, lenient=True)
    return Backup(name, version, rows.resources, rows.clients)


@contextlib.contextmanager
def _migrated_copy(db: sqlite3.Connection, version: int) -> Iterator[sqlite3.Connection]:
    """`db` itself if it has the current schema, else a migrated copy in memory.

    An older file is read as the code reads a current one, without writing to it.
    """
    if version == SCHEMA_VERSION:
        yield db
        return
    copy = sqlite3.connect(":memory:", isolation_level=None)
    try:
        db.backup(copy)
        _migrate(copy, version)
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
    for suffix in _SIDE_FILES:  # companions first: the main file's name is the anchor
        side = Path(f"{file}{suffix}")
        if side.exists():
            side.rename(f"{target}{suffix}")
    file.rename(target)
    return target


# -- checkpoints --------------------------------------------------------------------------


CHECKPOINT_EVERY = 256
"""WAL pages written between two background checkpoints, about: each statement counts
one, plus a page per 4 KiB of a large request or response."""

_PAGE = 4096

CHECKPOINT_BUSY_TIMEOUT = 0.1
"""Seconds a `RESTART` checkpoint waits for readers; the writer waits at most as long."""

WAL_LIMIT = 16_384
"""WAL frames (4 KiB pages) past which a checkpoint makes the writer wait for it."""

WAL_KEPT = 8 * 1024 * 1024
"""Bytes of WAL file kept when the log restarts after background checkpoints
(`journal_size_limit`); more is cut off. Twice what SQLite's own checkpoints let it reach."""


class _Checkpointer:
    """Copies committed WAL pages into the database file, on its own thread.

    SQLite's automatic checkpoint runs inside the commit that crosses its threshold: one
    flush in a few paid for copying the log into the file and syncing both, the largest
    part of a batched change's cost in a large catalog. A store opened with
    `background_checkpoints` (a registrar without `save_on_modify`) switches it off
    (`wal_autocheckpoint = 0`) and wakes this thread every `CHECKPOINT_EVERY` pages or so
    instead, as SQLite's WAL documentation suggests for writers that must not stall. It
    runs `PRAGMA wal_checkpoint(PASSIVE)` on its own connection, which never blocks the
    writer (and SQLite releases the GIL while it copies). A commit is exactly as durable
    as before: it is in the WAL either way, and SQLite repairs a checkpoint cut short by a
    crash when the file is next opened. (Under a steady stream of one-change commits, a
    concurrent copy measured twice as slow per commit as SQLite's own checkpoints, so a
    `save_on_modify` registrar keeps those.)

    A passive checkpoint cannot restart the log while the writer keeps appending; once
    the log holds more than `WAL_LIMIT` frames the checkpoint is `RESTART`, which holds
    new writes back while it waits for readers on older snapshots, for at most
    `CHECKPOINT_BUSY_TIMEOUT` (far below the writer's own 5 s busy timeout, so a reader
    that lingers, `rr-actors inspect` on a live file say, delays a write by that much and
    never fails it); so the WAL stays bounded under any load. The thread starts at the
    first wake-up: a store that writes little never has one. If it cannot start, or
    cannot open its connection, `wake` says so and the store goes back to SQLite's own
    checkpoints.
    """

    def __init__(self, path: Path, synchronous: str) -> None:
        self._path = path.resolve()  # the thread connects later: a chdir must not matter
        self._synchronous = synchronous
        self._wake = threading.Event()
        self._closing = False
        self._thread: threading.Thread | None = None
        self._db: sqlite3.Connection | None = None  # the thread's connection, once open
        self.done = threading.Condition()
        """Notified after each checkpoint (tests and benchmarks wait on it)."""
        self._running = False
        self.checkpoints = 0
        self.last: tuple[int, int, int] | None = None
        """The last checkpoint's `(busy, frames in the log, frames copied)`."""

    def wake(self) -> bool:
        """Ask for a checkpoint soon; `False` if no thread can do it (it could not start,
        or could not open its connection)."""
        if self._closing:
            return True
        if self._thread is not None and not self._thread.is_alive():
            return False
        if self._thread is None:
            thread = threading.Thread(
                target=self._run, name=f"rr-actors-checkpoint:{self._path.name}", daemon=True
            )
            try:
                thread.start()
            except RuntimeError:  # out of threads
                return False
            self._thread = thread
        self._wake.set()
        return True

    def wait_idle(self, timeout: float) -> bool:
        """Wait until no checkpoint is asked for or running; False after `timeout` seconds."""
        with self.done:
            return self.done.wait_for(
                lambda: not self._running and not self._wake.is_set(), timeout
            )

    def close(self, timeout: float = 10.0) -> None:
        """Stop the thread, interrupting the checkpoint in progress (it is safe to cut one
        short: the next one, or the next open, finishes the copy). Waits `timeout` s."""
        self._closing = True
        self._wake.set()
        db = self._db
        if db is not None:
            with contextlib.suppress(sqlite3.Error):
                db.interrupt()
        if self._thread is not None:
            self._thread.join(timeout)

    def _run(self) -> None:
        try:
            # by URI in `rw` mode: it never creates a file where the backup was
            db = sqlite3.connect(
                f"{self._path.as_uri()}?mode=rw",
                uri=True,
                isolation_level=None,
                timeout=CHECKPOINT_BUSY_TIMEOUT,
            )
            db.execute(f"PRAGMA synchronous = {self._synchronous}")
        except sqlite3.Error as exc:
            logger.warning("catalog %s: no checkpoint connection: %s", self._path, exc)
            return  # `wake` sees the thread gone: the store checkpoints as SQLite does
        self._db = db
        try:
            while True:
                self._wake.wait()
                if self._closing:
                    return
                with self.done:
                    self._wake.clear()
                    self._running = True
                self._checkpoint(db)
        finally:
            self._db = None
            db.close()
            with self.done:
                self._running = False
                self.done.notify_all()

    def _checkpoint(self, db: sqlite3.Connection) -> None:
        try:
            busy, log, copied = db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
            if log > WAL_LIMIT and copied < log:
                busy, log, copied = db.execute("PRAGMA wal_checkpoint(RESTART)").fetchone()
        except sqlite3.Error as exc:  # the WAL keeps every commit; retried at the next wake
            if not self._closing:  # (closing interrupts it)
                logger.warning("catalog %s: checkpoint failed: %s", self._path, exc)
            with self.done:
                self._running = False
                self.done.notify_all()
            return
        with self.done:
            self.last = (busy, log, copied)
            self.checkpoints += 1
            self._running = False
            self.done.notify_all()


# -- the store ----------------------------------------------------------------------------


class SqliteStore:
    """A `CatalogStore` in one SQLite file. Used by one thread at a time (the registrar's).

    Open it with [`SqliteStore.open`][rr_actors._store.sqlite.SqliteStore.open].
    """

    def __init__(
        self,
        path: Path,
        db: sqlite3.Connection,
        *,
        created: bool,
        synchronous: str = "NORMAL",
        background_checkpoints: bool = False,
    ) -> None:
        self.path = str(path)
        self._file = path
        self._db = db
        self._checkpointer: _Checkpointer | None = None
        if background_checkpoints:
            db.execute("PRAGMA wal_autocheckpoint = 0")  # the checkpointer's thread does it
            db.execute(f"PRAGMA journal_size_limit = {WAL_KEPT}")
            self._checkpointer = _Checkpointer(path, synchronous)
        self._unchecked = 0  # pages (about) written since the checkpointer was last woken
        self.checkpoint_every = CHECKPOINT_EVERY
        self._created = created
        self._loaded = False
        self._resources: dict[str, _Mirror] = {}
        # query id -> (row key, response_version)
        self._clients: dict[str, tuple[int, int]] = {}
        self._seq = 0
        self.closed = False
        self._decode = functools.partial(_decode, self.path)  # decodes a stored value lazily

    @classmethod
    def open(
        cls,
        path: str | os.PathLike[str],
        *,
        durability: Literal["process", "power"] = "process",
        background_checkpoints: bool = False,
    ) -> SqliteStore:
        """Open the backup at `path`, creating an empty one if there is no file.

        Args:
            path: the backup file; its directory must exist and be writable.
            durability: `"process"` (SQLite `synchronous=NORMAL`: a commit survives a
                crash of the process) or `"power"` (`synchronous=FULL`: it also survives
                power loss, at the cost of an fsync per commit).
            background_checkpoints: copy the WAL into the file on a thread of its own
                (`_Checkpointer`) instead of inside every few hundredth commit. For
                writes in bursts (a `save_interval` flush); a steady stream of small
                commits (`save_on_modify`) is slower with it (the copy competes with it).

        Returns:
            The open store; `load()` returns `None` if it was created just now.

        Raises:
            ConfigError: the path cannot hold a backup (missing directory, a directory,
                read-only file or location).
            CatalogCorruptError: the file exists but is not a usable rr_actors catalog
                (garbage, truncated, another program's database, a newer schema, ...).
        """
        file = Path(os.fspath(path))
        _check_location(file)
        created = False
        if not file.exists():
            _create(file)
            created = True
        version = _validate(file, tidy=True)
        name = str(file)
        try:
            db = _connect(file, read_only=False)
        except sqlite3.Error as exc:
            raise ConfigError(f"backup_path {name!r} cannot be opened: {exc}") from exc
        try:
            _prepare(db, name, durability, version)
        except BaseException:
            db.close()
            raise
        return cls(
            file,
            db,
            created=created,
            synchronous=_SYNCHRONOUS[durability],
            background_checkpoints=background_checkpoints,
        )

    def load(self) -> tuple[list[Resource], list[ClientRecord]] | None:
        """Every stored row, oldest first; `None` if the file was created by `open`.

        Raises:
            CatalogCorruptError: a row or a stored value cannot be read.
        """
        try:
            with _as_corrupt(self.path), gc_paused():
                rows = _read_rows(self._db, self._decode, lenient=False)
        except CatalogCorruptError:
            self.close(erase=False)  # unusable; closing also removes its -wal and -shm
            raise
        self._resources = rows.mirror
        self._clients = {
            c.query.id: (rows.client_seqs[c.query.id], c.response_version) for c in rows.clients
        }
        self._seq = rows.max_seq
        self._loaded = True
        if self._created and not rows.resources and not rows.clients:
            return None
        return rows.resources, rows.clients

    def restore(self) -> Restored | None:
        """Read what a registrar needs to serve again; `None` if `open` created the file.

        Unlike `load`, it does not read every served resource: the consumer ids (as two
        column strings), the resources in doubt or without a stored digest, those owning a
        dependency and the client records are read in one read transaction; the other
        resources are read from the file when the catalog first needs them (`unread`).
        So its cost grows with the number of consumer ids only, at a fraction of a row read.

        Raises:
            CatalogCorruptError: the backup cannot be read (duplicate ids, unknown
                states, ...); a resource read later that cannot be read raises it then.
        """
        try:
            with _as_corrupt(self.path), gc_paused():
                self._db.execute("BEGIN")
                try:
                    count, last = self._db.execute(
                        "SELECT count(*), ifnull(max(seq), 0) FROM resources"
                    ).fetchone()
                    consumers = _Consumers(self._db)
                    rows = self._db.execute(_RESOURCES_AT_ONCE).fetchall()
                    client_rows = self._db.execute(_CLIENTS).fetchall()
                finally:
                    self._db.execute("COMMIT")
                for row in rows:
                    _check_row(row)
                _check_keys([], [], client_rows)
                self._resources = {}
                resources = [
                    self._adopt(row, self._db.execute(_CONSUMERS_OF, (row[0],)).fetchall())
                    for row in rows
                ]
                for resource in resources:
                    if resource.digest == NO_DIGEST:
                        resource.digest = None  # indexed from its (decoded) request
                        _ = resource.request
                clients, client_seqs = _client_records(client_rows, self._decode)
                self._clients = {qid: (seq, 0) for qid, seq in client_seqs.items()}
        except CatalogCorruptError:
            self.close(erase=False)
            raise
        self._seq = max(last, consumers.max_seq, *client_seqs.values())
        self._loaded = True
        if self._created and not count and not clients:
            return None
        unread = _Unread(self, consumers, count, last, {row[0] for row in rows})
        return Restored(resources, clients, unread)

    def _adopt(self, row: Any, consumer_rows: list[Any]) -> Resource:
        """Build a stored resource with its consumers; from now on the store mirrors it."""
        seq, rid, server, state, digest, request, response = row
        resource = Resource.encoded(
            rid,
            server,
            _STATES_BY_CODE[state],
            NO_DIGEST if digest is None else digest,
            (request, response),
            self._decode,
            seq,
        )
        keys = {}
        for key, query_id, origin in consumer_rows:
            resource.consumers[query_id] = origin
            keys[query_id] = key
        self._resources[rid] = _Mirror(seq, resource.state, 0, keys)
        return resource

    def write(self, changes: Changes) -> None:
        """Apply `changes` (current rows, `None` for deleted ones) as one transaction.

        Only what differs from the last write reaches the file; rows are addressed by
        their key, so the cost of a change does not depend on the catalog's size. The
        statements are planned first (values are pickled then: one that cannot be raises
        before anything is written); a single statement is its own transaction (most
        changes: a consumer id added or released), several run between `BEGIN IMMEDIATE`
        and `COMMIT`. What the store remembers of the file changes only once committed.
        """
        if not self._loaded:
            self.load()
        ops: list[_Op] = []
        mirrors: list[tuple[dict[str, Any], str, Any]] = []  # (table, key, new value | _GONE)
        seq = self._seq
        for rid, resource in changes.resources.items():
            seq = self._plan_resource(ops, mirrors, rid, resource, seq)
        for qid, record in changes.clients.items():
            seq = self._plan_client(ops, mirrors, qid, record, seq)
        if ops:
            self._run(ops)
        self._seq = seq
        for table, key, value in mirrors:
            if value is _GONE:
                table.pop(key, None)
            else:
                table[key] = value

    def _run(self, ops: list[_Op]) -> None:
        db = self._db
        if len(ops) == 1 and not db.in_transaction:  # one statement: its own transaction
            sql, params = ops[0]
            db.execute(sql, params)
        else:
            db.execute("BEGIN IMMEDIATE")
            try:
                for sql, params in ops:
                    db.execute(sql, params)
                db.execute("COMMIT")
            except BaseException:
                _rollback(db)
                raise
        if self._checkpointer is None:
            return
        self._unchecked += len(ops)
        for _, params in ops:  # a large request or response fills many pages
            for value in params:
                if type(value) is bytes and len(value) > _PAGE:
                    self._unchecked += len(value) // _PAGE
        if self._unchecked >= self.checkpoint_every:
            self._unchecked = 0
            if not self._checkpointer.wake():  # no thread: SQLite's own, from now on
                db.execute("PRAGMA wal_autocheckpoint = 1000")
                self._checkpointer = None

    def _plan_resource(
        self,
        ops: list[_Op],
        mirrors: list[tuple[dict[str, Any], str, Any]],
        rid: str,
        resource: Resource | None,
        seq: int,
    ) -> int:
        old = self._resources.get(rid)
        if resource is None:
            if old is not None:
                ops.append(("DELETE FROM resources WHERE seq = ?", (old.seq,)))
                ops.append(("DELETE FROM consumers WHERE resource = ?", (old.seq,)))
                mirrors.append((self._resources, rid, _GONE))
            return seq
        if old is None:
            seq += 1
            digest = resource.digest
            if digest is None:
                digest = request_digest(resource.request)
            ops.append(
                (
                    "INSERT INTO resources (seq, id, server, state, digest, request, response) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?)",
                    (
                        seq,
                        rid,
                        resource.server,
                        _STATE_CODES[resource.state],
                        None if digest == NO_DIGEST else digest,
                        _dumps(resource.request),
                        _dumps(resource.response),
                    ),
                )
            )
            old_consumers: dict[str, int] = {}
            row = seq
        else:
            if old.response_version != resource.response_version:
                ops.append(
                    (
                        "UPDATE resources SET state = ?, response = ? WHERE seq = ?",
                        (_STATE_CODES[resource.state], _dumps(resource.response), old.seq),
                    )
                )
            elif old.state is not resource.state:
                ops.append(
                    (
                        "UPDATE resources SET state = ? WHERE seq = ?",
                        (_STATE_CODES[resource.state], old.seq),
                    )
                )
            old_consumers = old.consumers
            row = old.seq
        consumers = {}
        kept = 0
        for query_id, origin in resource.consumers.items():
            key = old_consumers.get(query_id)
            if key is None:
                seq += 1
                key = seq
                ops.append(
                    (
                        "INSERT INTO consumers (resource, seq, query_id, origin_rr) "
                        "VALUES (?, ?, ?, ?)",
                        (row, key, query_id, origin),
                    )
                )
            else:
                kept += 1
            consumers[query_id] = key
        if kept != len(old_consumers):  # some consumers left since the last write
            ops.extend(
                ("DELETE FROM consumers WHERE resource = ? AND seq = ?", (row, key))
                for query_id, key in old_consumers.items()
                if query_id not in consumers
            )
        mirror = _Mirror(row, resource.state, resource.response_version, consumers)
        mirrors.append((self._resources, rid, mirror))
        return seq

    def _plan_client(
        self,
        ops: list[_Op],
        mirrors: list[tuple[dict[str, Any], str, Any]],
        qid: str,
        record: ClientRecord | None,
        seq: int,
    ) -> int:
        old = self._clients.get(qid)
        if record is None:
            if old is not None:
                ops.append(("DELETE FROM clients WHERE seq = ?", (old[0],)))
                mirrors.append((self._clients, qid, _GONE))
            return seq
        query = record.query
        if old is None:
            seq += 1
            row = seq
            ops.append(
                (
                    "INSERT INTO clients (seq, query_id, server, serving_rr, origin_rr, "
                    "request, response, parent, loaded) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (
                        seq,
                        qid,
                        query.server,
                        query.serving_rr,
                        query.origin_rr,
                        _dumps(query.request),
                        _dumps(query.response),
                        record.parent,
                        int(record.loaded),
                    ),
                )
            )
        elif old[1] == record.response_version:
            row = old[0]
            ops.append(("UPDATE clients SET loaded = ? WHERE seq = ?", (int(record.loaded), row)))
        else:
            row = old[0]
            ops.append(
                (
                    "UPDATE clients SET response = ?, loaded = ? WHERE seq = ?",
                    (_dumps(query.response), int(record.loaded), row),
                )
            )
        mirrors.append((self._clients, qid, (row, record.response_version)))
        return seq

    def close(self, *, erase: bool) -> None:
        """Close the database; with `erase`, delete the file and its companions."""
        self.closed = True
        if self._checkpointer is not None:
            self._checkpointer.close()
        with contextlib.suppress(sqlite3.Error):
            self._db.close()
        if erase:
            for suffix in ("", *_SIDE_FILES):
                with contextlib.suppress(FileNotFoundError):
                    Path(f"{self._file}{suffix}").unlink()
