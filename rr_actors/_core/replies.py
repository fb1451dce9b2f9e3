"""Reply objects: where the answer to a message goes, and how a caller waits for it."""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import logging
import queue
import threading
from collections.abc import Callable
from typing import Any

import pykka

from rr_actors._core.actor import OneShotFuture
from rr_actors.errors import CallTimeoutError

__all__ = [
    "Answer",
    "CallbackReply",
    "FutureReply",
    "Join",
    "SharedJoin",
    "TokenReply",
    "Tokens",
    "wait",
]

logger = logging.getLogger("rr_actors")


class FutureReply:
    """Answers a pykka future; a second answer is ignored (the first one wins)."""

    __slots__ = ("future",)

    def __init__(self, future: OneShotFuture[Any] | None = None) -> None:
        self.future: OneShotFuture[Any] = future or OneShotFuture()

    def set_result(self, value: Any) -> None:
        with contextlib.suppress(queue.Full):
            self.future.set(value)

    def set_error(self, error: BaseException) -> None:
        with contextlib.suppress(queue.Full):
            self.future.set_exception((type(error), error, error.__traceback__))


def wait(future: pykka.Future[Any], timeout: float, what: str) -> Any:
    """Wait for `future` at most `timeout` seconds.

    Raises:
        CallTimeoutError: nothing arrived in time.
        Exception: whatever error the future holds.
    """
    try:
        return future.get(timeout=timeout)
    except pykka.Timeout:
        raise CallTimeoutError(f"{what} timed out after {timeout:g} s") from None


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
    """Answers by calling `then(value, error)` on the answering thread, at most once.

    For continuations that touch no actor state (a status acknowledgement): no trip
    through the asking actor's mailbox. `then` runs on whichever thread answers: a
    connection's reader thread, a callback worker, or another registrar's actor thread;
    so it must be quick and thread-safe. An exception from it is logged, never raised
    into the answering thread.
    """

    __slots__ = ("_lock", "_then")

    def __init__(self, then: Continuation) -> None:
        self._then: Continuation | None = then
        self._lock = threading.Lock()

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
    """Run `then()` once every started part is `done()` (in the actor thread).

    Call `add()` before starting each part and `seal()` after the last one.
    """

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
        """Count `parts` more open parts (or fewer), maybe seal; whether to fire now."""
        self._open += parts
        self._sealed = self._sealed or seal
        if self._sealed and self._open == 0:
            self._sealed = False  # fire once
            return True
        return False


class SharedJoin(Join):
    """`Join` whose parts may report from any thread; `then()` runs once, on the thread
    that completes the join (the last part's, or `seal()`'s), outside its lock.

    `add()` and `seal()` are called by the thread that starts the parts.
    """

    __slots__ = ("_lock",)

    def __init__(self, then: Callable[[], None]) -> None:
        super().__init__(then)
        self._lock = threading.Lock()

    def _update(self, parts: int, *, seal: bool) -> None:
        with self._lock:
            fire = self._count(parts, seal=seal)
        if fire:
            self._then()
