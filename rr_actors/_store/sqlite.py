"""The catalog backup's writer: an embedded SQLite database (semantics rules 13-16,
docs/explanation/semantics.md), what a write changes, and its checkpoints.

```
 registrar --Changes, told events--> Saver --write(changes, told)--> SqliteStore
   --plan_resource / plan_client: only what differs from its mirror (of consumers, only
   the ids added or released), values pickled here; the told events in the outbox
   (`outbox`)--> is the path still our file? (asked only once the kernel told that a
   name changed; else copy it whole into place, `files`)
   --> one transaction (WAL) --> file, its commit counted (`files.CommitCount`)
   --every CHECKPOINT_EVERY pages: wake()--> Checkpointer thread: its own connection,
   wal_checkpoint(PASSIVE), RESTART past WAL_LIMIT frames --> database file
 SqliteStore.open: `files` checks, creates, validates and prepares the file (rows: `schema`)
 SqliteStore.restore / load: `restore` reads it back
```

One file per registrar, in WAL mode; every `write` is one transaction, touching only the
rows that differ from the store's mirror of what it wrote (addressed by row key), so its
cost does not grow with the catalog nor with how widely a resource is shared. A write that
fails changes neither file nor mirror. Background checkpoints serve a store opened with
`background_checkpoints` (a registrar without `save_on_modify`); the others keep SQLite's
own. What each failure costs: "What the backup survives",
docs/explanation/failure-semantics.md.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import sqlite3
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

from rr_actors import events
from rr_actors._catalog import NO_DIGEST, Changes, ClientRecord, Resource, request_digest
from rr_actors._core import runtime
from rr_actors._platform import PLATFORM
from rr_actors._store import files, outbox, schema
from rr_actors._store.restore import (
    CONSUMERS_OF,
    Mirror,
    Restored,
    Texts,
    Unread,
    client_records,
    gc_paused,
    read_at_once,
    read_rows,
)
from rr_actors._store.schema import as_corrupt
from rr_actors.errors import CatalogCorruptError, CatalogWriteError, ConfigError

logger = logging.getLogger("rr_actors")


class SqliteStore:
    """A `CatalogStore` in one SQLite file, used by one thread at a time (the registrar's)."""

    def __init__(
        self,
        path: Path,
        db: sqlite3.Connection,
        *,
        created: bool,
        lock: files.BackupLock | None = None,
        synchronous: str = "NORMAL",
        background_checkpoints: bool = False,
    ) -> None:
        self.path = str(path)
        self._file = path.absolute()  # the same file after a chdir
        self._name = str(self._file)
        self._names = (self._name, f"{self._name}-wal")
        self._db = db
        self._lock = lock
        self._synchronous = synchronous
        self._guarded = runtime.guards_files()  # (not in a simulation: its files are its own)
        self._ids = files.file_ids(self._name) if self._guarded else (None, None)
        self._watch = PLATFORM.watch_names() if self._guarded else None
        self._aside: Path | None = None  # a whole copy not moved into place yet
        self._checkpointer: Checkpointer | None = None
        if background_checkpoints:
            self._hand_checkpoints_to_a_thread()
        self._unchecked = 0  # pages (about) written since the checkpointer was last woken
        self.checkpoint_every = CHECKPOINT_EVERY
        self._created = created
        self._checked = created or not self._guarded
        self._damaged: str | None = None
        self._loaded = False
        self._resources: dict[str, Mirror] = {}
        # query id -> (row key, response_version, request_text)
        self._clients: dict[str, tuple[int, int, str | None]] = {}
        self._seq = 0
        # resources a failed write changed: their next write compares every consumer
        self._owed: set[str] = set()
        self.closed = False
        self._decode = functools.partial(schema.decode, self.path)
        self._synced = synchronous == files.SYNCHRONOUS["power"]  # (all a restore reads)
        self._commits = files.CommitCount(self._file, kept=self._guarded, synced=self._synced)
        self.lost_commits = 0  # of the last run, that its WAL no longer held
        self.commits = 0  # write transactions since it opened

    @classmethod
    def open(
        cls,
        path: str | os.PathLike[str],
        *,
        durability: Literal["process", "power"] = "process",
        background_checkpoints: bool = False,
    ) -> SqliteStore:
        """Open the backup at `path`, creating an empty one if there is no file.

        `durability`: `"process"` (`synchronous=NORMAL`, nothing synced) or `"power"`
        (`FULL`: each commit's log, then its count, synced before it returns; a file
        created or put in place synced with its name); `background_checkpoints`: copy the
        WAL on a thread (`Checkpointer`).

        Raises:
            ConfigError: the path cannot hold a backup, the file belongs to another user,
                or another registrar has it open.
            CatalogCorruptError: the file is not a usable rr_actors catalog.
        """
        file = Path(os.fspath(path))
        files.check_location(file)
        lock = files.claim(file)  # before anything reads it: one registrar a file
        try:
            return cls._open(file, lock, durability, background_checkpoints)
        except BaseException:
            if lock is not None:
                lock.release()
            raise

    @classmethod
    def _open(
        cls,
        file: Path,
        lock: files.BackupLock | None,
        durability: Literal["process", "power"],
        background_checkpoints: bool,
    ) -> SqliteStore:
        created = made = False
        lost = None
        if not file.exists():
            made = files.create(file, synced=durability == "power")
            created = True
        if lock is not None:
            lock.hold_file()
        foreign = files.foreign_owner(file)
        if foreign is not None:
            raise ConfigError(
                f"backup_path {foreign}: restoring it would run code from it (unpickling)"
            )
        if not created:
            lost = files.lost_commits(file)  # before SQLite replays (and may remove) the log
        version = schema.SCHEMA_VERSION if made else files.validate(file, tidy=True)  # (known)
        name = str(file)
        try:
            db = files.connect(file, read_only=False)
        except sqlite3.Error as exc:
            raise ConfigError(f"backup_path {name!r} cannot be opened: {exc}") from exc
        checked = created or not runtime.guards_files()
        try:
            if not checked and _open_writes(db, name, version):
                files.check_pages(db, name)  # (before anything is written to it: rule 15)
                checked = True
            if made:  # (empty, current, WAL, written there already)
                db.execute(f"PRAGMA synchronous = {files.SYNCHRONOUS[durability]}")
            else:
                files.prepare(db, name, durability, version)
                with as_corrupt(name):  # (read at the last run's exit, if anyone listened)
                    outbox.clear(db)
        except BaseException:
            db.close()
            raise
        store = cls(
            file,
            db,
            created=created,
            lock=lock,
            synchronous=files.SYNCHRONOUS[durability],
            background_checkpoints=background_checkpoints,
        )
        store._checked = checked
        if lost is not None:
            store.lost_commits, why = lost
            logger.warning(
                "catalog backup %s: %s: %d acknowledged commits are lost (their loads, "
                "releases and unloads are not restored; consumers holding ids it lost are "
                "told FATAL when they reconcile)",
                name,
                why,
                store.lost_commits,
            )
            store._commits.close()  # reported once: the next commit counts the log afresh
        return store

    def _hand_checkpoints_to_a_thread(self) -> None:
        self._db.execute("PRAGMA wal_autocheckpoint = 0")  # the checkpointer's thread does it
        self._db.execute(f"PRAGMA journal_size_limit = {WAL_KEPT}")
        self._checkpointer = Checkpointer(self._file, self._synchronous)

    @property
    def connection(self) -> sqlite3.Connection:
        return self._db

    def load(self) -> tuple[list[Resource], list[ClientRecord]] | None:
        """Every stored row, oldest first; `None` if `open` created the file
        (`CatalogCorruptError`)."""
        try:
            with as_corrupt(self.path), gc_paused():
                rows = read_rows(self._db, self._decode, lenient=False)
        except CatalogCorruptError:
            self.close(erase=False)  # unusable; closing also removes its -wal and -shm
            raise
        self._resources = rows.mirror
        self._clients = {
            c.query.id: (rows.client_seqs[c.query.id], c.response_version, c.request_text)
            for c in rows.clients
        }
        self._seq = rows.max_seq
        self._loaded = True
        if self._created and not rows.resources and not rows.clients:
            return None
        return rows.resources, rows.clients

    def restore(self) -> Restored | None:
        """Read what a registrar needs to serve again (`restore.py`); `None` if `open`
        created the file (`CatalogCorruptError`)."""
        try:
            with as_corrupt(self.path), gc_paused():
                last, rows, client_rows, remaining = read_at_once(self._db)
                self._resources = {}
                self._seq = last
                resources = [
                    self.adopt(row, self._db.execute(CONSUMERS_OF, (row[0],)).fetchall())
                    for row in rows
                ]
                for resource in resources:
                    if resource.digest == NO_DIGEST:
                        resource.digest = None  # indexed from its (decoded) request
                        _ = resource.request
                clients, client_seqs = client_records(client_rows, self._decode)
                texts = {c.query.id: c.request_text for c in clients}
                self._clients = {qid: (seq, 0, texts[qid]) for qid, seq in client_seqs.items()}
        except CatalogCorruptError:
            self.close(erase=False)
            raise
        # (`adopt` raises `_seq` past each resource's consumer keys: no scan of them all)
        self._seq = max([self._seq, *client_seqs.values()])
        self._loaded = True
        if self._created and not last and not clients:
            return None
        unread = Unread(self, last, {row[0] for row in rows}, remaining=remaining)
        return Restored(resources, clients, unread)

    def adopt(self, row: Any, consumer_rows: list[Any]) -> Resource:
        """Build a stored resource with its consumers; from now on the store mirrors it."""
        seq, rid, server, state, digest, request, response, *texts, failed = row
        resource = Resource.encoded(
            rid,
            server,
            schema.STATES_BY_CODE[state],
            NO_DIGEST if digest is None else digest,
            (request, response),
            self._decode,
            seq,
            (texts[0], texts[1], texts[2]),
            failed=bool(failed),
        )
        keys = {}
        for key, query_id, origin in consumer_rows:
            resource.consumers[query_id] = origin
            keys[query_id] = key
            self._seq = max(self._seq, key)  # its next consumer's key comes after these
        self._resources[rid] = Mirror(
            seq, resource.state, 0, keys, (texts[0], texts[1], texts[2]), resource.failed
        )
        return resource

    def mirrored(self, last: int) -> tuple[int, int]:
        """Mirrored resource rows with a key up to `last`, and their consumer rows."""
        resources = consumers = 0
        for mirror in self._resources.values():
            if mirror.seq <= last:
                resources += 1
                consumers += len(mirror.consumers)
        return resources, consumers

    def write(self, changes: Changes, told: Sequence[events.Event] = ()) -> None:
        """Apply `changes` (current rows, `None` for deleted ones) and the numbered events
        of `told` (in the outbox) as one transaction: only what differs from the mirror,
        of a resource's consumers only those `changes.consumers` names. The statements are
        planned (pickled) before anything is written; the mirror changes once committed.

        Raises:
            CatalogWriteError: the write failed (a full disk, `errno` `ENOSPC`; the store
                is as before: write them again later), or the file is damaged (chained
                from the `CatalogCorruptError`; nothing is written to it any more).
            CatalogCorruptError: rows the first write had to read (`load`) cannot be read.
        """
        owed = self._owed
        try:
            if not self._loaded:
                self.load()
            ops: list[Op] = []
            mirrors: list[tuple[dict[str, Any], str, Any]] = []  # (table, key, value | GONE)
            seq = self._seq
            touched, written = changes.consumers, self._resources
            for rid, resource in changes.resources.items():
                ids = None if rid in owed else touched.get(rid)
                seq = plan_resource(written, ops, mirrors, rid, resource, seq, ids)
            for qid, record in changes.clients.items():
                seq = plan_client(self._clients, ops, mirrors, qid, record, seq)
            if told:
                outbox.plan_told(told, ops)
            if ops:
                self._commit(ops)
        except BaseException:
            owed.update(changes.resources)
            raise
        if owed:
            owed.difference_update(changes.resources)
        self._seq = seq
        for table, key, value in mirrors:
            if value is GONE:
                table.pop(key, None)
            else:
                table[key] = value

    @property
    def damaged(self) -> str | None:
        """Why the file is damaged, or `None`; once set, nothing more is written to it."""
        return self._damaged

    def found_damaged(self, why: str) -> None:
        if self._damaged is None:
            self._damaged = why
            logger.error(
                "catalog backup %s is damaged (%s): its registrar writes nothing more to "
                "it, so it stays as it was; changes are refused from now on. Keep it for "
                "analysis (quarantine_backup) and restart",
                self.path,
                why,
            )

    def _refuse_if_damaged(self) -> None:
        """Raise `CatalogWriteError` if the file is damaged; check its pages first, once,
        before the first write (the lazy restore left pages unread)."""
        if not self._checked and self._damaged is None:
            self._checked = True
            try:
                files.check_pages(self._db, self.path)
            except CatalogCorruptError as exc:
                self.found_damaged(exc.cause)
        if self._damaged is None:
            return
        corrupt = CatalogCorruptError(self.path, self._damaged)
        raise CatalogWriteError(
            self.path,
            f"the file is damaged ({self._damaged}); nothing more is written to it, so it "
            "stays as it was: keep it for analysis (quarantine_backup) and restart",
        ) from corrupt

    def _commit(self, ops: list[Op]) -> None:
        if not self._checked or self._damaged is not None:
            self._refuse_if_damaged()
        watch = self._watch  # (`_keep_in_place`'s first step, spared a call)
        if watch is None or self._aside is not None or not watch.quiet():
            self._keep_in_place()
        try:
            self._run(ops)
        except sqlite3.Error as exc:
            if schema.damaged_file(exc):
                self.found_damaged(f"{type(exc).__name__}: {exc}")
                self._refuse_if_damaged()
            raise files.write_error(self.path, exc) from exc

    def _run(self, ops: list[Op]) -> None:
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
                schema.rollback(db)
                raise
        self.commits += 1
        self._commits.committed()
        if self._checkpointer is None:
            return
        self._unchecked += len(ops)
        for _, params in ops:  # a large request or response fills many pages
            for value in params:
                if type(value) is bytes and len(value) > PAGE:
                    self._unchecked += len(value) // PAGE
        if self._unchecked >= self.checkpoint_every:
            self._unchecked = 0
            if not self._checkpointer.wake():  # no thread: SQLite's own, from now on
                db.execute("PRAGMA wal_autocheckpoint = 1000")
                self._checkpointer = None

    def _keep_in_place(self) -> None:
        """Write the whole catalog to a new file if the path lost the one being written
        ("A deleted backup", failure-semantics.md); two `stat`s, only once the platform's
        watch (`Platform.watch_names`) told of a change. `CatalogWriteError`: the copy
        failed (retried next time)."""
        if not self._guarded:
            return
        if self._aside is None:
            watch = self._watch
            if watch is not None and watch.quiet():  # nothing happened to the names
                return
            if self._ids[1] is None:  # the -wal appears with the first transaction
                self._ids = (self._ids[0], files.file_ids(self._name)[1])
            if watch is not None and self._ids[1] is not None:
                watch.arm(self._names)  # (first: a change made during the check is told)
            why = files.moved(self._name, self._ids)
            if why is None:
                return
            logger.warning(
                "catalog backup %s: %s while its registrar runs; writing the whole catalog "
                "to a new file there",
                self.path,
                why,
            )
            try:
                self._aside = files.copy_aside(self._db, self._file)
            except (sqlite3.Error, OSError) as exc:
                raise files.write_error(self.path, exc) from exc
            self._close_connections()
        try:  # no connection is open on the old file now: SQLite would remove the new -wal
            files.put_in_place(self._aside, self._file, synced=self._synced)
            self._aside = None
            if self._lock is not None:  # (before SQLite locks the new file: see `lockfile`)
                self._lock.file_replaced()
            db = files.connect(self._file, read_only=False)
            db.execute(f"PRAGMA synchronous = {self._synchronous}")
        except (sqlite3.Error, OSError) as exc:
            raise files.write_error(self.path, exc) from exc
        self._db = db
        if self._watch is not None:
            self._watch.close()  # (armed at the next commit, once the new -wal exists)
        self._ids = files.file_ids(self._file)
        self._commits.reopen()
        if self._checkpointer is not None:
            self._hand_checkpoints_to_a_thread()

    def _close_connections(self) -> None:
        if self._checkpointer is not None:
            self._checkpointer.close()
        with contextlib.suppress(sqlite3.Error):
            self._db.close()

    def close(self, *, erase: bool) -> None:
        """Close the database; with `erase`, delete the file and its companions. Without, a
        file deleted since the last commit is written again first; never raises."""
        try:
            if not self.closed:
                if not erase and self._damaged is None:
                    try:
                        self._keep_in_place()
                    except CatalogWriteError as exc:  # logged: a stop or a crash goes on
                        kept = f"a whole copy is at {self._aside}" if self._aside else "it is lost"
                        logger.error("%s; %s", exc, kept)  # noqa: TRY400 - the cause says it all
                self.closed = True
                self._commits.close()  # (first: SQLite removes the log as it closes)
                if self._watch is not None:
                    self._watch.close()
                if self._aside is None:
                    self._close_connections()
            if erase:
                files.remove_files(self._file)
            if self._aside is not None and erase:
                files.remove_files(self._aside)
        finally:  # (whatever happened: the file is no longer this store's)
            lock, self._lock = self._lock, None
            if lock is not None:
                lock.release()


def _open_writes(db: sqlite3.Connection, name: str, version: int) -> bool:
    """Whether opening the file writes to it (a migration, or last run's outbox to clear)."""
    if version != schema.SCHEMA_VERSION:
        return True
    with as_corrupt(name):
        return bool(db.execute("SELECT EXISTS (SELECT 1 FROM outbox)").fetchone()[0])


# -- what a write changes --------------------------------------------------------------------

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
                    schema.STATE_CODES[resource.state],
                    None if digest == NO_DIGEST else digest,
                    schema.dumps(resource.request),
                    schema.dumps(resource.response),
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
        values += [schema.STATE_CODES[resource.state], schema.dumps(resource.response)]
    elif old.state is not resource.state:
        columns.append("state")
        values.append(schema.STATE_CODES[resource.state])
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
                    schema.dumps(query.request),
                    schema.dumps(query.response),
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
                (schema.dumps(query.response), int(record.loaded), record.request_text, row),
            )
        )
    mirrors.append((written, qid, (row, record.response_version, record.request_text)))
    return seq


