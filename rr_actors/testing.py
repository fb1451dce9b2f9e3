"""Helpers for testing code built on rr_actors (and rr_actors itself).

Placement-independent helpers: [`crash`][rr_actors.testing.crash] and
[`catalog_snapshot`][rr_actors.testing.catalog_snapshot] accept a `ResourceRegistrar` (a
registrar in this process) or a [`RemoteRegistrar`][rr_actors.testing.RemoteRegistrar] (a
registrar in a manager process of a system). A `RemoteRegistrar` has the methods of a
`ResourceRegistrar`, so one test body exercises both placements.

State that a test shares with callbacks which may run in another process (journals,
events, barriers) comes from [`SharedObjects`][rr_actors.testing.SharedObjects].
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable, Iterator
from multiprocessing.managers import BaseProxy, SyncManager
from typing import Any

import cloudpickle
import pykka

from rr_actors._core.replies import FutureReply, wait
from rr_actors._process.manager import mp_context
from rr_actors._process.remote import FORWARD_MARGIN, RemoteRegistrar
from rr_actors._registrar.registrar import CatalogView, ResourceRegistrar, _Crash, _Request

__all__ = [
    "CatalogView",
    "Records",
    "RemoteRegistrar",
    "SharedObjects",
    "catalog_snapshot",
    "crash",
    "running_actors",
]


# -- placement-independent helpers -----------------------------------------------------


def crash(registrar: ResourceRegistrar | RemoteRegistrar, *, timeout: float = 5.0) -> None:
    """Make a registrar die as if it hit a bug: no cleanup the way `stop()` would do it.

    For a `ResourceRegistrar` its actor dies (the in-process analogue of SIGKILL); for a
    `RemoteRegistrar` its manager process gets SIGKILL. Either way its callers get
    `RegistrarUnavailableError`, its backup keeps what was written, and unless a supervisor
    will restart it, the providers release its consumer ids (death watch). Returns once it
    is dead and the providers were told.

    Args:
        registrar: the registrar to kill.
        timeout: seconds to wait for its death.
    """
    if isinstance(registrar, RemoteRegistrar):
        registrar.kill(timeout=timeout)
        return
    registrar._ref.tell(_Crash())
    registrar._died.wait(timeout)  # the actor's death handling ran, death watch included


def catalog_snapshot(
    registrar: ResourceRegistrar | RemoteRegistrar, *, timeout: float = 5.0
) -> CatalogView:
    """A copy of the registrar's catalog rows, after checking the catalog's invariants.

    Args:
        registrar: a registrar of this process, or a `RemoteRegistrar` (the snapshot is
            taken in its process and sent back).
        timeout: seconds to wait for the registrar.

    Raises:
        AssertionError: an index of the catalog disagrees with its rows.
        CallTimeoutError: no answer within `timeout` seconds.
        RegistrarUnavailableError: the registrar died.
    """
    if isinstance(registrar, RemoteRegistrar):
        snapshot = functools.partial(catalog_snapshot, timeout=timeout)
        remote: CatalogView = registrar.run(snapshot, timeout=timeout + FORWARD_MARGIN)
        return remote
    reply = FutureReply()
    registrar._ref.tell(_Request(lambda actor, r: actor.op_snapshot(r), reply))
    view: CatalogView = wait(reply.future, timeout, "catalog_snapshot()")
    return view


def running_actors() -> list[Any]:
    """The pykka actors still running in this process."""
    return list(pykka.ActorRegistry.get_all())


# -- state shared with callbacks in other processes ------------------------------------


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

    A `multiprocessing` `SyncManager` (one helper process, started with the forkserver or
    spawn context) holds the objects; what you get are proxies that pickle (cloudpickle
    too), so callbacks that captured them work in manager processes. Every process started
    by this one (same authkey) can use them.

    Use as a context manager, or `start()` / `close()`.
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
