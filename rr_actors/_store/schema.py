"""The backup's rows: their SQL schema, how a file is created, migrated and checked, how a
row's values are encoded, decoded and cheaply checked, and the statements a write plans.

```
 empty file --MIGRATIONS[0]--> v1 --MIGRATIONS[1]--> v2 --MIGRATIONS[2]--> v3 --MIGRATIONS[3]--> v4
   --MIGRATIONS[4]--> v5 --MIGRATIONS[5]--> v6 --MIGRATIONS[6]--> v7 (SCHEMA_VERSION)
 request / response --dumps--> cloudpickle bytes (NULL for None) --> resources / clients row
 row --check_rows (no unpickling)--> Resource.encoded --decode, on first use--> value
 Changes (rid -> Resource | None, qid -> ClientRecord | None, rid -> the consumer ids added
   or released since the last write) --Written.plan (plan_resource / plan_client), against
   the mirror of what the store last wrote--> [(sql, params), ...] and the mirror entries
   that `Written.settle` sets once they committed (`GONE`: remove)
```

Each step is one transaction; a new file is made at once (`create`). The layout, the
digests and why a file is trusted only if its schema is exactly what these migrations
create: "The backup's file", docs/explanation/inside.md. `migrate` and `schema_version`
read `SCHEMA_VERSION` and `MIGRATIONS` from this module when they run (tests replace them
here). Values are stored as they cross between processes (`wire.dumps`; `NULL` for
`None`). Reading validates cheaply what it does not decode (a whole pickle, a known state,
no id twice), so a damaged row left on disk raises `CatalogCorruptError` when first used.
Only what differs from the mirror reaches the file, addressed by row key (`seq`), and of a
resource's consumers only the ids `Changes.consumers` names: a change costs the same
however large the catalog or widely shared the resource.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import pickle
import sqlite3
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from rr_actors._catalog import (
    DIGEST_SCHEME,
    NO_DIGEST,
    Changes,
    ClientRecord,
    Decoder,
    Resource,
    ResourceState,
    request_digest,
)
from rr_actors._catalog.texts import NOT_SHOWN_OLD
from rr_actors._core import wire
from rr_actors.errors import CatalogCorruptError

APPLICATION_ID = 0x72724163  # "rrAc": `PRAGMA application_id` of every catalog file

SCHEMA_VERSION = 7
"""The schema version this code writes; older files are migrated, newer ones refused."""

CREATED_VERSION = 7  # what `CREATE` makes: the objects of `MIGRATIONS[:7]` (a test checks)
CREATE = (
    "CREATE TABLE rr_actors_schema (version INTEGER NOT NULL, digest_scheme TEXT);"
    "CREATE TABLE clients (seq INTEGER PRIMARY KEY, query_id TEXT NOT NULL, server TEXT NOT "
    "NULL, serving_rr TEXT NOT NULL, origin_rr TEXT NOT NULL, request BLOB, response BLOB, "
    "parent TEXT, loaded INTEGER NOT NULL, request_text TEXT);CREATE TABLE resources (seq "
    "INTEGER PRIMARY KEY, id TEXT NOT NULL, server TEXT NOT NULL, state INTEGER NOT NULL, "
    "digest INTEGER, request BLOB, response BLOB, request_text TEXT, response_text TEXT, "
    "label TEXT, failed INTEGER NOT NULL DEFAULT 0);CREATE TABLE consumers (resource INTEGER "
    "NOT NULL, seq INTEGER NOT NULL, query_id TEXT NOT NULL, origin_rr TEXT NOT NULL, "
    "PRIMARY KEY (resource, seq)) WITHOUT ROWID;CREATE UNIQUE INDEX resources_by_id ON "
    "resources (id);CREATE INDEX resources_by_request ON resources (server, digest);CREATE "
    "INDEX resources_unsettled ON resources (seq) WHERE state != 1 OR digest IS NULL;CREATE "
    "UNIQUE INDEX consumers_by_query ON consumers (query_id);CREATE TABLE outbox (slot "
    "INTEGER PRIMARY KEY, pid INTEGER NOT NULL, seq INTEGER NOT NULL, event TEXT NOT NULL)"
)


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
    """v1 -> v2: a digest column (filled by `refresh_digests`), integer states, consumers
    keyed by their resource's row."""
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
    """v2 -> v3: indexes that let a restore leave served resources on disk until used."""
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
    """v3 -> v4: display texts (and a label) beside every stored value (`NOT_SHOWN_OLD`
    for the rows before)."""
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
    """v4 -> v5: consumer ids indexed, so a restore need not read them."""
    db.execute("CREATE UNIQUE INDEX consumers_by_query ON consumers (query_id)")


