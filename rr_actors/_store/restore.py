"""Reading a backup back: lazily for a registrar (`Unread`), or every row at once
(`read_rows`: `SqliteStore.load`, and `read_backup` for inspection).

```
 SqliteStore.restore --read_at_once, one read transaction--> resources in doubt, without
                   a digest or with a dependency, and every client record (as rows):
                   nothing more --> Restored(resources, clients, unread), the store's mirror
 Catalog lookup (digest, consumer id, server, origin) --Unread--> rows read, checked, adopted:
                   the store mirrors them (`SqliteStore.adopt`), memory is the truth from then on
 after it serves: the registrar sweeps the rest in slices (`Unread.sweep`): unheld
                   resources and consumers' registrars, between calls
 read_backup: `files.inspected` (checked, read only, migrated in memory), then every row:
                   read_rows, one snapshot (also `SqliteStore.load`), the collector paused
```

So what a restart reads before it serves does not grow with the catalog: each other row
is read through the indexes when the catalog first looks it up. Either way a restored
resource keeps its values encoded until first used (`Resource.encoded`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import os
import sqlite3
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Protocol

from rr_actors._catalog import NO_DIGEST, ClientRecord, Decoder, Listing, Resource
from rr_actors._store import files, schema
from rr_actors._types import Query
from rr_actors.errors import CatalogCorruptError, RegistrarStoppedError

RESOURCE_COLUMNS = (
    "seq, id, server, state, digest, request, response, request_text, response_text, label, failed"
)
"""The columns of a resource row, in the order every reader reads them."""

CLIENT_COLUMNS = (
    "seq, query_id, server, serving_rr, origin_rr, request, response, parent, loaded, request_text"
)
"""The columns of a client row, in the order every reader reads them."""


def client_records(
    client_rows: list[Any], decode: Decoder
) -> tuple[list[ClientRecord], dict[str, tuple[int, int, str | None]]]:
    """Client records from their rows (oldest first), and their mirror (`Written.clients`)."""
    clients = []
    mirror = {}
    for row in client_rows:
        seq, qid, server, serving, origin, request, response, parent, loaded, text = row
        query = Query(
            qid,
            server,
            serving,
            origin,
            decode(qid, "request", request),
            decode(qid, "response", response),
        )
        clients.append(ClientRecord(query, parent, bool(loaded), request_text=text))
        mirror[qid] = (seq, 0, text)
    return clients, mirror


_LISTED_RESOURCES = (  # a resource as `Catalog.rows` lists it: (id, server, state, digest, failed)
    "SELECT seq, id, server, CASE state "  # noqa: S608
    + " ".join(
        f"WHEN {code} THEN '{state.value}'" for code, state in enumerate(schema.STATES_BY_CODE)
    )
    + " ELSE CAST(state AS TEXT) END, coalesce(CAST(digest AS TEXT), ''), "
    "CASE WHEN failed THEN 'failed' ELSE '' END FROM resources WHERE seq <= ? ORDER BY seq LIMIT ?"
)  # (unread rows are loaded, with a digest: the `ELSE` is never taken)

_LISTED_CONSUMERS = (
    "SELECT c.resource, c.query_id, r.id, c.origin_rr FROM consumers c "
    "JOIN resources r ON r.seq = c.resource WHERE c.resource <= ? "
    "ORDER BY c.resource, c.seq LIMIT ?"
)

# (S608: the SQL is built from this module's constants only)
RESOURCES = f"SELECT {RESOURCE_COLUMNS} FROM resources ORDER BY seq"  # noqa: S608
_RESOURCE_BY_SEQ = f"SELECT {RESOURCE_COLUMNS} FROM resources WHERE seq = ?"  # noqa: S608
RESOURCES_AT_ONCE = (  # what a restore reads as rows: in doubt, no digest, or a parent
    f"SELECT {RESOURCE_COLUMNS} FROM resources "  # noqa: S608
    "WHERE state != 1 OR digest IS NULL "  # == _UNSETTLED: the partial index serves it
    f"UNION SELECT {RESOURCE_COLUMNS} FROM resources "
    "WHERE id IN (SELECT parent FROM clients WHERE parent IS NOT NULL) ORDER BY seq"
)
CONSUMERS_OF = (  # one key range of the (resource, seq) key: in arrival order
    "SELECT seq, query_id, origin_rr FROM consumers WHERE resource = ?"
)
CLIENTS = f"SELECT {CLIENT_COLUMNS} FROM clients ORDER BY seq"  # noqa: S608
_RESOURCE_OF = "SELECT resource FROM consumers WHERE query_id = ?"  # index consumers_by_query


class RowStore(Protocol):
    """What `Unread` reads the rows it was left through (`SqliteStore` is one)."""

    path: str
    closed: bool

    @property
    def connection(self) -> sqlite3.Connection: ...

    def adopt(self, row: Any, consumer_rows: list[Any]) -> Resource: ...

    def mirrored(self, last: int) -> tuple[int, int]: ...

    def found_damaged(self, why: str) -> None: ...


SWEEP_ROWS = 2_000  # restored resources one slice of `Unread.sweep` looks at


class Unread:
    """The served resources of a restored backup not in memory yet (`UnreadRows`): one read
    is adopted by the store and never returned again; rows after `last` are never read."""

    def __init__(self, store: RowStore, last: int, read: set[int], *, remaining: bool) -> None:
        self._store = store
        self._last = last
        self._read = read  # row keys of restored resources already in memory
        self.remaining = remaining

    def by_request(self, server: str, digest: int) -> list[Resource]:
        """Unread resources of `server` whose request digest is `digest`."""
        return self._fetch(
            "SELECT seq FROM resources WHERE server = ? AND digest = ? AND seq <= ?",
            (server, digest, self._last),
        )

    def by_consumer(self, query_id: str) -> Resource | None:
        """The unread resource that has consumer `query_id`, if any (one index lookup)."""
        if not self.remaining:
            return None
        self._check_open()
        with self._reading():
            row = self._store.connection.execute(_RESOURCE_OF, (query_id,)).fetchone()
            seq = None if row is None else int(row[0])
        if seq is None or seq > self._last or seq in self._read:
            return None  # unknown, the catalog's own, or in memory (memory is the truth)
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

    def consumer_ids_from(self, origin_rr: str) -> list[str]:
        """The consumer ids of unread resources that `origin_rr` holds (none is read)."""
        if not self.remaining:
            return []
        self._check_open()
        with self._reading():
            rows = self._store.connection.execute(
                "SELECT query_id, resource FROM consumers WHERE origin_rr = ? AND resource <= ?",
                (origin_rr, self._last),
            ).fetchall()
        return [query_id for query_id, resource in rows if resource not in self._read]

    def sweep(self, after: int) -> tuple[list[Resource], set[str], int | None]:
        """Look at the next `SWEEP_ROWS` restored resources (as `Catalog.sweep`)."""
        if not self.remaining:
            return [], set(), None
        self._check_open()
        with self._reading():
            db = self._store.connection
            looked_at, upto = db.execute(
                "SELECT count(*), max(seq) FROM (SELECT seq FROM resources "
                "WHERE seq > ? AND seq <= ? ORDER BY seq LIMIT ?)",
                (after, self._last, SWEEP_ROWS),
            ).fetchone()
            if upto is None:
                return [], set(), None
            origins = {
                origin
                for (origin,) in db.execute(
                    "SELECT DISTINCT origin_rr FROM consumers WHERE resource > ? AND resource <= ?",
                    (after, upto),
                )
            }
        unheld = self._fetch(
            "SELECT seq FROM resources r WHERE seq > ? AND seq <= ? AND state = 1 AND NOT "
            "EXISTS (SELECT 1 FROM consumers c WHERE c.resource = r.seq) ORDER BY seq",
            (after, upto),
        )
        return unheld, origins, upto if looked_at == SWEEP_ROWS else None

    def every(self) -> list[Resource]:
        """Every unread resource, oldest first."""
        resources = self._fetch(
            "SELECT seq FROM resources WHERE seq <= ? ORDER BY seq", (self._last,)
        )
        self.remaining = False
        return resources

    def listing(self, limit: int) -> Listing | None:
        """The unread resources and consumers as rows keyed by row key, without reading
        them (as `Catalog.rows`); `None` if either kind has more than `limit`."""
        if not self.remaining:
            return [], []
        self._check_open()
        mirrored = self._store.mirrored(self._last)
        with self._reading():  # (the rows come out as strings: no per-field Python work)
            db = self._store.connection
            last = self._last
            rows = db.execute(_LISTED_RESOURCES, (last, limit + mirrored[0] + 1)).fetchall()
            consumers = db.execute(_LISTED_CONSUMERS, (last, limit + mirrored[1] + 1)).fetchall()
        read = self._read
        if read:
            rows = [row for row in rows if row[0] not in read]
            consumers = [row for row in consumers if row[0] not in read]
        if len(rows) > limit or len(consumers) > limit:
            return None
        return rows, consumers

    def counts(self) -> tuple[int, int]:
        """How many resources and consumer ids are unread (two counts of the file)."""
        if not self.remaining:
            return 0, 0
        self._check_open()
        mirrored = self._store.mirrored(self._last)
        with self._reading():
            db = self._store.connection
            (resources,) = db.execute(
                "SELECT count(*) FROM resources WHERE seq <= ?", (self._last,)
            ).fetchone()
            (consumers,) = db.execute(
                "SELECT count(*) FROM consumers WHERE resource <= ?", (self._last,)
            ).fetchone()
        return resources - mirrored[0], consumers - mirrored[1]

    def _fetch(self, sql: str, args: tuple[Any, ...]) -> list[Resource]:
        if not self.remaining:
            return []
        self._check_open()
        with self._reading():
            seqs = [
                seq for (seq,) in self._store.connection.execute(sql, args) if seq not in self._read
            ]
        return self._take(seqs)

    def _take(self, seqs: list[int]) -> list[Resource]:
        """Read resource rows `seqs` with their consumers; hand over all of them or none."""
        store = self._store
        db = store.connection
        read = []
        with self._reading():
            for seq in seqs:
                row = db.execute(_RESOURCE_BY_SEQ, (seq,)).fetchone()
                if row is None:
                    continue
                schema.check_rows([row])
                read.append((row, db.execute(CONSUMERS_OF, (seq,)).fetchall()))
        resources = [store.adopt(row, consumers) for row, consumers in read]
        self._read.update(row[0] for row, _ in read)
        return resources

    def _reading(self) -> contextlib.AbstractContextManager[None]:
        """`schema.as_corrupt`; damage SQLite reports turns the store read-only."""
        return schema.as_corrupt(self._store.path, self._store.found_damaged)

    def _check_open(self) -> None:
        if self._store.closed:
            raise RegistrarStoppedError(
                f"the catalog backup {self._store.path!r} was closed (its registrar stopped)"
            )


@dataclasses.dataclass
class Restored:
    """What `SqliteStore.restore` read: enough to serve, the rest (`unread`) on first use."""

    resources: list[Resource]
    clients: list[ClientRecord]
    unread: Unread


def read_at_once(store: RowStore, decode: Decoder) -> tuple[Restored, schema.Written]:
    """What a restore reads before it serves, in one read transaction, and the mirror of it
    (`SqliteStore.restore`): the resource rows in doubt (`RESOURCES_AT_ONCE`), checked
    (`ValueError`) and adopted with their consumer rows; every client record; the other
    resource rows left unread (`Unread`)."""
    db = store.connection
    db.execute("BEGIN")
    try:
        (last,) = db.execute("SELECT ifnull(max(seq), 0) FROM resources").fetchone()
        rows = db.execute(RESOURCES_AT_ONCE).fetchall()
        client_rows = db.execute(CLIENTS).fetchall()
        more = db.execute(  # (at most len(rows) + 1 keys)
            "SELECT seq FROM resources ORDER BY seq LIMIT ?", (len(rows) + 1,)
        ).fetchall()
        schema.check_rows(rows, [], client_rows)
        with_consumers = [(row, db.execute(CONSUMERS_OF, (row[0],)).fetchall()) for row in rows]
    finally:
        db.execute("COMMIT")
    # (`adopt` raises `seq` past each resource's consumer keys: no scan of them all)
    written = schema.Written(max([last, *(row[0] for row in client_rows[-1:])]))
    resources = [written.adopt(row, consumers, decode) for row, consumers in with_consumers]
    for resource in resources:
        if resource.digest == NO_DIGEST:
            resource.digest = None  # indexed from its (decoded) request
            _ = resource.request
    clients, written.clients = client_records(client_rows, decode)
    at_once = {row[0] for row in rows}
    remaining = any(seq not in at_once for (seq,) in more)
    return Restored(resources, clients, Unread(store, last, at_once, remaining=remaining)), written


# -- every row at once (`SqliteStore.load`, `read_backup`) -------------------------------------


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


def read_backup(path: str | os.PathLike[str], *, unpickle: bool = True) -> Backup:
    """Read a catalog backup without changing it (it may belong to a running registrar).

    An older schema is migrated in memory, never in the file. Values whose classes are
    not importable here come back as `Unreadable`; without `unpickle`, every value is a
    `NotUnpickled` (only the stored display texts show them) and any owner's file is read.

    Args:
        path: the backup file.
        unpickle: decode the stored requests and responses.

    Returns:
        Its rows and schema version.

    Raises:
        ConfigError: `path` does not exist or is not a file; with `unpickle`, it belongs
            to another user.
        CatalogCorruptError: the file is not a readable rr_actors catalog.
    """
    file = Path(os.fspath(path))
    with files.inspected(file, unpickle=unpickle) as (db, version), gc_paused():
        decode = schema.lenient_decode if unpickle else schema.not_unpickled
        rows = read_rows(db, decode, lenient=True)
    return Backup(str(file), version, rows.resources, rows.clients)


@contextlib.contextmanager
def gc_paused() -> Iterator[None]:
    """Pause the cyclic garbage collector while a catalog is built (many containers, no
    cycles: each burst would rescan every object built so far)."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


