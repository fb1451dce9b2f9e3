"""When catalog changes reach the backup, and how: the save policy (rules 13-14) over
its writer, an embedded SQLite file (rules 13-16, docs/explanation/semantics.md), and the
writer's background checkpoints.

```
 registrar --changed(changes, told) / stage(changes)--> Saver: pending (one Changes)
   --save_on_modify, a turn's end (write), every save_interval (flush)--> SqliteStore.write
   --`schema.Written.plan`: only what differs from its mirror of what it wrote, values
   pickled before anything is written; the told events in the outbox (`outbox`)-->
   is the path still our file? (`BackupFile.keep_in_place`, asked only once the kernel
   told that a name changed; else the whole catalog copied into place)
   --> one transaction (WAL) --> file, its commit counted (`files.CommitCount`)
   --every CHECKPOINT_EVERY pages: wake()--> Checkpointer thread: its own connection,
   wal_checkpoint(PASSIVE), RESTART past WAL_LIMIT frames --> database file
   a write fails (CatalogWriteError): pending kept, merged into the next; retry()
 open_catalog: SqliteStore.open (`files.open_backup` checks, claims, creates, validates,
   prepares) --> SqliteStore.restore (`restore` reads it back; the store mirrors what it
   read) --> Catalog.restore
```

With `save_on_modify` every change is written before the registrar answers (a turn's
staged changes in one transaction: group commit); otherwise changes accumulate and are
flushed every `save_interval` seconds, on `save_catalog()` and on a clean stop. The events
that tell of a change (`told`) go into the transaction of a write made at once (the
outbox), never kept pending. A write that fails changes neither file nor mirror, keeps its
changes pending, and `failure` says the backup is behind until then. One file per
registrar, in WAL mode; a `write` touches only the rows that differ from the store's
mirror of what it wrote, so its cost does not grow with the catalog. Background
checkpoints serve a store opened with `background_checkpoints` (a registrar without
`save_on_modify`); the others keep SQLite's own. What each failure costs: "What the backup
survives", docs/explanation/failure-semantics.md.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import sqlite3
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal, Protocol

from rr_actors import events
from rr_actors._catalog import Catalog, Changes, ClientRecord, Resource
from rr_actors._core import runtime
from rr_actors._store import outbox, schema
from rr_actors._store.files import BackupFile, check_pages, open_backup, write_error
from rr_actors._store.restore import Restored, gc_paused, read_at_once, read_rows
from rr_actors.config import RegistrarConfig
from rr_actors.errors import CatalogCorruptError, CatalogWriteError

logger = logging.getLogger("rr_actors")

timer_factory: runtime.StartTimer = runtime.thread_timer  # (tests replace it)


class CatalogStore(Protocol):
    """Durable storage of one registrar's catalog rows."""

    path: str

    def load(self) -> tuple[list[Resource], list[ClientRecord]] | None: ...

    def restore(self) -> Restored | None: ...

    def write(self, changes: Changes, told: Sequence[events.Event] = ()) -> None: ...

    def close(self, *, erase: bool) -> None: ...

    @property
    def damaged(self) -> str | None: ...


def open_store(config: RegistrarConfig) -> CatalogStore | None:
    """Open the backup named by `config.backup_path` (`None` without one)."""
    if config.backup_path is None:
        return None
    # bursts (flushes) are checkpointed off the registrar's thread; a commit per change keeps
    # SQLite's own
    return SqliteStore.open(
        config.backup_path,
        durability=config.durability,
        background_checkpoints=not config.save_on_modify,
    )