def _upgrade_v6(db: sqlite3.Connection) -> None:
    """v5 -> v6: a `failed` mark per resource (its provider reported it `FATAL`)."""
    db.execute("ALTER TABLE resources ADD COLUMN failed INTEGER NOT NULL DEFAULT 0")


def _upgrade_v7(db: sqlite3.Connection) -> None:
    """v6 -> v7: an outbox, the events of a change written in its transaction."""
    db.execute(
        "CREATE TABLE outbox (slot INTEGER PRIMARY KEY, pid INTEGER NOT NULL, "
        "seq INTEGER NOT NULL, event TEXT NOT NULL)"
    )


INDEXES = ("resources_by_id", "resources_by_request", "resources_unsettled", "consumers_by_query")

_UNSETTLED = "state != 1 OR digest IS NULL"  # the rows a restore reads at once

MIGRATIONS: tuple[Callable[[sqlite3.Connection], None], ...] = (
    _create_v1,
    _upgrade_v2,
    _upgrade_v3,
    _upgrade_v4,
    _upgrade_v5,
    _upgrade_v6,
    _upgrade_v7,
)
"""`MIGRATIONS[v]` brings a version-`v` file to version `v + 1` (0 is an empty file)."""
assert len(MIGRATIONS) == SCHEMA_VERSION


def rollback(db: sqlite3.Connection) -> None:
    """Roll back after a failure without hiding it (a failed COMMIT may have ended it)."""
    if db.in_transaction:
        with contextlib.suppress(sqlite3.Error):
            db.execute("ROLLBACK")


def schema_version(db: sqlite3.Connection, path: str) -> int:
    """Validate that `db` is an rr_actors catalog (`CatalogCorruptError`); its version."""
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
    """The schema objects version `version` has: made once per process, in memory."""
    return _objects_of(tuple(MIGRATIONS[:version]))


def check_objects(db: sqlite3.Connection, path: str, version: int) -> None:
    """Raise `CatalogCorruptError` unless `db`'s schema is exactly what version `version`
    has (type, name and SQL text of every object; only `sqlite_master` is read)."""
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


def create(db: sqlite3.Connection) -> None:
    """Make a catalog of `SCHEMA_VERSION` in the new, empty `db` in one transaction."""
    db.execute("BEGIN IMMEDIATE")  # (a failure: the file is not used)
    db.execute(f"PRAGMA application_id = {APPLICATION_ID}")
    for statement in CREATE.split(";"):
        db.execute(statement)
    db.execute("INSERT INTO rr_actors_schema VALUES (?, ?)", (CREATED_VERSION, DIGEST_SCHEME))
    for step in range(CREATED_VERSION, SCHEMA_VERSION):  # (tests add steps)
        MIGRATIONS[step](db)
        db.execute("UPDATE rr_actors_schema SET version = ?", (step + 1,))
    db.execute("COMMIT")


_IMAGES: dict[tuple[int, tuple[Callable[[sqlite3.Connection], None], ...]], bytes] = {}


def empty_image() -> bytes:
    """The bytes of an empty catalog file of `SCHEMA_VERSION` in WAL mode, made by SQLite in
    memory once a process (the forkserver's preload: once for every manager process), that
    `files.create` writes as a new backup: no connection, no statement, per file."""
    key = (SCHEMA_VERSION, MIGRATIONS)
    if key not in _IMAGES:
        db = sqlite3.connect(":memory:", isolation_level=None)
        create(db)
        image = bytearray(db.serialize())
        db.close()
        image[18:20] = b"\x02\x02"  # the header's file format versions: 2, WAL (SQLite's format)
        _IMAGES[key] = bytes(image)
    return _IMAGES[key]


def refresh_digests(db: sqlite3.Connection, name: str) -> None:
    """Recompute every stored digest if they were written under another `DIGEST_SCHEME`
    (one transaction; a request that cannot be decoded keeps `NULL`)."""
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