@dataclasses.dataclass
class Rows:
    """Rows read from a backup, and the mirror a store needs to update them (`written`)."""

    resources: list[Resource]
    clients: list[ClientRecord]
    written: schema.Written


def read_rows(
    db: sqlite3.Connection, decode: Callable[[str, str, bytes | None], Any], *, lenient: bool
) -> Rows:
    """Read every row in one read transaction (a snapshot, also of a live file). Values stay
    encoded until first used, but requests without a digest; `lenient` (inspection)
    decodes every value at once."""
    db.execute("BEGIN")
    try:
        rows = db.execute(RESOURCES).fetchall()
        consumer_rows = db.execute(
            "SELECT seq, query_id, resource, origin_rr FROM consumers ORDER BY seq"
        ).fetchall()
        client_rows = db.execute(CLIENTS).fetchall()
    finally:
        db.execute("COMMIT")
    schema.check_rows(rows, consumer_rows, client_rows, values=not lenient)
    encoded = Resource.encoded
    states = schema.STATES_BY_CODE
    resources = [
        encoded(
            rid,
            server,
            states[state],
            NO_DIGEST if digest is None else digest,
            (request, response),
            decode,
            0,
            (request_text, response_text, label),
            failed=bool(failed),
        )
        for (
            _,
            rid,
            server,
            state,
            digest,
            request,
            response,
            request_text,
            response_text,
            label,
            failed,
        ) in rows
    ]
    for resource in resources:
        if lenient:
            _ = resource.request, resource.response
        if resource.digest == NO_DIGEST:
            resource.digest = None  # the catalog indexes it from its (decoded) request
            _ = resource.request
    mirrors = [
        schema.Mirror(row[0], r.state, r.response_version, {}, (row[7], row[8], row[9]), r.failed)
        for row, r in zip(rows, resources, strict=True)
    ]
    by_seq = {row[0]: (r, m) for row, r, m in zip(rows, resources, mirrors, strict=True)}
    for seq, query_id, resource_seq, origin in consumer_rows:
        owner = by_seq.get(resource_seq)
        if owner is None:
            raise ValueError(f"consumer {query_id} belongs to a missing resource")
        owner[0].consumers[query_id] = origin
        owner[1].consumers[query_id] = seq
    kinds = (rows, consumer_rows, client_rows)  # (each read in the order of its keys)
    written = schema.Written(max([0, *(kind[-1][0] for kind in kinds if kind)]))
    written.resources = {r.id: m for r, m in zip(resources, mirrors, strict=True)}
    clients, written.clients = client_records(client_rows, decode)
    return Rows(resources, clients, written)
