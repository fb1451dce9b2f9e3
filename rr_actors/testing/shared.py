"""State a test shares with callbacks that may run in another process."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from multiprocessing.managers import BaseProxy, SyncManager
from typing import Any

import cloudpickle

from rr_actors._process.manager import mp_context

__all__ = ["Records", "SharedObjects"]


class _RecordsState:
    """The server side of a `Records` list: cloudpickled items, in order."""

    def __init__(self) -> None:
        self._items: list[bytes] = []
        self._lock = threading.Lock()

    def append(self, item: bytes) -> None:
        with self._lock:
            self._items.append(item)

    def items(self) -> list[bytes]:
        with self._lock:
            return list(self._items)

    def __len__(self) -> int:
        return len(self._items)


class Records(BaseProxy):
    """An append-only list shared between processes (a `multiprocessing` proxy).

    Reads return copies: iterating, indexing, `len` and `==` (with a list or another
    `Records`) work on a snapshot. Items are cloudpickled, so any value a callback sees
    (closures' classes included) can be recorded. Safe from any thread of any process
    started with the same authkey (the children of this process).
    """

    _exposed_ = ("append", "items", "__len__")

    def _ask(self, method: str, *args: Any) -> Any:
        """Call `method` on the shared list (typeshed types `_callmethod` as returning None)."""
        callmethod: Callable[..., Any] = self._callmethod
        return callmethod(method, args)

    def append(self, item: Any) -> None:
        """Add `item` at the end."""
        self._ask("append", cloudpickle.dumps(item))

    def snapshot(self) -> list[Any]:
        """A copy of the items, in the order they were appended."""
        return [cloudpickle.loads(data) for data in self._ask("items")]

    def __len__(self) -> int:
        count: int = self._ask("__len__")
        return count

    def __iter__(self) -> Iterator[Any]:
        return iter(self.snapshot())

    def __getitem__(self, index: Any) -> Any:
        return self.snapshot()[index]

    def __eq__(self, other: object) -> bool:
        if isinstance(other, Records):
            other = other.snapshot()
        return self.snapshot() == other

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"Records({self.snapshot()!r})"

    __str__ = __repr__


class _Manager(SyncManager):
    """A `SyncManager` that also serves `Records`."""


_Manager.register("Records", _RecordsState, Records)


class SharedObjects:
    """Events, barriers, locks and lists that a test shares with callbacks in any process.

    A `multiprocessing` `SyncManager` (one helper process, forkserver or spawn) holds them;
    its proxies pickle (cloudpickle too), so callbacks that captured them work in manager
    processes started by this one. Use as a context manager, or `start()` / `close()`.
    """

    def __init__(self) -> None:
        self._manager = _Manager(ctx=mp_context())
        self._started = False

    def start(self) -> SharedObjects:
        """Start the helper process (returns `self`)."""
        self._manager.start()
        self._started = True
        return self

    @property
    def pid(self) -> int | None:
        """The helper process's pid, or `None` before `start`."""
        process = getattr(self._manager, "_process", None)
        return None if process is None else int(process.pid)

    def event(self) -> threading.Event:
        """A new shared `threading.Event`-like object."""
        event: threading.Event = self._manager.Event()
        return event

    def lock(self) -> threading.Lock:
        """A new shared lock."""
        lock: threading.Lock = self._manager.Lock()
        return lock

    def barrier(self, parties: int, *, timeout: float | None = None) -> threading.Barrier:
        """A new shared `threading.Barrier` for `parties` threads (`timeout` in seconds)."""
        barrier: threading.Barrier = self._manager.Barrier(parties, timeout=timeout)
        return barrier

    def list(self) -> Records:
        """A new shared append-only list."""
        records: Records = self._manager.Records()  # type: ignore[attr-defined]
        return records

    def close(self) -> None:
        """Stop the helper process (its objects stop working)."""
        if self._started:
            self._started = False
            self._manager.shutdown()

    def __enter__(self) -> SharedObjects:
        return self.start()

    def __exit__(self, *_: object) -> None:
        self.close()