# -- a row's values ---------------------------------------------------------------------------

STATE_CODES = {ResourceState.LOADING: 0, ResourceState.LOADED: 1, ResourceState.UNLOADING: 2}
STATES_BY_CODE = tuple(STATE_CODES)


def dumps(value: Any) -> bytes | None:
    """Encode a request or response for a row (`None` is stored as `NULL`)."""
    return None if value is None else wire.dumps(value)


def loads(blob: bytes | None) -> Any:
    return None if blob is None else pickle.loads(blob)


def decode(path: str, rid: str, field: str, blob: bytes | None) -> Any:
    """Decode a restored resource's stored value on first use (`CatalogCorruptError`)."""
    try:
        return loads(blob)
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


def check_rows(
    rows: list[Any],
    consumer_rows: Sequence[Any] = (),
    client_rows: Sequence[Any] = (),
    *,
    values: bool = True,
) -> None:
    """Raise `ValueError` for a resource row with an unknown state or (`values`) a request
    or response that cannot be a pickle (a cheap check of what a restore leaves encoded),
    or for an id stored twice (it would replace the first silently)."""
    for row in rows:
        state = row[3]
        if type(state) is not int or not 0 <= state < len(STATES_BY_CODE):
            raise ValueError(f"resource {row[1]} has an unknown state {state!r}")
        if values and (_not_a_pickle(row[5]) or _not_a_pickle(row[6])):
            raise ValueError(f"the stored request or response of resource {row[1]} is not a pickle")
    for what, ids in (
        ("resource id", [row[1] for row in rows]),
        ("consumer query id", [row[1] for row in consumer_rows]),
        ("client query id", [row[1] for row in client_rows]),
    ):
        if len(set(ids)) != len(ids):
            raise ValueError(f"{what} {first_duplicate(ids)} is stored twice")


def first_duplicate(values: list[Any]) -> Any:
    seen: set[Any] = set()
    for value in values:
        if value in seen:
            return value
        seen.add(value)
    return None


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


@dataclasses.dataclass(frozen=True)
class NotUnpickled:
    """Stands for a stored request or response that was not unpickled (`size`: of the
    pickle, in bytes)."""

    size: int

    def __repr__(self) -> str:
        return f"<not unpickled, {self.size} bytes>"


def not_unpickled(_rid: str, _field: str, blob: bytes | None) -> Any:
    return None if blob is None else NotUnpickled(len(blob) if type(blob) is bytes else 0)


def lenient_decode(_rid: str, _field: str, blob: bytes | None) -> Any:
    """Decode a stored value, or stand for it with an `Unreadable` (inspection)."""
    try:
        return loads(blob)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is shown, not raised
        return Unreadable(f"{type(exc).__name__}: {exc}", len(blob or b""))


_DAMAGE_CODES = frozenset({"SQLITE_CORRUPT", "SQLITE_NOTADB"})  # pages not as written


def damaged_file(exc: BaseException) -> bool:
    """Whether SQLite raised `exc` because the file's pages are damaged (not a row)."""
    if not isinstance(exc, sqlite3.DatabaseError):
        return False
    code = getattr(exc, "sqlite_errorname", None)
    if code is not None:
        return any(code == c or code.startswith(f"{c}_") for c in _DAMAGE_CODES)
    return "malformed" in str(exc) or "not a database" in str(exc)


@contextlib.contextmanager
def as_corrupt(path: str, on_damage: Callable[[str], None] | None = None) -> Iterator[None]:
    """Raise `CatalogCorruptError`, naming `path`, for what SQLite, unpickling or a row
    check raises (`on_damage` told first when the pages are damaged)."""
    try:
        yield
    except sqlite3.DatabaseError as exc:
        why = f"{type(exc).__name__}: {exc}"
        if on_damage is not None and damaged_file(exc):
            on_damage(why)
        raise CatalogCorruptError(path, why) from exc
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


# -- what a write changes: the statements from the mirror to the catalog's rows --------------


