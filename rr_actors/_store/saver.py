"""When catalog changes reach the backup: the save policy (rules 13-14).

`Saver` sits between the registrar actor and its `CatalogStore`. With `save_on_modify`
every change is written before the registrar answers; otherwise changes accumulate and
are flushed every `save_interval` seconds (a crash loses at most that window), on
`save_catalog()` and on a clean stop.

```
 registrar --changed(changes, told)--> pending --flush() / on_modify--> store.write(pending)
                                    ^                                   |
                                    +-- kept on CatalogWriteError ------+--> failure
 registrar --retry()--> store.write(pending) --ok--> failure = None
```

The events that tell of a change (`told`) go into the transaction that writes it when
that write is made at once (`save_on_modify`, or `changed(..., now=True)`), so a kill
after the commit leaves them in the backup's outbox (`outbox.py`). They are never kept
pending: a write that fails drops them, and its caller publishes them or undoes the
change. Changes left to the interval's flush carry none (their events are published
before the flush: a crash loses the change, not the event).

A write that fails (a full disk) raises `CatalogWriteError`; its changes stay pending
and are written, merged with what changed since, by the next write that succeeds, and
`failure` tells the registrar that the backup is behind until then.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Protocol

from rr_actors import events
from rr_actors._catalog import Catalog, Changes, ClientRecord, Resource
from rr_actors._core import runtime
from rr_actors.config import RegistrarConfig
from rr_actors.errors import CatalogWriteError

if TYPE_CHECKING:
    from rr_actors._store.restore import Restored

__all__ = ["CatalogStore", "Saver", "open_catalog", "open_store", "timer_factory"]

logger = logging.getLogger("rr_actors")

_NOTHING = Changes({}, {})  # (what is pending when nothing is: never changed in place)


timer_factory: runtime.StartTimer = runtime.thread_timer
"""Starts every save-interval timer. Tests replace it (monkeypatch) with a manual clock."""


class CatalogStore(Protocol):
    """Durable storage of one registrar's catalog rows."""

    path: str

    def load(self) -> tuple[list[Resource], list[ClientRecord]] | None:
        """Every stored row, or `None` when there was no backup (a first start)."""

    def restore(self) -> Restored | None:
        """What a registrar needs to serve again (the rest read on first use), or `None`."""

    def write(self, changes: Changes, told: Sequence[events.Event] = ()) -> None:
        """Apply `changes` as one transaction, with the events `told` that tell of them.

        Raises:
            CatalogWriteError: nothing of `changes` was written (a full disk, ...).
        """

    def close(self, *, erase: bool) -> None:
        """Close the store; with `erase`, remove its files."""

    @property
    def damaged(self) -> str | None:
        """Why the file is damaged (nothing more is written to it), or `None`."""


def open_store(config: RegistrarConfig) -> CatalogStore | None:
    """Open the backup named by `config.backup_path` (`None` without one).

    Raises:
        ConfigError: the path cannot hold a backup (missing directory, read-only, ...).
        CatalogCorruptError: the file exists but is not a readable catalog.
    """
    if config.backup_path is None:
        return None
    from rr_actors._store.sqlite import SqliteStore  # noqa: PLC0415 - only with a backup

    # Changes written in bursts (flushes: every `save_interval`, `save_catalog`, `stop`)
    # are checkpointed off the registrar's thread; a commit per change (`save_on_modify`)
    # keeps SQLite's own.
    return SqliteStore.open(
        config.backup_path,
        durability=config.durability,
        background_checkpoints=not config.save_on_modify,
    )


