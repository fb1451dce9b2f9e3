"""Reading a backup back lazily (`Unread`); every row at once is `files.read_rows`.

```
 SqliteStore.restore --one read transaction--> Consumers   (every consumer id -> its resource row)
                                               resources in doubt, without a digest or with a
                                               dependency, and every client record (as rows)
                   --> Restored(resources, clients, unread)
 Catalog lookup (digest, consumer id, server, origin) --Unread--> rows read, checked, adopted:
                   the store mirrors them (`SqliteStore.adopt`), memory is the truth from then on
```

Restoring does not read every row (`SqliteStore.restore`): the consumer ids are read as
column strings by one aggregate query, the resources in doubt (or without a digest,
or owning a dependency) and the client records as rows; every other resource is read
when the catalog first looks it up, through the indexes. So a restart costs a fraction of
a full read, and an index is written only when a resource is added or removed, never
when a consumer id is.

`files.read_rows` reads everything in one snapshot instead (`SqliteStore.load`, `read_backup`).
Either way a restored resource keeps its request and response encoded until first used
(`Resource.encoded`).
"""

from __future__ import annotations

import dataclasses
import sqlite3
from collections.abc import Callable
from typing import Any, Protocol

from rr_actors._catalog import ClientRecord, Resource, ResourceState
from rr_actors._platform import PLATFORM
from rr_actors._store.codec import (
    as_corrupt,
    check_row,
    first_duplicate,
)
from rr_actors._types import Query
from rr_actors.errors import CatalogCorruptError, RegistrarStoppedError

__all__ = [
    "CLIENTS",
    "CLIENT_COLUMNS",
    "CONSUMERS_OF",
    "RESOURCES_AT_ONCE",
    "RESOURCE_COLUMNS",
    "Consumers",
    "Mirror",
    "Restored",
    "RowStore",
    "Texts",
    "Unread",
    "client_records",
]


class Mirror:
    """What the store last wrote for one resource (to write only the difference)."""

    __slots__ = ("consumers", "response_version", "seq", "state", "texts")

    def __init__(
        self,
        seq: int,
        state: ResourceState,
        response_version: int,
        consumers: dict[str, int],
        texts: Texts = (None, None, None),
    ) -> None:
        self.seq = seq  # the row's key
        self.state = state
        # The catalog bumps `Resource.response_version` on every response it sets (also
        # the same object again, mutated); decoding a restored one does not.
        self.response_version = response_version
        self.consumers = consumers  # consumer query id -> its row's key
        self.texts = texts  # (request_text, response_text, label) as written


Texts = tuple[str | None, str | None, str | None]
"""A resource row's `(request_text, response_text, label)`."""

RESOURCE_COLUMNS = (
    "seq, id, server, state, digest, request, response, request_text, response_text, label"
)
"""The columns of a resource row, in the order every reader reads them."""

CLIENT_COLUMNS = (
    "seq, query_id, server, serving_rr, origin_rr, request, response, parent, loaded, request_text"
)
"""The columns of a client row, in the order every reader reads them."""


_Op = tuple[str, tuple[Any, ...]]


def client_records(
    client_rows: list[Any], decode: Callable[[str, str, bytes | None], Any]
) -> tuple[list[ClientRecord], dict[str, int]]:
    """Client records from their rows (oldest first), with each record's row key."""
    clients = []
    seqs = {}
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
        seqs[qid] = seq
    return clients, seqs


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
_SEP = "\x1f"  # joins the consumer ids in one string (checked: a collision reads rows)


class Consumers:
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
            raise ValueError(f"consumer query id {first_duplicate(keys)} is stored twice")
        del keys, values
        if count >= _TRIM_AFTER:
            PLATFORM.release_free_memory()

    def resource_of(self, query_id: str) -> int | None:
        """The resource row key of consumer `query_id`, if it is stored."""
        resource = self.index.get(query_id)
        return None if resource is None else int(resource)


_TRIM_AFTER = 10_000
"""Consumer ids from which building `Consumers` frees enough (MBs) to hand it back."""


class RowStore(Protocol):
    """What `Unread` reads the rows it was left through (`SqliteStore` is one)."""

    path: str
    closed: bool

    @property
    def connection(self) -> sqlite3.Connection:
        """The store's connection to its file."""
        ...

    def adopt(self, row: Any, consumer_rows: list[Any]) -> Resource:
        """Build a stored resource with its consumers; from now on the store mirrors it."""
        ...


class Unread:
    """The served resources of a restored backup that are not in memory yet (`UnreadRows`).

    A restore reads the consumer ids, the resources in doubt and the clients; the other
    resources stay in the file until the catalog asks for one (by request digest, by
    consumer id, by server, ...). Reading one builds it with its consumers, records its
    mirror in the store and never returns it again: from then on memory is the truth.
    Rows written after the restore (`seq > last`) are the catalog's own and never read.
    """

    def __init__(
        self, store: RowStore, consumers: Consumers, count: int, last: int, read: set[int]
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
        with as_corrupt(self._store.path):
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

    def origins(self) -> set[str]:
        """The registrars that consumers of unread resources belong to (none is read)."""
        if not self.remaining:
            return set()
        self._check_open()
        with as_corrupt(self._store.path):
            rows = self._store.connection.execute(
                "SELECT DISTINCT origin_rr FROM consumers WHERE resource <= ?", (self._last,)
            ).fetchall()
        return {origin for (origin,) in rows}

    def consumer_ids_from(self, origin_rr: str) -> list[str]:
        """The consumer ids of unread resources that `origin_rr` holds (none is read)."""
        if not self.remaining:
            return []
        self._check_open()
        with as_corrupt(self._store.path):
            rows = self._store.connection.execute(
                "SELECT query_id, resource FROM consumers WHERE origin_rr = ? AND resource <= ?",
                (origin_rr, self._last),
            ).fetchall()
        return [query_id for query_id, resource in rows if resource not in self._read]

    def unheld(self) -> list[Resource]:
        """Every unread resource loaded and held by no consumer, oldest first.

        One pass over the resources' keys, each looked up in the consumers' key.
        """
        return self._fetch(
            "SELECT seq FROM resources r WHERE seq <= ? AND state = 1 AND NOT EXISTS "
            "(SELECT 1 FROM consumers c WHERE c.resource = r.seq) ORDER BY seq",
            (self._last,),
        )

    def every(self) -> list[Resource]:
        """Every unread resource, oldest first."""
        return self._fetch("SELECT seq FROM resources WHERE seq <= ? ORDER BY seq", (self._last,))

    def _fetch(self, sql: str, args: tuple[Any, ...]) -> list[Resource]:
        if not self.remaining:
            return []
        self._check_open()
        with as_corrupt(self._store.path):
            seqs = [
                seq for (seq,) in self._store.connection.execute(sql, args) if seq not in self._read
            ]
        return self._take(seqs)

    def _take(self, seqs: list[int]) -> list[Resource]:
        """Read resource rows `seqs` with their consumers; hand over all of them or none.

        Every row is read and checked before any is adopted, so a damaged one fails the
        lookup without marking its healthy neighbours read (they stay on disk, whole).
        """
        store = self._store
        db = store.connection
        read = []
        with as_corrupt(store.path):
            for seq in seqs:
                row = db.execute(_RESOURCE_BY_SEQ, (seq,)).fetchone()
                if row is None:
                    continue
                check_row(row)
                read.append((row, db.execute(CONSUMERS_OF, (seq,)).fetchall()))
        resources = [store.adopt(row, consumers) for row, consumers in read]
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
    unread: Unread