class Mirror:
    """What the store last wrote for one resource (to write only the difference)."""

    __slots__ = ("consumers", "failed", "response_version", "seq", "state", "texts")

    def __init__(
        self,
        seq: int,
        state: ResourceState,
        response_version: int,
        consumers: dict[str, int],
        texts: Texts = (None, None, None),
        failed: bool = False,
    ) -> None:
        self.seq = seq  # the row's key
        self.state = state
        # The catalog bumps `Resource.response_version` on every response it sets (also
        # the same object again, mutated); decoding a restored one does not.
        self.response_version = response_version
        self.consumers = consumers  # consumer query id -> its row's key
        self.texts = texts  # (request_text, response_text, label) as written
        self.failed = failed  # the `failed` mark as written


Texts = tuple[str | None, str | None, str | None]
"""A resource row's `(request_text, response_text, label)`."""


Op = tuple[str, tuple[Any, ...]]  # one planned SQL statement and its parameters
GONE = object()  # a mirror entry to delete once a write committed


def plan_resource(
    written: dict[str, Mirror],
    ops: list[Op],
    mirrors: list[tuple[dict[str, Any], str, Any]],
    rid: str,
    resource: Resource | None,
    seq: int,
    touched: dict[str, None] | None = None,
) -> int:
    """Append to `ops` the statements for resource `rid` (`None`: removed), and to `mirrors`
    the `(table, key, value)` entries to set once they committed; the last row key.
    `touched`: the consumer ids to look at (`None`: every one)."""
    old = written.get(rid)
    if resource is None:
        if old is not None:
            ops.append(("DELETE FROM resources WHERE seq = ?", (old.seq,)))
            ops.append(("DELETE FROM consumers WHERE resource = ?", (old.seq,)))
            mirrors.append((written, rid, GONE))
        return seq
    texts = (resource.request_text, resource.response_text, resource.label)
    if old is None:
        seq += 1
        digest = resource.digest
        if digest is None:
            digest = request_digest(resource.request)
        ops.append(
            (
                "INSERT INTO resources (seq, id, server, state, digest, request, response, "
                "request_text, response_text, label, failed) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    seq,
                    rid,
                    resource.server,
                    STATE_CODES[resource.state],
                    None if digest == NO_DIGEST else digest,
                    dumps(resource.request),
                    dumps(resource.response),
                    *texts,
                    int(resource.failed),
                ),
            )
        )
        keys: dict[str, int] = {}
        row = seq
        touched = None
        update: Op | None = None
    else:
        update = None
        if (
            old.response_version != resource.response_version
            or old.state is not resource.state
            or old.texts != texts
            or old.failed != resource.failed
        ):
            update = _resource_update(old, resource, texts)
            ops.append(update)
        keys = old.consumers
        row = old.seq
    now = resource.consumers
    if touched is None:  # every consumer, against the mirror
        touched = {**dict.fromkeys(now), **dict.fromkeys(keys)}
    for query_id in touched:  # one INSERT or DELETE each whose row differs from `now`
        key = keys.get(query_id)
        if query_id in now:
            if key is None:
                seq += 1
                ops.append(
                    (
                        "INSERT INTO consumers (resource, seq, query_id, origin_rr) "
                        "VALUES (?, ?, ?, ?)",
                        (row, seq, query_id, now[query_id]),
                    )
                )
                mirrors.append((keys, query_id, seq))
        elif key is not None:
            ops.append(("DELETE FROM consumers WHERE resource = ? AND seq = ?", (row, key)))
            mirrors.append((keys, query_id, GONE))
    if old is None or update is not None:
        # (the consumer keys stay in `keys`, the one dict: changed in place once committed)
        mirror = Mirror(
            row, resource.state, resource.response_version, keys, texts, resource.failed
        )
        mirrors.append((written, rid, mirror))
    return seq


def _resource_update(old: Mirror, resource: Resource, texts: Texts) -> Op:
    """The one `UPDATE` that brings a written resource row up to date."""
    columns: list[str] = []
    values: list[Any] = []
    if old.response_version != resource.response_version:
        columns += ["state", "response"]
        values += [STATE_CODES[resource.state], dumps(resource.response)]
    elif old.state is not resource.state:
        columns.append("state")
        values.append(STATE_CODES[resource.state])
    if old.texts != texts:
        columns += ["request_text", "response_text", "label"]
        values += texts
    if old.failed != resource.failed:
        columns.append("failed")
        values.append(int(resource.failed))
    assignments = ", ".join(f"{column} = ?" for column in columns)
    sql = f"UPDATE resources SET {assignments} WHERE seq = ?"  # noqa: S608 - our column names
    return (sql, (*values, old.seq))


