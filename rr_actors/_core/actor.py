"""pykka's threading actor with hand-offs that wake the other thread once, not twice.

Every use of pykka's extension points (`_create_actor_inbox`, `_create_future`,
`_start_actor_loop`) and private names is in this file. `Actor` has an inbox (a `LateQueue`:
a `queue.SimpleQueue` whose items go to a handler once it closed), `OneShotFuture`s, an
`on_late` for every envelope its loop leaves or gets after it ended, and a *turn*: one
thread at a time handles its messages, in order:

```
 deliver(ref, message) (a carrier's receiving thread: it holds no lock)
   ├─ a kind the actor lets in (`Actor.inline`), its turn free, and every message put
   │  before this one handled (`Inbox.handled` == this one's ticket)?
   │     handle it here, in the turn; the actor's thread sleeps on
   └─ otherwise: put it in the inbox (the actor's thread handles it in order)
 the actor's thread: get an envelope ─► take the turn ─► handle it (and, with `drain`,
   the envelopes waiting after it, a bounded number) ─► on_turn_end ─► give the turn back
```

Why: docs/explanation/inside.md, "One wake-up per hand-off".
"""

from __future__ import annotations

import itertools
import logging
import math
import queue
import sys
import types
from collections.abc import Callable
from types import TracebackType
from typing import Any, Self, TypeAlias, TypeVar

import pykka

from rr_actors._core import runtime
from rr_actors._platform import forkserver

__all__ = [
    "SIGNAL_CHECK",
    "Actor",
    "ContainedError",
    "Inbox",
    "Late",
    "LateQueue",
    "OneShotFuture",
    "awaiting",
    "deliver",
    "mark_awaiting",
    "on_actor_thread",
    "refuse",
]

_pykka_logger = logging.getLogger("pykka")  # (where pykka's own loop logs)
_logger = logging.getLogger("rr_actors")

_CALLBACKS_MADE = runtime.Lock()  # (`OneShotFuture.add_done_callback`: the first list)

_loop_numbers = itertools.count()  # (the actors' threads' names)

_ACTOR_THREAD = runtime.local()  # `active` on the thread of an `Actor`'s loop


def on_actor_thread() -> bool:
    """Whether the calling thread runs an actor's loop or steps an awaited operation: such a thread
    must never wait on the network (a carrier answers there from what it knows)."""
    flags = _ACTOR_THREAD.__dict__  # (this thread's: a `getattr` that misses raises inside)
    return bool(flags.get("active", False) or flags.get("awaiting", False))


def awaiting() -> bool:
    """Whether the calling thread steps an awaited operation now (`mark_awaiting`)."""
    return bool(_ACTOR_THREAD.__dict__.get("awaiting", False))


def mark_awaiting(on: bool) -> None:
    _ACTOR_THREAD.awaiting = on


T = TypeVar("T")

# pykka's own (private) aliases: what `sys.exc_info()` returns, and a get hook
OptExcInfo: TypeAlias = tuple[
    type[BaseException] | None, BaseException | None, TracebackType | None
]
GetHookFunc: TypeAlias = Callable[[float | None], T]


SIGNAL_CHECK = 0.1
"""Seconds the main thread blocks at most in one go in a future's wait (so Ctrl-C is seen)."""