# -- the background checkpointer --------------------------------------------------------------

CHECKPOINT_EVERY = 256  # WAL pages, about, between two background checkpoints
PAGE = 4096  # bytes in a WAL page (SQLite's default)
CHECKPOINT_BUSY_TIMEOUT = 0.1  # seconds a `RESTART` checkpoint waits for readers
WAL_LIMIT = 16_384  # WAL frames past which a checkpoint makes the writer wait for it
WAL_KEPT = 8 * 1024 * 1024  # bytes of WAL kept when the log restarts (`journal_size_limit`)


class Checkpointer:
    """Copies committed WAL pages into the database file, on its own thread, started at the
    first wake-up (why and how: "The backup's file", docs/explanation/inside.md)."""

    def __init__(self, path: Path, synchronous: str) -> None:
        self._path = path.resolve()  # the thread connects later: a chdir must not matter
        self._synchronous = synchronous
        self._wake = runtime.Event()
        self._closing = False
        self._thread: runtime.Thread | None = None
        self._db: sqlite3.Connection | None = None  # the thread's connection, once open
        self.done = runtime.Condition()  # notified after each checkpoint
        self._running = False
        self.checkpoints = 0
        self.last: tuple[int, int, int] | None = None  # (busy, frames in the log, copied)

    def wake(self) -> bool:
        """Ask for a checkpoint soon; `False` if no thread can do it."""
        if self._closing:
            return True
        if self._thread is not None and not self._thread.is_alive():
            return False
        if self._thread is None:
            thread = runtime.Thread(
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
        """Stop the thread, interrupting the checkpoint in progress (safe: the next one, or
        the next open, finishes the copy); wait `timeout` seconds."""
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
            db = runtime.hold(
                sqlite3.connect(
                    f"{self._path.as_uri()}?mode=rw",
                    uri=True,
                    isolation_level=None,
                    timeout=CHECKPOINT_BUSY_TIMEOUT,
                )
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
