"""The background checkpointer: copies committed WAL pages into the file off the writer.

```
 SqliteStore.write --commit--> WAL --every CHECKPOINT_EVERY pages: wake()--> Checkpointer thread
                                     its own connection: wal_checkpoint(PASSIVE),
                                     RESTART past WAL_LIMIT frames --> database file
```

Used by a store opened with `background_checkpoints` (a registrar without
`save_on_modify`); the others keep SQLite's own.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
from pathlib import Path

from rr_actors._core import runtime

logger = logging.getLogger("rr_actors")


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