class OneShotFuture(pykka.Future[T]):
    """A pykka future handed over by releasing one lock: `pykka.ThreadingFuture`'s interface,
    settling twice raises `queue.Full`, plus `add_done_callback` (how a loop awaits it)."""

    def __init__(self) -> None:
        super().__init__()
        self._claim = runtime.Lock()  # taken, never released, by whatever settles it
        self._ready = runtime.Lock()  # held until settled; waiters pass it on
        self._ready.acquire()
        self._settled = False
        self._value: Any = None
        self._exc_info: OptExcInfo | None = None
        self._done_callbacks: list[Callable[[OneShotFuture[T]], object]] | None = None

    def __repr__(self) -> str:
        return "<rr_actors.OneShotFuture>"

    def _wait(self, timeout: float | None = None) -> bool:
        """Block until settled, at most `timeout` s; whether it is (a wait that runs out looks once
        more). The main thread waits in `SIGNAL_CHECK` slices, so that a Ctrl-C is raised."""
        if self._settled:
            return True
        end: float | None = None  # (sliced: when the whole wait ends)
        if (timeout is None or timeout > SIGNAL_CHECK) and runtime.handles_signals():
            end = math.inf if timeout is None else runtime.monotonic() + timeout
        while True:
            if end is not None:
                timeout = min(SIGNAL_CHECK, end - runtime.monotonic())
            acquired = False
            try:
                if timeout is None:
                    acquired = self._ready.acquire()
                else:
                    acquired = self._ready.acquire(
                        timeout=min(max(timeout, 0.0), runtime.TIMEOUT_MAX)
                    )
            finally:  # (also if the wait is interrupted: other waiters must get through)
                if acquired:
                    self._ready.release()  # the next waiter, if any, gets through too
            if acquired or self._settled:
                return True
            if end is None or runtime.monotonic() >= end:
                return False

    def wait(self, timeout: float | None = None) -> bool:
        """Block until it is settled, at most `timeout` seconds; whether it is."""
        return self._wait(timeout)

    def get(self, *, timeout: float | None = None) -> T:
        if not self._wait(timeout):
            raise pykka.Timeout(f"{timeout} seconds")
        if self._get_hook is not None:
            with self._hook_lock:  # the hook runs once, however many threads get
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
        self._hook_lock = runtime.Lock()
        super().set_get_hook(func)
        self._settle()

    def _take_claim(self) -> None:
        if not self._claim.acquire(blocking=False):
            raise runtime.Full

    def add_done_callback(self, fn: Callable[[OneShotFuture[T]], object]) -> None:
        """Run `fn(self)` once settled (at once if it is, else on the settling thread), each
        callback once, in order; what one raises is logged. For quick wake-ups only."""
        callbacks = self._done_callbacks
        if callbacks is None:
            with _CALLBACKS_MADE:  # (two threads adding the first at once: one list)
                if self._done_callbacks is None:
                    self._done_callbacks = []
                callbacks = self._done_callbacks
        callbacks.append(fn)  # then read `_settled`: one of this and `_settle` sees the other
        if self._settled:
            self._run_done_callbacks(callbacks)

    def _settle(self) -> None:
        self._settled = True  # written before the release: a waiter that wakes sees it
        self._ready.release()
        callbacks = self._done_callbacks  # (read after `_settled` was written)
        if callbacks:
            self._run_done_callbacks(callbacks)

    def _run_done_callbacks(self, callbacks: list[Callable[[OneShotFuture[T]], object]]) -> None:
        """Run each of `callbacks` once (`pop` gives each to one thread)."""
        while True:
            try:
                fn = callbacks.pop(0)
            except IndexError:
                return
            try:
                fn(self)
            except Exception:
                _logger.exception("a done callback of a future raised")


Late = Callable[[Any], None]
"""Handles an item its consumer will not take any more (on any thread)."""


class LateQueue(queue.SimpleQueue[Any]):
    """A queue that, once closed, hands what is left and what is put later to `late`, each item
    once. Its methods call `_put`, not `SimpleQueue.put`: a simulation subclasses it."""

    _late: Late | None = None
    _put = queue.SimpleQueue.put

    def __new__(cls) -> Self:
        made: Self = super().__new__(runtime.queue_class(cls))
        return made

    def put(self, item: Any, block: bool = True, timeout: float | None = None) -> None:
        self._put(item, block, timeout)
        if self._late is not None:
            self._drain(self._late)

    def close(self, late: Late) -> None:
        """Its consumer ended: hand what is here, and what comes later, to `late`."""
        self._late = late
        self._drain(late)

    def _drain(self, late: Late) -> None:
        while True:
            try:
                item = self.get_nowait()
            except runtime.Empty:
                return
            late(item)


class Inbox(LateQueue):
    """An actor's inbox with its turn; once closed, what is left and what arrives goes to `late`.
    Each envelope takes a ticket; one is handled in the turn only once `handled` equals it."""

    def __init__(self) -> None:
        super().__init__()
        self.turn = runtime.Lock()
        self.handled = 0
        self.stopped = False  # a handler run in the turn stopped the actor
        self._tickets = itertools.count()
        self._run: Callable[[Any], None] | None = None  # set once the actor's loop runs

    def put(self, item: Any, block: bool = True, timeout: float | None = None) -> None:
        next(self._tickets)
        self._put(item, block, timeout)  # (`LateQueue.put`, one frame less)
        if self._late is not None:
            self._drain(self._late)

    def run_or_put(self, item: Any) -> None:
        """Handle `item` on this thread in the turn if the actor is idle, else put it."""
        ticket = next(self._tickets)
        run = self._run
        if run is not None and self.turn.acquire(blocking=False):
            try:
                if self.handled == ticket and self._late is None:
                    try:
                        run(item)
                    finally:
                        self.handled += 1
                    return
            finally:
                self.turn.release()
        LateQueue.put(self, item)  # (its ticket is taken)


