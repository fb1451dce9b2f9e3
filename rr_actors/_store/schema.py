"""The backup's schema: its version, how a file is created and migrated, how it is checked.

Layout (schema version 7):

* `rr_actors_schema(version, digest_scheme)`: one row, the schema version and the
  `DIGEST_SCHEME` of the stored digests; `PRAGMA application_id` marks the file as an
  rr_actors catalog.
* `resources(seq, id, server, state, digest, request, response, request_text,
  response_text, label, failed)`: served resources, `seq` being the insertion order,
  `state` 0/1/2 (loading/loaded/unloading), `digest` the request's `request_digest`
  (`NULL` if it has none), the `*_text` columns the bounded `repr`s the owning registrar
  made of the values, `label` what its server's `label(request)` returned (`NULL`: not
  made yet, or none), `failed` 1 once its provider reported it `FATAL` (never matched
  again), else 0. Indexed by `id` (unique), by `(server, digest)`, and (partial index) the rows
  not loaded or without a digest.
* `consumers(resource, seq, query_id, origin_rr)`: consumer ids, `resource` being the `seq`
  of their resource; clustered by `(resource, seq)` (`WITHOUT ROWID`), so a scan yields
  each resource's consumers together, in arrival order; a unique index on `query_id`
  finds a consumer id's resource without reading the others (a restore reads no
  consumer id until a call needs it).
* `clients(seq, query_id, server, serving_rr, origin_rr, request, response, parent,
  loaded, request_text)`: outbound queries (`parent` set for dependencies).
* `outbox(slot, pid, seq, event)`: the events that tell of the last changes, written in
  their transaction (`outbox.py`): a ring of `outbox.SLOTS` rows, `event` the JSON
  text `[events schema, type, field values...]`, emptied at each open.

The display texts let a reader show a backup without unpickling anything (unpickling
runs code from the file: `rr-actors observe --state` and `graph --state` never do).

```
 empty file --MIGRATIONS[0]--> v1 --MIGRATIONS[1]--> v2 --MIGRATIONS[2]--> v3 --MIGRATIONS[3]--> v4
   --MIGRATIONS[4]--> v5 --MIGRATIONS[5]--> v6 --MIGRATIONS[6]--> v7 (SCHEMA_VERSION)
```

Each step is one transaction (`migrate`). The stored digest is deterministic (BLAKE2b of
strings, numbers' own `hash()`), never the per-process `hash()` of a string, so a restore
indexes every resource from its digest alone and leaves its request and response encoded
until first used. A file whose digests were written under another `DIGEST_SCHEME`
(another Python version or word size) has them recomputed, in one transaction, when it
is opened (`refresh_digests`).

A file is trusted only if its schema is exactly what these migrations create
(`check_objects`: every table a table, every index an index, the same SQL text, no view
or trigger): a `resources` that is a view over an endless query would otherwise make a
plain read fill the disk.

`migrate` and `schema_version` read `SCHEMA_VERSION` and `MIGRATIONS` from this module
when they run (tests replace them here to add a version).
"""

from __future__ import annotations

import contextlib
import functools
import sqlite3
from collections.abc import Callable
from typing import Any

from rr_actors._catalog import DIGEST_SCHEME, request_digest
from rr_actors._catalog.texts import NOT_SHOWN_OLD
from rr_actors._store.codec import as_corrupt, loads
from rr_actors.errors import CatalogCorruptError

__all__ = [
    "APPLICATION_ID",
    "INDEXES",
    "MIGRATIONS",
    "SCHEMA_VERSION",
    "check_objects",
    "expected_objects",
    "migrate",
    "refresh_digests",
    "rollback",
    "schema_version",
]

APPLICATION_ID = 0x72724163  # "rrAc"
"""`PRAGMA application_id` of every rr_actors catalog file."""

SCHEMA_VERSION = 7
"""The schema version this code writes; older files are migrated, newer ones refused."""


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


