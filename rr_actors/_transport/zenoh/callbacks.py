"""Zenoh's callback threads, and rr_actors' threads that call Zenoh, ended before the
interpreter finalizes.

A thread that takes the GIL then aborts the process (cpython#87135, pyo3#4874). How and
why: docs/explanation/inside.md ("Zenoh's threads at the end").
"""

from __future__ import annotations

import contextlib
import threading
import time
import weakref
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

if TYPE_CHECKING:
    import zenoh

T = TypeVar("T")

END_TIMEOUT = 2.0
"""Seconds a session's close waits for its callback threads and its workers to end."""


class Worker(Protocol):
    """A thread of rr_actors that calls Zenoh: its owner closes it, the session joins it."""

    @property
    def name(self) -> str: ...
    def join(self, timeout: float | None) -> bool: ...
    def on_own_thread(self) -> bool: ...
    def close(self, *, timeout: float | None = 0.0) -> bool: ...  # queued get `timeout` s


_Ref = weakref.ref[Any]

_cond = threading.Condition()
_live: dict[str, set[_Ref]] = {}  # session's Zenoh id -> one per callback thread not ended
_ending: dict[str, list[threading.Thread]] = {}  # threads whose callback was dropped
_workers: dict[str, weakref.WeakSet[Worker]] = {}  # session's Zenoh id -> its workers
_ended: set[str] = set()  # sessions whose close waited for their workers: none registers now
_calls: dict[str, int] = {}  # session's Zenoh id -> calls under way on other threads (`calling`)
_local = threading.local()  # `.callback`: the session whose tracked callback this thread runs


def worker(session: zenoh.Session, executor: Worker) -> bool:
    """Count `executor` (weakly) among what the session's close joins; whether it was."""
    zid = str(session.zid())
    with _cond:
        if zid not in _ended:
            _workers.setdefault(zid, weakref.WeakSet()).add(executor)
            return True
    executor.close(timeout=0)
    executor.join(END_TIMEOUT)  # (on its own thread: returns at once)
    return False


class SessionEndedError(Exception):
    """A Zenoh call refused before it began: its session closed (`calling`)."""


@contextlib.contextmanager
def calling(session: zenoh.Session) -> Iterator[None]:
    """Around a Zenoh call on a thread no close joins: the close waits for it.

    Raises `SessionEndedError` once the session closed.
    """
    zid = str(session.zid())
    with _cond:
        if zid in _ended:
            raise SessionEndedError(f"session {zid} closed")
        _calls[zid] = _calls.get(zid, 0) + 1
    try:
        yield
    finally:
        with _cond:
            left = _calls[zid] - 1
            if left:
                _calls[zid] = left
            else:
                del _calls[zid]
                _cond.notify_all()


def tracked(session: zenoh.Session, callback: Callable[[T], object]) -> zenoh.handlers.Callback[T]:
    """`callback`, to declare on `session`, with its Zenoh thread tracked until it ends."""
    import zenoh  # noqa: PLC0415 - (the observer's modules import this one without Zenoh)

    zid = str(session.zid())

    def run(sample: T) -> None:
        _local.callback = zid
        try:
            callback(sample)
        finally:
            _local.callback = None

    def gone(ref: _Ref) -> None:  # (its thread ended, or never began: a failed declare)
        with _cond:
            refs = _live.get(zid, set())
            refs.discard(ref)
            if not refs:
                _live.pop(zid, None)
            _cond.notify_all()

    def dropped() -> None:  # (Zenoh's `drop`, on the callback's thread as it ends)
        with _cond:
            threads = [thread for thread in _ending.get(zid, ()) if thread.is_alive()]
            _ending[zid] = [*threads, threading.current_thread()]
        gone(ref)

    ref = weakref.ref(run, gone)
    with _cond:
        _live.setdefault(zid, set()).add(ref)
    return zenoh.handlers.Callback(run, dropped)


def live(session: zenoh.Session) -> int:
    """How many callback threads of `session` have not ended."""
    with _cond:
        return len(_live.get(str(session.zid()), ()))


def wait_ended(session: zenoh.Session, timeout: float | None = None) -> list[str]:
    """After the session closed: wait for its workers, callback threads and calls,
    and refuse calls from now on. Returns what had not ended within `timeout` seconds.
    """
    deadline = time.monotonic() + (END_TIMEOUT if timeout is None else timeout)
    zid = str(session.zid())
    closed = session.is_closed()
    with _cond:
        if closed:  # (a worker registered from now on is joined at once: `worker`)
            _ended.add(zid)
        workers = list(_workers.pop(zid, ()))
    left = sorted(
        executor.name
        for executor in workers
        if not executor.on_own_thread() and not executor.join(max(0.0, deadline - time.monotonic()))
    )
    own = 1 if getattr(_local, "callback", None) == zid else 0  # (closed from its callback)
    with _cond:
        _cond.wait_for(
            lambda: len(_live.get(zid, ())) <= own and not (closed and _calls.get(zid)),
            max(0.0, deadline - time.monotonic()),
        )
        ending = _ending.pop(zid, [])
        calls = _calls.get(zid, 0) if closed else 0
    me = threading.current_thread()
    for thread in ending:
        if thread is not me:
            thread.join(max(0.0, deadline - time.monotonic()))
    with _cond:
        running = max(len(_live.get(zid, ())) - own, 0)
    running += sum(thread.is_alive() for thread in ending if thread is not me)
    if running:
        left.append(f"{running} Zenoh callback threads")
    if calls:
        left.append(f"{calls} Zenoh calls of other threads")
    return left