def refuse(envelope: Any) -> None:
    """Answer an envelope as pykka's final drain does: a stop as done, an ask `ActorDeadError`."""
    if envelope.reply_to is None:
        return
    if isinstance(envelope.message, pykka.messages._ActorStop):  # (as pykka's own drain)
        envelope.reply_to.set(None)
        return
    error = pykka.ActorDeadError("the actor stopped before handling the message")
    envelope.reply_to.set_exception((pykka.ActorDeadError, error, None))


_WAKE = pykka._envelope.Envelope(None)
"""Put when a handler run in the turn stopped the actor: its thread wakes and ends."""


def deliver(ref: pykka.ActorRef[Any], message: Any) -> None:
    """`ref.tell(message)`, or handled on this thread in an idle `Actor`'s turn (`Actor.inline`);
    the caller holds no lock a handler might take. `pykka.ActorDeadError` if it is not running."""
    if type(message) not in ref.actor_class.inline:
        ref.tell(message)
        return
    if not ref.is_alive():
        raise pykka.ActorDeadError(f"{ref} not found")
    inbox = ref.actor_inbox
    assert isinstance(inbox, Inbox)  # (an `Actor`'s: only it lets kinds in)
    inbox.run_or_put(pykka._envelope.Envelope(message))


class ContainedError(RuntimeError):
    """A handler raised a `BaseException` not an `Exception`: it fails that actor alone (pykka
    would take it for the process going down and stop every actor)."""


