"""A thread that handles one event at a time: the generic part of a supervisor.

After OTP, where `supervisor` is a callback module on top of `gen_server`'s receive loop:
this is the loop, `rr_actors._supervision.node` the callbacks. Events are posted from
any thread (watcher threads, timers, callers); the handler runs on the mailbox's own
thread, never concurrently with itself, and never polls.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
from collections.abc import Callable
from typing import Any

__all__ = ["Mailbox"]

logger = logging.getLogger("rr_actors")


@dataclasses.dataclass(frozen=True)
class _Do:
    fn: Callable[[], Any]
    done: queue.SimpleQueue[tuple[bool, Any]] | None


@dataclasses.dataclass(frozen=True)
class _Quit:
    pass


class Mailbox:
    """One thread, one queue: `handle(event)` for each posted event, then `after()`.

    Args:
        name: the thread's name.
        handle: called on the mailbox thread with each posted event; an exception it
            raises is logged (it never ends the loop).
        after: called on the mailbox thread after each event and each `call`/`cast`.
    """

    def __init__(
        self, name: str, handle: Callable[[object], None], after: Callable[[], None]
    ) -> None:
        self._queue: queue.SimpleQueue[object] = queue.SimpleQueue()
        self._handle = handle
        self._after = after
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)

    def start(self) -> None:
        """Start the thread."""
        self._thread.start()

    def is_alive(self) -> bool:
        """Whether the thread runs."""
        return self._thread.is_alive()

    def post(self, event: object) -> None:
        """Queue `event` for `handle` (any thread; returns at once)."""
        self._queue.put(event)

    def call(self, fn: Callable[[], Any]) -> Any:
        """Run `fn()` on the mailbox thread and return its result (or raise its exception).

        Never call it from the mailbox thread itself (it would wait for itself).
        """
        done: queue.SimpleQueue[tuple[bool, Any]] = queue.SimpleQueue()
        self._queue.put(_Do(fn, done))
        ok, value = done.get()
        if not ok:
            raise value
        return value

    def cast(self, fn: Callable[[], Any]) -> None:
        """Run `fn()` on the mailbox thread after what is queued now (returns at once)."""
        self._queue.put(_Do(fn, None))

    def quit(self, timeout: float) -> None:
        """End the loop after what is queued now; wait up to `timeout` seconds for it."""
        self._queue.put(_Quit())
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    def _loop(self) -> None:
        while True:
            event = self._queue.get()
            if isinstance(event, _Quit):
                return
            try:
                if isinstance(event, _Do):
                    self._run(event)
                else:
                    self._handle(event)
            except Exception:
                logger.exception("%s failed handling %r", self._thread.name, event)
            self._after()

    @staticmethod
    def _run(event: _Do) -> None:
        try:
            result = (True, event.fn())
        except BaseException as exc:  # handed to the caller, or logged
            if event.done is None:
                logger.exception("a task on a supervisor's thread failed")
                return
            result = (False, exc)
        if event.done is not None:
            event.done.put(result)
