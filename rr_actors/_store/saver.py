"""When catalog changes reach the backup: the save policy (rules 13-14).

With `save_on_modify` every change is written before the registrar answers; otherwise
changes accumulate and are flushed every `save_interval` seconds, on `save_catalog()` and
on a clean stop.

```
 registrar --changed(changes, told)--> pending --flush() / on_modify--> store.write(pending)
                                    ^                                   |
                                    +-- kept on CatalogWriteError ------+--> failure
 registrar --retry()--> store.write(pending) --ok--> failure = None
```

The events that tell of a change (`told`) go into the transaction of a write made at
once (the outbox), never kept pending. A write that fails keeps its changes pending,
merged into the next write, and `failure` says the backup is behind until then.
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
    from rr_actors._store.sqlite import SqliteStore  # noqa: PLC0415 - only with a backup

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
        from rr_actors._store.restore import gc_paused  # noqa: PLC0415 - only with a backup

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
