"""Zenoh's callback threads, ended before the interpreter finalizes.

zenoh-python runs each Python callback (a subscriber's, a queryable's, a liveliness
subscriber's, a listener's) on a `threading.Thread` of its own, which waits in Rust for
the next sample with the GIL released, and ends once its declaration went (undeclared, or
its session closed). Declared from a daemon thread (an actor's, a manager's) that thread
is a daemon too, which the interpreter does not wait for. On CPython < 3.14 a thread that
takes the GIL once the interpreter finalizes is ended by `pthread_exit`, whose unwinding
through Zenoh's Rust frames makes glibc abort the process ("FATAL: exception not
rethrown", SIGABRT; cpython#87135, pyo3#4874): a callback running as the program ends,
or a callback thread woken by its session's close a moment too late.

```
 declare_*(key, tracked(session, fn))   its thread is counted (per session) while it lives
   zenoh's thread per callback ─► fn(sample) ... until the declaration goes
 ZenohCarrier.leave: session.close() ─► wait_ended(session): each such thread ended, joined
   (the exit hook closes a network left open as the main thread ends: `_core.exit`,
    before the interpreter finalizes)
```

How a thread is seen to end without a hook in zenoh-python: Zenoh calls the callback's
`drop` on its thread as the thread ends (which names the thread, to join it). A
declaration that failed before Zenoh made its thread never calls it, but drops the
function at once (a weak reference says so): nothing is left to wait for. (The function
of a thread that ended is dropped later, when pyo3 next runs: not the end's signal.)
"""

from __future__ import annotations

import threading
import time
import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

if TYPE_CHECKING:
    import zenoh

__all__ = ["END_TIMEOUT", "live", "tracked", "wait_ended"]

T = TypeVar("T")

END_TIMEOUT = 2.0
"""Seconds a session's close waits for its callback threads to end (they end at once: a
callback of the carrier queues what it gets, never blocks)."""

_Ref = weakref.ref[Any]

_cond = threading.Condition()
_live: dict[str, set[_Ref]] = {}  # session's Zenoh id -> one per callback thread not ended
_ending: dict[str, list[threading.Thread]] = {}  # threads whose callback was dropped
_local = threading.local()  # `.callback`: the session whose tracked callback this thread runs


def tracked(session: zenoh.Session, callback: Callable[[T], object]) -> zenoh.handlers.Callback[T]:
    """`callback`, to declare on `session` (any `declare_*` that takes a handler): called
    on Zenoh's callback thread for it, one sample at a time, as `callback` is."""
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


def wait_ended(session: zenoh.Session, timeout: float = END_TIMEOUT) -> bool:
    """Wait until every callback thread of `session` ended (the session closed, or their
    declarations went), and join each: none then runs Python again.

    Called after the session closed (the caller's thread; on a callback's own thread, that
    one is not waited for). Returns whether all ended within `timeout` seconds.
    """
    deadline = time.monotonic() + timeout
    zid = str(session.zid())
    own = 1 if getattr(_local, "callback", None) == zid else 0  # (closed from its callback)
    with _cond:
        ended = _cond.wait_for(lambda: len(_live.get(zid, ())) <= own, timeout)
        ending = _ending.pop(zid, [])
    me = threading.current_thread()
    for thread in ending:
        if thread is not me:
            thread.join(max(0.0, deadline - time.monotonic()))
    return ended and not any(thread.is_alive() for thread in ending if thread is not me)