def _upgrade_v2(db: sqlite3.Connection) -> None:
    """v1 -> v2: a digest column, integer states, consumers keyed by their resource's row.

    The digests are filled in by `refresh_digests` (the scheme is still `NULL`). A row
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


def _upgrade_v4(db: sqlite3.Connection) -> None:
    """v3 -> v4: display texts (and a label) beside every stored value.

    Rows written before have none: they read `NOT_SHOWN_OLD` (nothing is unpickled to
    make one: the file may not be the reader's).
    """
    for table, column in (
        ("resources", "request_text"),
        ("resources", "response_text"),
        ("resources", "label"),
        ("clients", "request_text"),
    ):
        db.execute(f"ALTER TABLE {table} ADD COLUMN {column} TEXT")
    db.execute(
        "UPDATE resources SET request_text = ?, response_text = ?", (NOT_SHOWN_OLD, NOT_SHOWN_OLD)
    )
    db.execute("UPDATE clients SET request_text = ?", (NOT_SHOWN_OLD,))


def _upgrade_v5(db: sqlite3.Connection) -> None:
    """v4 -> v5: consumer ids indexed, so a restore need not read them (issue 34).

    A restart used to read every consumer id into memory before it served (the only
    part of a restore that grew with the catalog); a call now finds its id through this
    index. A file with a consumer id stored twice fails here (`UNIQUE constraint failed`).
    """
    db.execute("CREATE UNIQUE INDEX consumers_by_query ON consumers (query_id)")


def _upgrade_v6(db: sqlite3.Connection) -> None:
    """v5 -> v6: a `failed` mark per resource (its provider reported it `FATAL`).

    A resource marked so is never matched by an equal request again, also after a
    restore. Rows written before have none (0): the version that wrote them matched a
    dead resource like a live one, and kept no mark to restore.
    """
    db.execute("ALTER TABLE resources ADD COLUMN failed INTEGER NOT NULL DEFAULT 0")


def _upgrade_v7(db: sqlite3.Connection) -> None:
    """v6 -> v7: an outbox, the events of a change written in its transaction (issue 40).

    A SIGKILL between a commit and the publishing of the events that tell of it lost
    them, with no gap to show it; the supervisor's side reads them from here after the
    exit (`outbox.py`). A file written before has none to read.
    """
    db.execute(
        "CREATE TABLE outbox (slot INTEGER PRIMARY KEY, pid INTEGER NOT NULL, "
        "seq INTEGER NOT NULL, event TEXT NOT NULL)"
    )


INDEXES = ("resources_by_id", "resources_by_request", "resources_unsettled", "consumers_by_query")
"""The indexes of a current file: a restore relies on them (unique ids, dedup, doubt)."""

_UNSETTLED = "state != 1 OR digest IS NULL"
"""Resources a restore reads at once: in doubt (not loaded), or indexed by their value."""

MIGRATIONS: tuple[Callable[[sqlite3.Connection], None], ...] = (
    _create_v1,
    _upgrade_v2,
    _upgrade_v3,
    _upgrade_v4,
    _upgrade_v5,
    _upgrade_v6,
    _upgrade_v7,
)
"""`MIGRATIONS[v]` brings a version-`v` file to version `v + 1` (0 is an empty file).

To change the schema: append a migration, bump `SCHEMA_VERSION`, add a test that opens a
file written by the previous version. Never edit a released migration.
"""
assert len(MIGRATIONS) == SCHEMA_VERSION


def rollback(db: sqlite3.Connection) -> None:
    """Roll back after a failure without hiding it (a failed COMMIT may have ended it)."""
    if db.in_transaction:
        with contextlib.suppress(sqlite3.Error):
            db.execute("ROLLBACK")


def schema_version(db: sqlite3.Connection, path: str) -> int:
    """Validate that `db` is an rr_actors catalog and return its schema version.

    Raises:
        CatalogCorruptError: it is not one (another program's database, a newer schema,
            a missing index, ...), naming `path`.
    """
    application_id = db.execute("PRAGMA application_id").fetchone()[0]
    tables = sorted(
        row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")
    )
    if application_id != APPLICATION_ID or "rr_actors_schema" not in tables:
        raise CatalogCorruptError(
            path,
            f"not an rr_actors catalog (application_id {application_id:#x}, tables {tables})",
        )
    rows = db.execute("SELECT version FROM rr_actors_schema LIMIT 2").fetchall()
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
    if version == SCHEMA_VERSION:  # (first: its own message)
        indexes = {
            row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type = 'index'")
        }
        for index in INDEXES:
            if index not in indexes:
                raise CatalogCorruptError(path, f"index {index} is missing")
    check_objects(db, path, version)
    return version


def _normal(sql: str | None) -> str | None:
    """SQL text compared as words: case, quotes and spacing aside."""
    if sql is None:
        return None
    return " ".join(sql.replace('"', " ").replace("(", " ( ").replace(",", " , ").split()).lower()


@functools.cache
def _objects_of(migrations: tuple[Callable[[sqlite3.Connection], None], ...]) -> frozenset[Any]:
    """The schema objects `(type, name, table, SQL)` these migrations create, in memory."""
    db = sqlite3.connect(":memory:", isolation_level=None)
    try:
        for step in migrations:
            step(db)
        rows = db.execute("SELECT type, name, tbl_name, sql FROM sqlite_master").fetchall()
    finally:
        db.close()
    return frozenset((kind, name, table, _normal(sql)) for kind, name, table, sql in rows)


def expected_objects(version: int = SCHEMA_VERSION) -> frozenset[Any]:
    """The schema objects version `version` has: made once per process, in memory.

    Making them runs every migration (2-3 ms): a spare manager process does it while it
    idles (`rr_actors._process.child`), not its restore after a crash.
    """
    return _objects_of(tuple(MIGRATIONS[:version]))


def check_objects(db: sqlite3.Connection, path: str, version: int) -> None:
    """Raise `CatalogCorruptError` unless `db`'s schema is exactly what version `version` has.

    Every table, index, view and trigger is compared with what `MIGRATIONS[:version]`
    create (type, name and SQL text): a view or a trigger in place of, or next to, a
    table could make a read run any query (an endless recursive one fills the disk
    with temporary data). Nothing but `sqlite_master` is read.

    Raises:
        CatalogCorruptError: an object is not what it should be, naming `path` and it.
    """
    expected = expected_objects(version)
    rows = db.execute("SELECT type, name, tbl_name, sql FROM sqlite_master LIMIT 1000").fetchall()
    found = {(kind, name, table, _normal(sql)) for kind, name, table, sql in rows}
    known = {o[1]: o[0] for o in expected}
    problems = []
    for kind, name, _, sql in found - expected:
        if name in known and known[name] != kind:
            problems.append((0, name, f"{name!r} is a {kind}, not a {known[name]}"))
        elif name in known:
            problems.append((1, name, f"the {kind} {name!r} is not as rr_actors creates it: {sql}"))
        else:
            problems.append((2, name, f"an unknown {kind} {name!r}"))
    if problems:
        why = min(problems)[2]  # the most telling one: a known name of another kind first
        raise CatalogCorruptError(path, f"not an rr_actors schema (version {version}): {why}")
    missing = sorted(o[1] for o in expected - found)
    if missing:
        raise CatalogCorruptError(path, f"schema version {version} lacks {', '.join(missing)}")


def migrate(db: sqlite3.Connection, version: int) -> None:
    """Bring `db` from `version` to `SCHEMA_VERSION`, each step one transaction."""
    for step in range(version, SCHEMA_VERSION):
        db.execute("BEGIN IMMEDIATE")
        try:
            MIGRATIONS[step](db)
            db.execute("UPDATE rr_actors_schema SET version = ?", (step + 1,))
        except BaseException:
            rollback(db)
            raise
        db.execute("COMMIT")


def refresh_digests(db: sqlite3.Connection, name: str) -> None:
    """Recompute every stored digest if they were written under another `DIGEST_SCHEME`.

    One transaction; a request that cannot be decoded here keeps a `NULL` digest (the
    restore then decodes it, and reports it as `CatalogCorruptError`).

    Raises:
        CatalogCorruptError: SQLite reports the file damaged (naming `name`).
    """
    with as_corrupt(name):
        scheme = db.execute("SELECT digest_scheme FROM rr_actors_schema").fetchone()[0]
        if scheme == DIGEST_SCHEME:
            return
        db.execute("BEGIN IMMEDIATE")
        try:
            updates = []
            for seq, blob in db.execute("SELECT seq, request FROM resources").fetchall():
                try:
                    digest = request_digest(loads(blob))
                except Exception:  # noqa: BLE001 - reported when the row is restored
                    digest = None
                updates.append((digest, seq))
            db.executemany("UPDATE resources SET digest = ? WHERE seq = ?", updates)
            db.execute("UPDATE rr_actors_schema SET digest_scheme = ?", (DIGEST_SCHEME,))
        except BaseException:
            rollback(db)
            raise
        db.execute("COMMIT")