class Saver:
    """Applies the save policy of a `RegistrarConfig` to a store (or to nothing).

    Runs on the registrar actor's thread (it is not thread-safe). When a write fails
    (`CatalogWriteError`: a full disk, an I/O error), the changes it carried stay pending,
    `failure` holds the error and `durable` does not change. Every later write (the next
    change with `save_on_modify`, a `flush`, `retry`) writes everything pending, merged
    with what changed since; the first that succeeds clears `failure`. So while `failure`
    is set, the file holds what was written before it, and the registrar may serve all of
    that; a registrar that promises durability (`durable`) refuses new loads until `retry`
    succeeds.
    """

    def __init__(self, store: CatalogStore | None, config: RegistrarConfig) -> None:
        self.store = store
        self.on_modify = config.save_on_modify
        self.flush_interval = (
            config.save_interval if store is not None and not config.save_on_modify else None
        )
        self._pending = _NOTHING  # (never changed in place: `_take` replaces it)
        self._told: Sequence[events.Event] = ()  # (only while `changed` writes them)
        self._failure: CatalogWriteError | None = None

    @property
    def durable(self) -> bool:
        """Whether every change is written before it is acknowledged."""
        return self.store is not None and self.on_modify

    @property
    def failure(self) -> CatalogWriteError | None:
        """The error of the last write if it failed; `None` once a write succeeded.

        While it is set, changes wait in memory (`pending`) and the file holds what was
        written before.
        """
        return self._failure

    @property
    def pending(self) -> bool:
        """Whether changes wait to be written (none without a store)."""
        return bool(self._pending)

    def schedule(self, tick: Callable[[], None]) -> runtime.Cancellable | None:
        """Start the save-interval timer: `tick()` runs once, `flush_interval` s from now.

        Returns `None` (and starts nothing) when this policy has no interval. `tick` runs
        on the timer's thread; the registrar's tick only sends its actor a message.
        """
        if self.flush_interval is None:
            return None
        return timer_factory(self.flush_interval, tick)

    def changed(
        self, changes: Changes, told: Sequence[events.Event] = (), *, now: bool = False
    ) -> bool:
        """Take changes just made to the catalog; with `save_on_modify` (or `now`), write
        them now, with the events `told` that tell of them in the same transaction.

        Args:
            changes: the changed rows (`Catalog.drain_changes`).
            told: the events that tell of them, written with them if they are written
                now (never kept pending: a write that fails drops them).
            now: write them now whatever the policy (with what was pending).

        Returns:
            Whether they were written now (`False`: they wait for the next flush).

        Raises:
            CatalogWriteError: the write made now failed: `changes` (and whatever was
                pending) stay pending, and `failure` is this error.
        """
        if self.store is None:
            return False
        self._take(changes)
        if not (self.on_modify or now):
            return False
        self._told = told
        try:
            self.flush()
        finally:
            self._told = ()
        return True

    def stage(self, changes: Changes) -> None:
        """Take changes to write with the next `write` (a registrar's turn: its changes
        are one transaction at the turn's end), whatever the policy; none without a store."""
        if self.store is None:
            return
        self._take(changes)

    def _take(self, changes: Changes) -> None:
        """Add `changes` to what is pending (taken as they are when nothing is: the
        caller hands them over), with the consumer ids each changed resource added or
        released: the write looks at those only, not at every holder."""
        pending = self._pending
        if pending:
            pending.update(changes)
        else:  # (most writes: nothing else waits)
            self._pending = changes

    def write(self, told: Sequence[events.Event] = ()) -> None:
        """Write what is pending now, one transaction, with the events `told` that tell of
        it (the end of a registrar's turn); nothing without a store or pending changes.

        Raises:
            CatalogWriteError: the write failed: the changes stay pending, `failure` is
                this error, and `told` is dropped (never kept pending).
        """
        self._told = told
        try:
            self.flush()
        finally:
            self._told = ()

    def flush(self) -> None:
        """Write what accumulated since the last write.

        The changes are forgotten only once written: if the write raises they stay
        pending, and the next write (or flush) tries them again with what came since.

        Raises:
            CatalogWriteError: the write failed (the changes stay pending; `failure` is
                this error until a write succeeds).
        """
        if self.store is None or not self._pending:
            return
        try:
            self.store.write(self._pending, self._told)
        except CatalogWriteError as exc:
            self._failure = exc
            raise
        self._pending = _NOTHING
        self._failure = None

    def retry(self) -> bool:
        """Try again to write what is pending (after a `CatalogWriteError`).

        Returns:
            `True` if nothing is pending any more (it was written now, or there was
            nothing to write) and `failure` is `None`; `False` if the write failed again
            (`failure` holds the new error). Never raises `CatalogWriteError`.
        """
        try:
            self.flush()
        except CatalogWriteError:
            return False
        return True

    def close(self, *, erase: bool, flush: bool = True) -> None:
        """Close the store: flush first (unless erasing, or `flush=False` after a crash).

        The store is closed even if the flush raises (the error is then re-raised, and
        what was pending is lost with the process's memory). A damaged file (`damaged`)
        is not flushed to: it stays as it was found, what was pending is lost (logged,
        ERROR), and nothing is raised (the calls that made those changes were refused
        already, or were acknowledged without durability); it is not erased either, even
        with `erase` (kept for analysis, logged, ERROR).

        Raises:
            CatalogWriteError: the last flush failed.
        """
        if self.store is None:
            return
        damaged = self.store.damaged
        if damaged is not None and self._pending and flush and not erase:
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
    """Open a registrar's backup and build its catalog from it (a fresh one without).

    Returns:
        The save policy over the opened store, the catalog, and whether it was restored
        from an existing backup.

    Raises:
        ConfigError: the path cannot hold a backup (missing directory, read-only, ...).
        CatalogCorruptError: the file exists but is not a readable catalog.
    """
    store = open_store(config)
    try:
        from rr_actors._store.files import gc_paused  # noqa: PLC0415 - only with a backup

        restored = None
        catalog = Catalog(track_changes=store is not None)
        if store is not None:
            with gc_paused():  # building many rows allocates no cycles: skip the rescans
                restored = store.restore()
                if restored is not None:
                    catalog = Catalog.restore(restored.resources, restored.clients, restored.unread)
    except BaseException:
        if store is not None:
            store.close(erase=False)
        raise
    return Saver(store, config), catalog, restored is not None
