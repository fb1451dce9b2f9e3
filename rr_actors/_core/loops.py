"""asyncio at the edge of the actors: awaiting a future, running coroutines on a loop.

```
 an event loop awaits a one-shot future (`settled`):
   loop thread: future.add_done_callback(wake) ──► await a loop future
   the settling thread (an actor, a connection's reader): wake ──► call_soon_threadsafe
   ──► the loop resolves its future ──► the awaiting task goes on (no thread blocked)
 steps (`replies.Steps`) driven on a loop: `run_steps_async`, each `Wait` is `settled`
 a coroutine function run on a loop, from any thread (`OnLoop`):
   submit(*args, then) ──call_soon_threadsafe──► a task: fn(*args), after the task of
   the submission before it ──► then(error) on the loop thread once it ended
```

A coroutine callback with no loop of its own runs on the process's loop (`process_loop`):
one thread for all (a coroutine that awaits costs no thread).
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import functools
import logging
from collections.abc import Callable
from typing import Any, TypeVar

from rr_actors._core import runtime, traces
from rr_actors._core.actor import OneShotFuture, mark_awaiting
from rr_actors._core.replies import Steps, left, let_go, when_waiting
from rr_actors._platform import forkserver

logger = logging.getLogger("rr_actors")

T = TypeVar("T")

Then = Callable[[BaseException | None], object]
"""Told once a coroutine submitted to a loop ended: its error, or `None`."""


def is_coroutine_function(fn: object) -> bool:
    """Whether `fn` returns a coroutine (`async def`, a partial of one, an async `__call__`)."""
    if asyncio.iscoroutinefunction(fn):
        return True
    call = getattr(fn, "__call__", None)  # noqa: B004 - (the method, not callable())
    return call is not None and asyncio.iscoroutinefunction(call)


def _wake(waiter: asyncio.Future[bool], value: bool) -> None:
    if not waiter.done():
        waiter.set_result(value)


def _wake_from(loop: asyncio.AbstractEventLoop, waiter: asyncio.Future[bool], _: object) -> None:
    try:
        loop.call_soon_threadsafe(_wake, waiter, True)
    except RuntimeError:  # the loop was closed: its task is gone with it
        return


async def settled(future: OneShotFuture[Any], timeout: float | None) -> bool:
    """Await `future` (settled by any thread) at most `timeout` seconds; whether it is. No thread
    waits: its done callback wakes the loop."""
    if future._settled:
        return True
    loop = asyncio.get_running_loop()
    waiter: asyncio.Future[bool] = loop.create_future()
    expiry = None if timeout is None else loop.call_later(timeout, _wake, waiter, False)
    future.add_done_callback(functools.partial(_wake_from, loop, waiter))
    try:
        return await waiter or future._settled
    finally:
        if expiry is not None:
            expiry.cancel()


async def run_steps_async(steps: Steps[T]) -> T:
    """Run `steps` on the running loop (`settled`); a cancellation is thrown in at their `yield`."""
    mark_awaiting(True)  # (each step: this thread may take an idle actor's turn)
    try:
        future, deadline = next(steps)
        while True:
            if future._settled:  # (settled already: a dedup hit answered in the turn)
                future, deadline = steps.send(True)
                continue
            mark_awaiting(False)  # (the loop runs other tasks while this one waits)
            let_go()
            try:
                done = await settled(future, left(deadline))
            except BaseException as exc:  # noqa: BLE001 - (the task cancelled: the steps decide)
                mark_awaiting(True)
                future, deadline = steps.throw(exc)
                continue
            mark_awaiting(True)
            future, deadline = steps.send(done)
    except StopIteration as ended:
        result: T = ended.value
        return result
    finally:
        mark_awaiting(False)


# -- coroutine functions run on a loop --------------------------------------------------


class _ProcessLoop:
    """The process's own event loop, on one daemon thread started at its first use."""

    def __init__(self) -> None:
        self._lock = runtime.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self.ident: int | None = None  # its thread's

    def get(self) -> asyncio.AbstractEventLoop:
        loop = self._loop
        if loop is not None:
            return loop
        with self._lock:
            if self._loop is None:
                started = runtime.Event()
                loop = runtime.new_event_loop()
                thread = runtime.Thread(
                    target=self._run, args=(loop, started), name="rr-loop", daemon=True
                )
                thread.start()
                started.wait()
                self.ident = thread.ident
                self._loop = loop
            return self._loop

    @staticmethod
    def _run(loop: asyncio.AbstractEventLoop, started: runtime.Event) -> None:
        asyncio.set_event_loop(loop)
        loop.call_soon(started.set)
        loop.run_forever()

    def forget(self) -> None:
        self._lock = runtime.Lock()
        self._loop = None
        self.ident = None