def plan_client(
    written: dict[str, tuple[int, int, str | None]],
    ops: list[Op],
    mirrors: list[tuple[dict[str, Any], str, Any]],
    qid: str,
    record: ClientRecord | None,
    seq: int,
) -> int:
    """Plan the statements for client record `qid` (`None`: removed), as `plan_resource`
    (`written`: query id -> `(row key, response_version, request_text)`)."""
    old = written.get(qid)
    if record is None:
        if old is not None:
            ops.append(("DELETE FROM clients WHERE seq = ?", (old[0],)))
            mirrors.append((written, qid, GONE))
        return seq
    query = record.query
    if old is None:
        seq += 1
        row = seq
        ops.append(
            (
                "INSERT INTO clients (seq, query_id, server, serving_rr, origin_rr, request, "
                "response, parent, loaded, request_text) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    seq,
                    qid,
                    query.server,
                    query.serving_rr,
                    query.origin_rr,
                    dumps(query.request),
                    dumps(query.response),
                    record.parent,
                    int(record.loaded),
                    record.request_text,
                ),
            )
        )
    elif old[1] == record.response_version:
        row = old[0]
        ops.append(
            (
                "UPDATE clients SET loaded = ?, request_text = ? WHERE seq = ?",
                (int(record.loaded), record.request_text, row),
            )
        )
    else:
        row = old[0]
        ops.append(
            (
                "UPDATE clients SET response = ?, loaded = ?, request_text = ? WHERE seq = ?",
                (dumps(query.response), int(record.loaded), record.request_text, row),
            )
        )
    mirrors.append((written, qid, (row, record.response_version, record.request_text)))
    return seq


class Written:
    """What a store last wrote, so that a write plans only the difference: each resource's
    `Mirror`, each client's `(row key, response_version, request_text)`, the last row key."""

    def __init__(self, seq: int = 0) -> None:
        self.resources: dict[str, Mirror] = {}
        self.clients: dict[str, tuple[int, int, str | None]] = {}
        self.seq = seq

    def plan(self, changes: Changes, owed: set[str]) -> tuple[list[Op], list[Any], int]:
        """The statements that write `changes` (of a resource in `owed`, every consumer
        compared), the mirror entries to `settle` once they committed, the last row key."""
        ops: list[Op] = []
        mirrors: list[tuple[dict[str, Any], str, Any]] = []  # (table, key, value | GONE)
        seq, touched = self.seq, changes.consumers
        for rid, resource in changes.resources.items():
            ids = None if rid in owed else touched.get(rid)
            seq = plan_resource(self.resources, ops, mirrors, rid, resource, seq, ids)
        for qid, record in changes.clients.items():
            seq = plan_client(self.clients, ops, mirrors, qid, record, seq)
        return ops, mirrors, seq

    def settle(self, mirrors: list[Any], seq: int) -> None:
        self.seq = seq
        for table, key, value in mirrors:
            if value is GONE:
                table.pop(key, None)
            else:
                table[key] = value

    def adopt(self, row: Any, consumer_rows: list[Any], decode: Decoder) -> Resource:
        """Build a stored resource with its consumers from its rows, and mirror it."""
        seq, rid, server, state, digest, request, response, *texts, failed = row
        resource = Resource.encoded(
            rid,
            server,
            STATES_BY_CODE[state],
            NO_DIGEST if digest is None else digest,
            (request, response),
            decode,
            seq,
            (texts[0], texts[1], texts[2]),
            failed=bool(failed),
        )
        keys = {}
        for key, query_id, origin in consumer_rows:
            resource.consumers[query_id] = origin
            keys[query_id] = key
            self.seq = max(self.seq, key)  # its next consumer's key comes after these
        self.resources[rid] = Mirror(
            seq, resource.state, 0, keys, (texts[0], texts[1], texts[2]), resource.failed
        )
        return resource

    def mirrored(self, last: int) -> tuple[int, int]:
        """Mirrored resource rows with a key up to `last`, and their consumer rows."""
        resources = consumers = 0
        for mirror in self.resources.values():
            if mirror.seq <= last:
                resources += 1
                consumers += len(mirror.consumers)
        return resources, consumers