class Saver:
    """Applies the save policy of a `RegistrarConfig` to a store (or to nothing), on the
    registrar actor's thread."""

    def __init__(self, store: CatalogStore | None, config: RegistrarConfig) -> None:
        self.store = store
        self.on_modify = config.save_on_modify
        self.flush_interval = (
            config.save_interval if store is not None and not config.save_on_modify else None
        )
        self._pending: Changes | None = None  # (none: nothing is)
        self._failure: CatalogWriteError | None = None

    @property
    def durable(self) -> bool:
        return self.store is not None and self.on_modify

    @property
    def failure(self) -> CatalogWriteError | None:
        """The error of the last write if it failed; `None` once a write succeeded."""
        return self._failure

    @property
    def pending(self) -> bool:
        return self._pending is not None

    def schedule(self, tick: Callable[[], None]) -> runtime.Cancellable | None:
        """Start the save-interval timer (`tick` runs once, on the timer's thread); `None`
        without an interval."""
        if self.flush_interval is None:
            return None
        return timer_factory(self.flush_interval, tick)

    def changed(
        self, changes: Changes | None, told: Sequence[events.Event] = (), *, now: bool = False
    ) -> bool:
        """Take changes just made to the catalog (`None`: none); with `save_on_modify` (or
        `now`), write what is pending now with `told`; whether it was written now
        (`CatalogWriteError`: it stays pending)."""
        if self.store is None:
            return False
        if changes is not None:
            self._take(changes)
        if not (self.on_modify or now):
            return False
        self.write(told)
        return True

    def stage(self, changes: Changes) -> None:
        """Take changes (not empty: `Catalog.changed` said so) to write with the next
        `write` (a registrar's turn), whatever the policy."""
        if self.store is None:
            return
        self._take(changes)

    def _take(self, changes: Changes) -> None:
        pending = self._pending
        if pending is None:  # (most writes: nothing else waits)
            self._pending = changes
        else:
            pending.update(changes)

    def write(self, told: Sequence[events.Event] = ()) -> None:
        """Write what is pending now with `told`, one transaction (the end of a registrar's
        turn). `CatalogWriteError`: the changes stay pending, `told` is dropped."""
        store, pending = self.store, self._pending
        if store is None or pending is None:
            return
        try:
            store.write(pending, told)
        except CatalogWriteError as exc:
            self._failure = exc
            raise
        self._pending = None
        self._failure = None

    def flush(self) -> None:
        """Write what accumulated since the last write (`CatalogWriteError`: it stays
        pending)."""
        self.write()

    def retry(self) -> bool:
        """Try again to write what is pending; whether nothing is pending any more."""
        try:
            self.flush()
        except CatalogWriteError:
            return False
        return True

    def close(self, *, erase: bool, flush: bool = True) -> None:
        """Close the store: flush first (unless erasing, or `flush=False` after a crash);
        closed even if the flush raises `CatalogWriteError`. A damaged file is neither
        flushed to nor erased (logged, ERROR)."""
        if self.store is None:
            return
        damaged = self.store.damaged
        if damaged is not None and self._pending is not None and flush and not erase:
            logger.error(
                "catalog backup %s is damaged (%s): the changes made since were not "
                "written to it, and are lost with this stop",
                self.store.path,
                damaged,
            )
        if damaged is not None and erase:
            logger.error(
                "catalog backup %s is damaged (%s): it was kept, not erased "
                "(erase_on_destruct), so it can be analysed (quarantine_backup)",
                self.store.path,
                damaged,
            )
            erase = False
        try:
            if flush and not erase and damaged is None:
                self.flush()
        finally:
            self.store.close(erase=erase)
            self.store = None


def open_catalog(config: RegistrarConfig) -> tuple[Saver, Catalog, bool]:
    """Open a registrar's backup and build its catalog from it: the save policy, the
    catalog, and whether it was restored (`ConfigError`, `CatalogCorruptError`)."""
    store = open_store(config)
    try:
        restored = None
        catalog = Catalog(track_changes=store is not None)
        if store is not None:
            with gc_paused():
                restored = store.restore()
                if restored is not None:
                    catalog = Catalog.restore(restored.resources, restored.clients, restored.unread)
    except BaseException:
        if store is not None:
            store.close(erase=False)
        raise
    return Saver(store, config), catalog, restored is not None


# -- the writer: one SQLite file, one transaction a write -----------------------------------