class Actor(pykka.ThreadingActor):
    """`pykka.ThreadingActor` with an `Inbox`, `OneShotFuture`s and the turn, on a daemon thread
    (`rr_actors._core.exit` stops actors cleanly first)."""

    use_daemon_thread = True
    actor_inbox: Inbox

    inline: frozenset[type] = frozenset()
    """The message kinds `deliver` may handle in this actor's turn; none by default."""

    drain: int = 1
    """Messages one turn handles at most (those already waiting after the first), within
    `drain_seconds`. 1: a turn a message.
    """

    drain_seconds: float = 0.0
    ends_turns: bool = False
    """Whether `on_turn_end` runs at the end of each turn."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # pykka makes these with `threading` and `uuid`: the runtime's instead
        stopped = runtime.Event()
        self.actor_stopped = self._actor_ref.actor_stopped = stopped
        self.actor_urn = self._actor_ref.actor_urn = f"urn:uuid:{runtime.new_id()}"

    def _handle_receive(self, message: Any) -> Any:
        try:
            return super()._handle_receive(message)
        except Exception:
            raise
        except BaseException as exc:  # pykka would stop every actor of the process
            raise ContainedError(
                f"{type(self).__name__} failed: a handler raised {type(exc).__qualname__}"
            ) from exc

    @staticmethod
    def _create_actor_inbox() -> Inbox:
        return Inbox()

    @staticmethod
    def _create_future() -> pykka.Future[Any]:
        return OneShotFuture()

    def _start_actor_loop(self) -> None:
        name = f"{type(self).__name__}-{next(_loop_numbers)}"  # (as pykka names it)
        runtime.Thread(target=self._actor_loop, name=name, daemon=self.use_daemon_thread).start()

    def _actor_loop_setup(self) -> None:
        _ACTOR_THREAD.active = True  # (on the actor's new thread: `on_actor_thread`)
        super()._actor_loop_setup()

    def _actor_loop_running(self) -> None:
        # pykka's loop, each envelope handled in the turn (module docstring)
        inbox = self.actor_inbox
        if self.inline:
            inbox._run = self._run_in_turn
        while not self.actor_stopped.is_set():
            envelope = inbox.get()
            with inbox.turn:
                try:
                    if inbox.stopped:  # by a handler run in the turn meanwhile
                        if envelope is not _WAKE:
                            self.on_late(envelope)
                        return
                    self._handle_envelope(envelope)
                finally:
                    inbox.handled += 1
                if self.drain > 1:
                    self._drain_inbox(inbox)
                if self.ends_turns:
                    self._end_turn()

    def _drain_inbox(self, inbox: Inbox) -> None:
        """Handle the envelopes waiting in `inbox`, within `drain` and `drain_seconds`."""
        handled = 1
        until = runtime.monotonic() + self.drain_seconds
        while (
            handled < self.drain
            and not inbox.empty()
            and not inbox.stopped
            and not self.actor_stopped.is_set()
            and runtime.monotonic() < until
        ):
            envelope = inbox.get()  # (this thread is its only reader: it is there)
            try:
                self._handle_envelope(envelope)
            finally:
                inbox.handled += 1
            handled += 1

    def _run_in_turn(self, envelope: Any) -> None:
        was = getattr(_ACTOR_THREAD, "active", False)
        _ACTOR_THREAD.active = True
        try:
            self._handle_envelope(envelope)
            if self.ends_turns:
                self._end_turn()
        finally:
            _ACTOR_THREAD.active = was
        if self.actor_stopped.is_set():  # it failed or stopped: the actor's thread ends
            self.actor_inbox.stopped = True
            self.actor_inbox.put(_WAKE)

    def _end_turn(self) -> None:
        """`on_turn_end`; what it raises fails the actor as a tell's handler's failure does."""
        try:
            self.on_turn_end()
        except Exception:  # noqa: BLE001 - (as a tell's failure: `on_failure`, the actor stops)
            self._fail()
        except BaseException:  # noqa: BLE001 - (as pykka: the process is going down)
            self._stop()
            pykka.ActorRegistry.stop_all()

    def _fail(self) -> None:
        """As pykka for a failed tell: logged, `on_failure` runs (failing: logged), it stops."""
        self._handle_failure(*sys.exc_info())
        try:
            self.on_failure(*sys.exc_info())
        except Exception:  # noqa: BLE001 - (as pykka: logged, the actor stops)
            self._handle_failure(*sys.exc_info())

    def _handle_envelope(self, envelope: Any) -> None:
        try:
            response = self._handle_receive(envelope.message)
            if envelope.reply_to is not None:
                envelope.reply_to.set(response)
        except Exception:
            if envelope.reply_to is not None:
                _pykka_logger.info(
                    f"Exception returned from {self} to caller:", exc_info=sys.exc_info()
                )
                envelope.reply_to.set_exception()
            else:
                self._fail()
        except BaseException:  # noqa: BLE001 - (as pykka: the process is going down)
            self._stop()
            pykka.ActorRegistry.stop_all()

    def _actor_loop_teardown(self) -> None:
        # Instead of pykka's drain, which answers asks and drops tells.
        self.actor_inbox.close(self.on_late)
        self.on_ended()

    def end_now(self) -> None:
        """End this actor from its own thread at once; the rest of its inbox goes to `on_late`."""
        self._stop()

    def on_turn_end(self) -> None:
        """Run at the end of each turn when `ends_turns`, in it (a registrar commits its turn's
        changes here, then releases their answers)."""

    def on_ended(self) -> None:
        """Run on the actor's thread once its loop ended and its inbox went to `on_late`."""

    def on_late(self, envelope: Any) -> None:
        """An envelope that arrived after the loop ended (on the actor's thread for what was left,
        the sender's for what comes later): `refuse` it, unless overridden (thread-safely)."""
        refuse(envelope)


def _forget_actors() -> None:
    """In a forked child: every actor of the parent is dead (new events and registry lock: a
    parent's thread may have held the old ones)."""
    pykka.ActorRegistry._actor_refs_lock = runtime.RLock()
    for ref in pykka.ActorRegistry.get_all():
        stopped = runtime.Event()
        stopped.set()
        ref.actor_stopped = stopped
        pykka.ActorRegistry.unregister(ref)


forkserver.after_fork_in_child("the parent's actors", _forget_actors)


def _fresh_registry() -> object:
    return types.SimpleNamespace(_actor_refs=[], _actor_refs_lock=runtime.RLock())


runtime.process_state(pykka.ActorRegistry, _fresh_registry)
