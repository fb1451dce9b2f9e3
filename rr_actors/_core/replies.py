"""Reply objects: where the answer to a message goes, and how a caller waits for it.

A protocol that waits is written once as *steps*, a generator that yields a `Wait` per future it
needs and is sent whether it settled in time ("sans I/O", as h11 is written). `run_steps` blocks the
calling thread on each; `loops.run_steps_async` awaits it on an event loop. An exception the driver
gets while it waits is thrown into the steps at the `yield`, so both drivers take the same way out:

```
 steps ──yield (future, deadline)──► driver: block / await until settled or deadline
       ◄──────── send(settled: bool) ───┘   (interrupted: throw(exc) at the yield)
 ... return value ──► the driver returns it (StopIteration)
```
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import inspect
import itertools
import logging
from collections.abc import Callable, Generator
from typing import Any, TypeAlias, TypeVar

import pykka

from rr_actors._core import runtime
from rr_actors._core.actor import OneShotFuture
from rr_actors.errors import CallTimeoutError

T = TypeVar("T")

logger = logging.getLogger("rr_actors")


class FutureReply:
    """Answers a pykka future; a second answer is ignored (the first one wins)."""

    __slots__ = ("future",)

    def __init__(self, future: OneShotFuture[Any] | None = None) -> None:
        self.future: OneShotFuture[Any] = future or OneShotFuture()

    def set_result(self, value: Any) -> None:
        with contextlib.suppress(runtime.Full):
            self.future.set(value)

    def set_error(self, error: BaseException) -> None:
        with contextlib.suppress(runtime.Full):
            self.future.set_exception((type(error), error, error.__traceback__))


def wait(future: pykka.Future[Any], timeout: float, what: str) -> Any:
    """Wait for `future` at most `timeout` seconds (after `let_go`): its value, its error, or
    `CallTimeoutError` naming `what`."""
    let_go()
    try:
        return future.get(timeout=timeout)
    except pykka.Timeout:
        raise CallTimeoutError(f"{what} timed out after {timeout:g} s") from None


Wait: TypeAlias = tuple[OneShotFuture[Any], float | None]
"""`(future, deadline)` (`runtime.monotonic()` seconds; `None`: no bound): a plain tuple, as
every blocking call's steps yield one.
"""


def left(deadline: float | None) -> float | None:
    """Seconds left until `deadline` (never negative), `None` without one."""
    return None if deadline is None else max(0.0, deadline - runtime.monotonic())


Steps: TypeAlias = Generator[Wait, bool, T]
"""A protocol's steps: yields `Wait`s, is sent whether each settled in time, returns the result."""


_LET_GO: contextvars.ContextVar[Callable[[], None] | None] = contextvars.ContextVar(
    "rr_actors_let_go", default=None
)


def when_waiting(hook: Callable[[], None] | None) -> contextvars.Token[Callable[[], None] | None]:
    """In the current context, `let_go` runs `hook()` (any thread, maybe often) until
    `waited(token)`: a status callback that waits for a registrar lets its id's next start."""
    return _LET_GO.set(hook)


def waited(token: contextvars.Token[Callable[[], None] | None]) -> None:
    """Take back what `when_waiting` set (on the thread, in the context, that set it)."""
    _LET_GO.reset(token)


def let_go() -> None:
    """The current context is about to wait for a registrar: run its `when_waiting` hook."""
    hook = _LET_GO.get()
    if hook is not None:
        hook()


def run_steps(steps: Steps[T]) -> T:
    """Run `steps` on the calling thread, blocking on each future (after `let_go`); an exception
    while they wait is thrown into them at the `yield`."""
    resume: Callable[[Any], Wait] = steps.send
    given: Any = None  # (sent to start them)
    while True:
        try:
            future, deadline = resume(given)
            let_go()
            resume, given = steps.send, future.wait(left(deadline))
        except StopIteration as done:
            result: T = done.value
            return result
        except BaseException as exc:
            if inspect.getgeneratorstate(steps) != inspect.GEN_SUSPENDED:
                raise  # (the steps raised it: they are done)
            resume, given = steps.throw, exc