class SqliteStore:
    """A `CatalogStore` in one SQLite file, used by one thread at a time (the registrar's)."""

    def __init__(
        self,
        backup: BackupFile,
        db: sqlite3.Connection,
        *,
        created: bool,
        checked: bool,
        background_checkpoints: bool = False,
    ) -> None:
        self.path = backup.path
        self._file = backup
        self._db = db
        self._checkpointer: Checkpointer | None = None
        if background_checkpoints:
            self._hand_checkpoints_to_a_thread()
        self._unchecked = 0  # pages (about) written since the checkpointer was last woken
        self.checkpoint_every = CHECKPOINT_EVERY
        self._created = created
        self._checked = checked
        self._damaged: str | None = None
        self._loaded = False
        self._written = schema.Written()
        # resources a failed write changed: their next write compares every consumer
        self._owed: set[str] = set()
        self.closed = False
        self._decode = functools.partial(schema.decode, self.path)
        self._commits = backup.commits
        self.lost_commits = backup.lost_commits  # of the last run, that its WAL no longer held
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
        backup, db, created, checked = open_backup(Path(os.fspath(path)), durability)
        try:
            return cls(
                backup,
                db,
                created=created,
                checked=checked,
                background_checkpoints=background_checkpoints,
            )
        except BaseException:
            backup.release()
            raise

    def _hand_checkpoints_to_a_thread(self) -> None:
        self._db.execute("PRAGMA wal_autocheckpoint = 0")  # the checkpointer's thread does it
        self._db.execute(f"PRAGMA journal_size_limit = {WAL_KEPT}")
        self._checkpointer = Checkpointer(self._file.file, self._file.synchronous)

    @property
    def connection(self) -> sqlite3.Connection:
        return self._db

    def load(self) -> tuple[list[Resource], list[ClientRecord]] | None:
        """Every stored row, oldest first; `None` if `open` created the file
        (`CatalogCorruptError`)."""
        try:
            with schema.as_corrupt(self.path), gc_paused():
                rows = read_rows(self._db, self._decode, lenient=False)
        except CatalogCorruptError:
            self.close(erase=False)  # unusable; closing also removes its -wal and -shm
            raise
        self._written = rows.written
        self._loaded = True
        if self._created and not rows.resources and not rows.clients:
            return None
        return rows.resources, rows.clients

    def restore(self) -> Restored | None:
        """Read what a registrar needs to serve again (`restore.py`); `None` if `open`
        created the file (`CatalogCorruptError`)."""
        try:
            with schema.as_corrupt(self.path), gc_paused():
                restored, self._written = read_at_once(self, self._decode)
        except CatalogCorruptError:
            self.close(erase=False)
            raise
        self._loaded = True
        if self._created and not self._written.seq:  # (no row at all)
            return None
        return restored

    def adopt(self, row: Any, consumer_rows: list[Any]) -> Resource:
        """Build a stored resource with its consumers; from now on the store mirrors it."""
        return self._written.adopt(row, consumer_rows, self._decode)

    def mirrored(self, last: int) -> tuple[int, int]:
        """Mirrored resource rows with a key up to `last`, and their consumer rows."""
        return self._written.mirrored(last)

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
            ops, mirrors, seq = self._written.plan(changes, owed)
            if told:
                outbox.plan_told(told, ops)
            if ops:
                self._commit(ops)
        except BaseException:
            owed.update(changes.resources)
            raise
        if owed:
            owed.difference_update(changes.resources)
        self._written.settle(mirrors, seq)

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
                check_pages(self._db, self.path)
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

    def _commit(self, ops: list[schema.Op]) -> None:
        if not self._checked or self._damaged is not None:
            self._refuse_if_damaged()
        if not self._file.quiet():
            self._keep_in_place()
        try:
            self._run(ops)
        except sqlite3.Error as exc:
            if schema.damaged_file(exc):
                self.found_damaged(f"{type(exc).__name__}: {exc}")
                self._refuse_if_damaged()
            raise write_error(self.path, exc) from exc

    def _run(self, ops: list[schema.Op]) -> None:
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
        (`BackupFile.keep_in_place`; `CatalogWriteError`: retried next time)."""
        db = self._file.keep_in_place(self._db, self._close_connections)
        if db is None:
            return
        self._db = db
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
                        aside = self._file.aside
                        kept = f"a whole copy is at {aside}" if aside else "it is lost"
                        logger.error("%s; %s", exc, kept)  # noqa: TRY400 - the cause says it all
                self.closed = True
                self._file.closing()
                if self._file.aside is None:
                    self._close_connections()
            if erase:
                self._file.erase()
        finally:  # (whatever happened: the file is no longer this store's)
            self._file.release()


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
