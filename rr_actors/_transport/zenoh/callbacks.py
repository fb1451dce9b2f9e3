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
 declare_*(key, tracked(fn))   one per callback: its thread is counted while it lives
   zenoh's thread per callback ─► fn(sample) ... until the declaration goes
 ZenohCarrier.leave: session.close() ─► wait_ended(): every counted thread ended (joined)
   (the exit hook closes a network left open as the main thread ends: `_core.exit`,
    before the interpreter finalizes)
```

How a thread is seen to end without a hook in zenoh-python: the function given to Zenoh
is held by its thread's closure until the thread's end, where it is dropped (a weak
reference says so) right after Zenoh calls the callback's `drop` (which names the thread,
to join it). A declaration that failed before Zenoh made its thread drops the function at
once: nothing is left to wait for.
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

_cond = threading.Condition()
_live: set[weakref.ref[Callable[[Any], None]]] = set()  # one per callback thread not ended
_ending: list[threading.Thread] = []  # threads whose callback was dropped: joined next
_local = threading.local()  # `.callback`: this thread runs a tracked callback


def tracked(callback: Callable[[T], object]) -> zenoh.handlers.Callback[T]:
    """`callback`, to declare on a Zenoh session (any `declare_*` that takes a handler):
    called on Zenoh's callback thread for it, one sample at a time, as `callback` is."""
    import zenoh  # noqa: PLC0415 - (the observer's modules import this one without Zenoh)

    def run(sample: T) -> None:
        _local.callback = True
        callback(sample)

    with _cond:
        _live.add(weakref.ref(run, _gone))
    return zenoh.handlers.Callback(run, _dropped)


def _dropped() -> None:
    """Zenoh's `drop`: the callback's thread ends (it runs there)."""
    with _cond:
        _ending[:] = [thread for thread in _ending if thread.is_alive()]
        _ending.append(threading.current_thread())


def _gone(ref: weakref.ref[Callable[[Any], None]]) -> None:
    with _cond:
        _live.discard(ref)
        _cond.notify_all()


def live() -> int:
    """How many callback threads of this process have not ended."""
    with _cond:
        return len(_live)


def wait_ended(timeout: float = END_TIMEOUT) -> bool:
    """Wait until every callback thread of this process ended (its session closed, or its
    declaration went), and join each: none then runs Python again.

    Called after a session closed (the caller's thread; on a callback's own thread, that
    one is not waited for). Returns whether all ended within `timeout` seconds.
    """
    deadline = time.monotonic() + timeout
    own = 1 if getattr(_local, "callback", False) else 0  # (closed from a callback)
    with _cond:
        ended = _cond.wait_for(lambda: len(_live) <= own, timeout)
        ending, _ending[:] = list(_ending), []
    me = threading.current_thread()
    for thread in ending:
        if thread is not me:
            thread.join(max(0.0, deadline - time.monotonic()))
    return ended and not any(thread.is_alive() for thread in ending if thread is not me)
