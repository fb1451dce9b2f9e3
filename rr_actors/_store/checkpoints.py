"""The background checkpointer: copies committed WAL pages into the file off the writer.

```
 SqliteStore.write --commit--> WAL --every CHECKPOINT_EVERY pages: wake()--> Checkpointer thread
                                     its own connection: wal_checkpoint(PASSIVE),
                                     RESTART past WAL_LIMIT frames --> database file
```

Used by a store opened with `background_checkpoints` (a registrar without
`save_on_modify`); the others keep SQLite's own automatic checkpoints.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
from pathlib import Path

from rr_actors._core import runtime

__all__ = [
    "CHECKPOINT_BUSY_TIMEOUT",
    "CHECKPOINT_EVERY",
    "PAGE",
    "WAL_KEPT",
    "WAL_LIMIT",
    "Checkpointer",
]

logger = logging.getLogger("rr_actors")


CHECKPOINT_EVERY = 256
"""WAL pages written between two background checkpoints, about: each statement counts
one, plus a page per 4 KiB of a large request or response."""

PAGE = 4096
"""Bytes in a WAL page (SQLite's default page size), for the count above."""

CHECKPOINT_BUSY_TIMEOUT = 0.1
"""Seconds a `RESTART` checkpoint waits for readers; the writer waits at most as long."""

WAL_LIMIT = 16_384
"""WAL frames (4 KiB pages) past which a checkpoint makes the writer wait for it."""

WAL_KEPT = 8 * 1024 * 1024
"""Bytes of WAL file kept when the log restarts after background checkpoints
(`journal_size_limit`); more is cut off. Twice what SQLite's own checkpoints let it reach."""


class Checkpointer:
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
        self._wake = runtime.Event()
        self._closing = False
        self._thread: runtime.Thread | None = None
        self._db: sqlite3.Connection | None = None  # the thread's connection, once open
        self.done = runtime.Condition()
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
