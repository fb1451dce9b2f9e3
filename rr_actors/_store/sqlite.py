"""The catalog backup: an embedded SQLite database (DESIGN.md rules 13-16).

```
 registrar --Changes--> Saver --write(changes)--> SqliteStore --plan: only what differs from
   its mirror--> one transaction (WAL) --> file         (schema: `schema`, values: `codec`)
 SqliteStore.open: `files` checks, creates, validates and prepares the file
 SqliteStore.restore / load: `restore` reads it back; `checkpoints` copies the WAL off-thread
```

One file per registrar, in WAL mode. Every `write` is one transaction, so a crash at any
instant leaves the old or the new catalog, never a torn one. A write touches only the
rows that changed (the store keeps a small mirror of what it wrote to compute the
difference), so its cost does not grow with the catalog.
"""

from __future__ import annotations

import contextlib
import functools
import os
import sqlite3
from pathlib import Path
from typing import Any, Literal

from rr_actors._catalog import (
    NO_DIGEST,
    Changes,
    ClientRecord,
    Resource,
    request_digest,
)
from rr_actors._store import checkpoints, codec
from rr_actors._store.checkpoints import Checkpointer
from rr_actors._store.codec import STATE_CODES, STATES_BY_CODE, as_corrupt, check_keys, check_row
from rr_actors._store.files import (
    SIDE_FILES,
    SYNCHRONOUS,
    check_location,
    connect,
    create,
    prepare,
    validate,
)
from rr_actors._store.restore import (
    CLIENTS,
    CONSUMERS_OF,
    RESOURCES_AT_ONCE,
    Consumers,
    Mirror,
    Restored,
    Unread,
    client_records,
    gc_paused,
    read_rows,
)
from rr_actors._store.schema import rollback
from rr_actors.errors import CatalogCorruptError, ConfigError

__all__ = ["SqliteStore"]


_Op = tuple[str, tuple[Any, ...]]
"""One planned SQL statement and its parameters."""

_GONE = object()
"""Marks a mirror entry to delete once a write committed."""


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
        self._checkpointer: Checkpointer | None = None
        if background_checkpoints:
            db.execute("PRAGMA wal_autocheckpoint = 0")  # the checkpointer's thread does it
            db.execute(f"PRAGMA journal_size_limit = {checkpoints.WAL_KEPT}")
            self._checkpointer = Checkpointer(path, synchronous)
        self._unchecked = 0  # pages (about) written since the checkpointer was last woken
        self.checkpoint_every = checkpoints.CHECKPOINT_EVERY
        self._created = created
        self._loaded = False
        self._resources: dict[str, Mirror] = {}
        # query id -> (row key, response_version)
        self._clients: dict[str, tuple[int, int]] = {}
        self._seq = 0
        self.closed = False
        self._decode = functools.partial(codec.decode, self.path)  # decodes a stored value lazily

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
                (`Checkpointer`) instead of inside every few hundredth commit. For
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
        check_location(file)
        created = False
        if not file.exists():
            create(file)
            created = True
        version = validate(file, tidy=True)
        name = str(file)
        try:
            db = connect(file, read_only=False)
        except sqlite3.Error as exc:
            raise ConfigError(f"backup_path {name!r} cannot be opened: {exc}") from exc
        try:
            prepare(db, name, durability, version)
        except BaseException:
            db.close()
            raise
        return cls(
            file,
            db,
            created=created,
            synchronous=SYNCHRONOUS[durability],
            background_checkpoints=background_checkpoints,
        )

    @property
    def connection(self) -> sqlite3.Connection:
        """The store's connection to its file (the lazy restore reads rows through it)."""
        return self._db

    def load(self) -> tuple[list[Resource], list[ClientRecord]] | None:
        """Every stored row, oldest first; `None` if the file was created by `open`.

        Raises:
            CatalogCorruptError: a row or a stored value cannot be read.
        """
        try:
            with as_corrupt(self.path), gc_paused():
                rows = read_rows(self._db, self._decode, lenient=False)
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
            with as_corrupt(self.path), gc_paused():
                self._db.execute("BEGIN")
                try:
                    count, last = self._db.execute(
                        "SELECT count(*), ifnull(max(seq), 0) FROM resources"
                    ).fetchone()
                    consumers = Consumers(self._db)
                    rows = self._db.execute(RESOURCES_AT_ONCE).fetchall()
                    client_rows = self._db.execute(CLIENTS).fetchall()
                finally:
                    self._db.execute("COMMIT")
                for row in rows:
                    check_row(row)
                check_keys([], [], client_rows)
                self._resources = {}
                resources = [
                    self.adopt(row, self._db.execute(CONSUMERS_OF, (row[0],)).fetchall())
                    for row in rows
                ]
                for resource in resources:
                    if resource.digest == NO_DIGEST:
                        resource.digest = None  # indexed from its (decoded) request
                        _ = resource.request
                clients, client_seqs = client_records(client_rows, self._decode)
                self._clients = {qid: (seq, 0) for qid, seq in client_seqs.items()}
        except CatalogCorruptError:
            self.close(erase=False)
            raise
        self._seq = max(last, consumers.max_seq, *client_seqs.values())
        self._loaded = True
        if self._created and not count and not clients:
            return None
        unread = Unread(self, consumers, count, last, {row[0] for row in rows})
        return Restored(resources, clients, unread)

    def adopt(self, row: Any, consumer_rows: list[Any]) -> Resource:
        """Build a stored resource with its consumers; from now on the store mirrors it.

        Called by `restore` and by `Unread` when it reads a resource left on disk.
        """
        seq, rid, server, state, digest, request, response = row
        resource = Resource.encoded(
            rid,
            server,
            STATES_BY_CODE[state],
            NO_DIGEST if digest is None else digest,
            (request, response),
            self._decode,
            seq,
        )
        keys = {}
        for key, query_id, origin in consumer_rows:
            resource.consumers[query_id] = origin
            keys[query_id] = key
        self._resources[rid] = Mirror(seq, resource.state, 0, keys)
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
                rollback(db)
                raise
        if self._checkpointer is None:
            return
        self._unchecked += len(ops)
        for _, params in ops:  # a large request or response fills many pages
            for value in params:
                if type(value) is bytes and len(value) > checkpoints.PAGE:
                    self._unchecked += len(value) // checkpoints.PAGE
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
                        STATE_CODES[resource.state],
                        None if digest == NO_DIGEST else digest,
                        codec.dumps(resource.request),
                        codec.dumps(resource.response),
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
                        (STATE_CODES[resource.state], codec.dumps(resource.response), old.seq),
                    )
                )
            elif old.state is not resource.state:
                ops.append(
                    (
                        "UPDATE resources SET state = ? WHERE seq = ?",
                        (STATE_CODES[resource.state], old.seq),
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
        mirror = Mirror(row, resource.state, resource.response_version, consumers)
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
                        codec.dumps(query.request),
                        codec.dumps(query.response),
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
                    (codec.dumps(query.response), int(record.loaded), row),
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
            for suffix in ("", *SIDE_FILES):
                with contextlib.suppress(FileNotFoundError):
                    Path(f"{self._file}{suffix}").unlink()
