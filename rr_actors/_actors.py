"""pykka's threading actor with hand-offs that wake the other thread once, not twice.

`pykka.ThreadingActor` keeps its mailbox in a `queue.Queue` and answers asks through a
`pykka.ThreadingFuture`; both are built on `threading.Condition`. A condition hands over
in two steps: `notify()` wakes the waiter, which then blocks again on the condition's
lock until the notifier leaves its `with` block. On the project's 2-core VM, where waking
a thread on the other core is the dominant cost, that made a raw pykka `ask` take 37-49 us
against 16-18 us for a `threading.Lock` ping-pong between the same two threads
(`benchmarks/bench_core.py` has the ask; docs/performance.md has the figures).

`Actor` plugs two cheaper parts into pykka through its documented extension points for
actor implementations (`_create_actor_inbox`, `_create_future`, `_start_actor_loop`;
pykka's own gevent and eventlet actors were built on them): a `queue.SimpleQueue` inbox
(written in C, one lock per hand-off) and `OneShotFuture`, which hands its value over by
releasing one lock. Everything else, the actor loop, `tell`, `ask`, `stop` and
`on_failure`, is pykka's.

It also closes a gap of pykka's: `ActorRef.ask` checks `is_alive()` and then puts its
envelope, while a stopping actor drains its inbox once, so an ask that passes the check
just before the actor stops can land after the drain and is never answered (its asker,
say a blocking `ActorRef.stop`, waits forever). `Mailbox` answers such late envelopes
with `ActorDeadError`, as the drain would have; `refuse` answers one envelope the same
way, for an actor that drains its own inbox (the registrar does when it stops).
"""

from __future__ import annotations

import itertools
import queue
import sys
import threading
from collections.abc import Callable
from types import TracebackType
from typing import Any, TypeAlias, TypeVar

import pykka

__all__ = ["Actor", "Mailbox", "OneShotFuture", "refuse"]

T = TypeVar("T")

# The shapes of pykka's own (private) aliases for what `sys.exc_info()` returns and for a
# get hook.
OptExcInfo: TypeAlias = tuple[
    type[BaseException] | None, BaseException | None, TracebackType | None
]
GetHookFunc: TypeAlias = Callable[[float | None], T]


class OneShotFuture(pykka.Future[T]):
    """A pykka future whose value is handed over by releasing one lock.

    Behaves as `pykka.ThreadingFuture`: `get(timeout=)` blocks until `set`,
    `set_exception` or `set_get_hook` settled it, raises `pykka.Timeout` after `timeout`
    seconds, and returns (or raises) the same value on every later `get`; settling it a
    second time raises `queue.Full`. Any number of threads may wait on it at once.
    """

    def __init__(self) -> None:
        super().__init__()
        self._claim = threading.Lock()  # taken, never released, by whatever settles it
        self._ready = threading.Lock()  # held until settled; waiters pass it on
        self._ready.acquire()
        self._settled = False
        self._value: Any = None
        self._exc_info: OptExcInfo | None = None

    def __repr__(self) -> str:
        return "<rr_actors.OneShotFuture>"

    def get(self, *, timeout: float | None = None) -> T:
        if not self._settled:
            if timeout is None:
                self._ready.acquire()
            elif not self._ready.acquire(timeout=min(max(timeout, 0.0), threading.TIMEOUT_MAX)):
                raise pykka.Timeout(f"{timeout} seconds")
            self._ready.release()  # the next waiter, if any, gets through too
        if self._get_hook is not None:
            return super().get(timeout=timeout)
        if self._exc_info is not None:
            exc_type, exc_value, exc_traceback = self._exc_info
            assert exc_type is not None
            if exc_value is None:
                exc_value = exc_type()
            if exc_value.__traceback__ is not exc_traceback:
                raise exc_value.with_traceback(exc_traceback)
            raise exc_value
        value: T = self._value
        return value

    def set(self, value: Any | None = None) -> None:
        self._take_claim()
        self._value = value
        self._settle()

    def set_exception(self, exc_info: OptExcInfo | None = None) -> None:
        assert exc_info is None or len(exc_info) == 3
        self._take_claim()
        self._exc_info = sys.exc_info() if exc_info is None else exc_info
        self._settle()

    def set_get_hook(self, func: GetHookFunc[T]) -> None:
        self._take_claim()
        super().set_get_hook(func)
        self._settle()

    def _take_claim(self) -> None:
        if not self._claim.acquire(blocking=False):
            raise queue.Full

    def _settle(self) -> None:
        self._settled = True  # written before the release: a waiter that wakes sees it
        self._ready.release()


class Mailbox(queue.SimpleQueue[Any]):
    """An actor's inbox that answers what still arrives once its actor's loop ended.

    pykka's loop drains the inbox when it ends (`ActorDeadError` to each asker); `close()`
    runs after that, and from then on whatever is put (by an `ask` that saw the actor
    alive a moment earlier) is answered at once the same way. The put and the close each
    drain after their own write, so an envelope is answered by whichever comes second.
    """

    closed = False

    def put(self, item: Any, block: bool = True, timeout: float | None = None) -> None:
        super().put(item, block, timeout)
        if self.closed:
            self._drain()

    def close(self) -> None:
        """The actor's loop ended: answer what is here and what comes later."""
        self.closed = True
        self._drain()

    def _drain(self) -> None:
        while True:
            try:
                refuse(self.get_nowait())
            except queue.Empty:
                return


def refuse(envelope: Any) -> None:
    """Answer a pykka envelope its actor will not handle, as pykka's own final drain does.

    An `ask` (a blocking `ActorRef.stop` included) gets `ActorDeadError`; a `tell` has
    nobody to answer.
    """
    if envelope.reply_to is not None:
        error = pykka.ActorDeadError("the actor stopped before handling the message")
        envelope.reply_to.set_exception((pykka.ActorDeadError, error, None))


_numbers = itertools.count()


class Actor(pykka.ThreadingActor):
    """`pykka.ThreadingActor` with a `Mailbox` (a `queue.SimpleQueue`) and `OneShotFuture`s."""

    actor_inbox: Mailbox

    @staticmethod
    def _create_actor_inbox() -> Mailbox:
        return Mailbox()

    @staticmethod
    def _create_future() -> pykka.Future[Any]:
        return OneShotFuture()

    def _start_actor_loop(self) -> None:
        # As pykka's ThreadingActor, plus closing the mailbox once the loop ended.
        thread = threading.Thread(
            target=self._run_actor_loop, name=f"{type(self).__name__}-{next(_numbers)}"
        )
        thread.daemon = self.use_daemon_thread
        thread.start()

    def _run_actor_loop(self) -> None:
        try:
            self._actor_loop()
        finally:
            self.actor_inbox.close()