def on_own_thread(fn: Callable[[], T], name: str) -> Steps[T]:
    """Steps that run `fn()` on a fresh daemon thread and wait for its result: for the few
    operations that block outside steps (on a loop they hold that thread, never the loop)."""
    done: FutureReply = FutureReply()

    def run() -> None:
        try:
            result = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the steps
            done.set_error(exc)
        else:
            done.set_result(result)

    runtime.Thread(target=run, name=name, daemon=True).start()
    yield done.future, None
    result: T = done.future.get(timeout=0)
    return result


def asked(future: OneShotFuture[Any], deadline: float, limit: float, what: str) -> Steps[Any]:
    """Steps of one request: `future`'s value or error by `deadline`, else `CallTimeoutError`
    (`limit` seconds, `what` for the message)."""
    if not (yield future, deadline):
        raise CallTimeoutError(f"{what} timed out after {limit:g} s")
    return future.get(timeout=0)


@dataclasses.dataclass(frozen=True)
class Answer:
    """The answer to an actor's own ask, delivered to its mailbox."""

    token: int
    value: Any
    error: BaseException | None


class TokenReply:
    """Answers by telling an actor `(token, value, error)`; used for an actor's own asks."""

    __slots__ = ("ref", "token")

    def __init__(self, ref: pykka.ActorRef[Any], token: int) -> None:
        self.ref = ref
        self.token = token

    def set_result(self, value: Any) -> None:
        self._tell(value, None)

    def set_error(self, error: BaseException) -> None:
        self._tell(None, error)

    def _tell(self, value: Any, error: BaseException | None) -> None:
        try:
            self.ref.tell(Answer(self.token, value, error))
        except pykka.ActorDeadError:
            logger.debug("answer %s dropped: the registrar is gone", self.token)


Continuation = Callable[[Any, BaseException | None], None]


class CallbackReply:
    """Answers by calling `then(value, error)` on the answering thread, at most once: it must be
    quick and thread-safe; what it raises is logged."""

    __slots__ = ("_lock", "_then")

    def __init__(self, then: Continuation) -> None:
        self._then: Continuation | None = then
        self._lock = runtime.Lock()

    def set_result(self, value: Any) -> None:
        self._run(value, None)

    def set_error(self, error: BaseException) -> None:
        self._run(None, error)

    def _run(self, value: Any, error: BaseException | None) -> None:
        with self._lock:
            then, self._then = self._then, None
        if then is None:
            return  # answered already (the first answer wins)
        try:
            then(value, error)
        except Exception:
            logger.exception("a reply's continuation raised")


class Tokens:
    """The continuations an actor waits on, keyed by token (used in the actor thread only)."""

    def __init__(self) -> None:
        self._next = itertools.count()
        self._waiting: dict[int, Continuation] = {}

    def reply(self, ref: pykka.ActorRef[Any], then: Continuation) -> TokenReply:
        token = next(self._next)
        self._waiting[token] = then
        return TokenReply(ref, token)

    def answer(self, token: int, value: Any, error: BaseException | None) -> None:
        then = self._waiting.pop(token, None)
        if then is not None:
            then(value, error)


class Join:
    """Run `then()` once every part `add()`ed is `done()` and `seal()` was called (actor thread)."""

    __slots__ = ("_open", "_sealed", "_then")

    def __init__(self, then: Callable[[], None]) -> None:
        self._then = then
        self._open = 0
        self._sealed = False

    def add(self) -> Callable[..., None]:
        self._update(1, seal=False)
        return self.done

    def done(self, *_: Any) -> None:
        self._update(-1, seal=False)

    def seal(self) -> None:
        self._update(0, seal=True)

    def _update(self, parts: int, *, seal: bool) -> None:
        if self._count(parts, seal=seal):
            self._then()

    def _count(self, parts: int, *, seal: bool) -> bool:
        self._open += parts
        self._sealed = self._sealed or seal
        if self._sealed and self._open == 0:
            self._sealed = False  # fire once
            return True
        return False


class SharedJoin(Join):
    """`Join` whose parts may report from any thread; `then()` runs once, outside the lock, on
    the thread that completes it."""

    __slots__ = ("_lock",)

    def __init__(self, then: Callable[[], None]) -> None:
        super().__init__(then)
        self._lock = runtime.Lock()

    def _update(self, parts: int, *, seal: bool) -> None:
        with self._lock:
            fire = self._count(parts, seal=seal)
        if fire:
            self._then()