_PROCESS_LOOP = runtime.process_state(_ProcessLoop(), _ProcessLoop)
forkserver.after_fork_in_child("the process's event loop", _PROCESS_LOOP.forget)


def on_process_loop() -> bool:
    return _PROCESS_LOOP.ident == runtime.get_ident()


def process_loop() -> asyncio.AbstractEventLoop:
    """The process's own event loop (module docstring), started on first use."""
    return _PROCESS_LOOP.get()


class OnLoop:
    """A coroutine function and the event loop it runs on; submitted from any thread.
    Calls of one key (a callback's query id) run one at a time in order, unless one waits for
    a registrar (`replies.let_go`); each in a copy of the binder's context, with only its run's
    OpenTelemetry span current (`own`)."""

    __slots__ = ("_context", "_tails", "fn", "loop")

    _tails: dict[Any, tuple[asyncio.Task[None], asyncio.Event]]

    def __init__(self, fn: Callable[..., Any], loop: asyncio.AbstractEventLoop) -> None:
        self.fn = fn
        self.loop = loop
        self._context = contextvars.copy_context()
        self._tails = {}  # key -> its last call, and whether it let go (loop thread)

    @classmethod
    def bind(cls, fn: Callable[..., Any]) -> OnLoop:
        """`fn` on the loop running on this thread, else on the process's own loop."""
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            loop = process_loop()
        return cls(fn, loop)

    def __repr__(self) -> str:
        return f"<OnLoop {getattr(self.fn, '__qualname__', self.fn)!r}>"

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickle as the coroutine function alone: the other process binds a loop of its own."""
        return (_unbound, (self.fn,))

    def __call__(self, *args: Any) -> None:
        self.submit(*args)

    def submit(
        self,
        *args: Any,
        then: Then | None = None,
        key: Any = None,
        waits: Callable[[], object] | None = None,
        own: tuple[str, str, str] | None = None,
    ) -> None:
        """Run `fn(*args)` on the loop after the calls of `key` before; `then(error)` on the loop
        thread once it ended, `waits()` (any thread) as it lets the next go, `own` its run's span. A
        closed loop runs nothing: `then` gets a `RuntimeError` here."""
        try:
            self.loop.call_soon_threadsafe(self._start, args, then, key, waits, own)
        except RuntimeError as exc:  # the loop was closed
            if then is not None:
                then(exc)

    def _start(
        self,
        args: tuple[Any, ...],
        then: Then | None,
        key: Any,
        waits: Callable[[], object] | None,
        own: tuple[str, str, str] | None,
    ) -> None:
        before = self._tails.get(key)
        going = asyncio.Event()
        task = self.loop.create_task(
            self._run(before, going, args, then, key, waits, own), context=self._context.copy()
        )  # (a copy each: what one call sets in its context is its own)
        self._tails[key] = (task, going)

    async def _run(
        self,
        before: tuple[asyncio.Task[None], asyncio.Event] | None,
        going: asyncio.Event,
        args: tuple[Any, ...],
        then: Then | None,
        key: Any,
        waits: Callable[[], object] | None,
        own: tuple[str, str, str] | None,
    ) -> None:
        if before is not None:
            await _behind(*before)
        error: BaseException | None = None
        # (this task's context)
        when_waiting(functools.partial(_set_soon, self.loop, going, waits))
        # (its run's span current across its awaits; else none, not the binder's)
        traces.own_trace(own)
        try:
            await self.fn(*args)
        except Exception as exc:  # logged, as a callback run on a worker thread is
            logger.exception("coroutine callback %r raised", self)
            error = exc
        except BaseException as exc:  # noqa: BLE001 - told to `then` (cancelled too)
            error = exc
        if then is not None:
            then(error)
        tail = self._tails.get(key)
        if tail is not None and tail[0] is asyncio.current_task():
            del self._tails[key]


def _set_soon(
    loop: asyncio.AbstractEventLoop, event: asyncio.Event, waits: Callable[[], object] | None
) -> None:
    with contextlib.suppress(RuntimeError):
        loop.call_soon_threadsafe(event.set)
    if waits is not None:
        waits()


async def _behind(before: asyncio.Task[None], going: asyncio.Event) -> None:
    """Until the call `before` ended, or let the next of its key go (`going`)."""
    if before.done() or going.is_set():
        return
    waiter = asyncio.ensure_future(going.wait())
    try:
        await asyncio.wait((before, waiter), return_when=asyncio.FIRST_COMPLETED)
    finally:
        waiter.cancel()


def _unbound(fn: Callable[..., Any]) -> Callable[..., Any]:
    return fn
