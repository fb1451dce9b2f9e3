"""Tasks run one at a time, in the order submitted, on one thread: `SerialExecutor`.

```
 submit(task) ─► deque ─► its thread (started at the first task) ─► task()
   │  idle?  (nothing queued, nothing running)                        ├─ on_idle() when the
   └─ inline(): on the submitting thread, under the lock; its rest ─► │  deque runs empty
                                                                      └─ on_end() once, last
```

The package's one "queue and a thread" (carriers' writers and decoders, a supervisor's
thread, event subscriptions and forwarders): `ThreadPoolExecutor` with one worker, plus
running inline when idle, a bounded drain, a flush and a tick. A submitter never blocks
on a task; a task that raises is logged and the next one runs.
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Callable
from typing import Any, TypeVar

from rr_actors._core import runtime

logger = logging.getLogger("rr_actors")

T = TypeVar("T")

Task = Callable[[], object]


class _Mark:
    """A place in the queue (`flush`, `call`): set once the thread got there, or dropped."""

    __slots__ = ("fn", "ran", "reached", "result")

    def __init__(self, fn: Callable[[], Any] | None = None) -> None:
        self.fn = fn
        self.reached = runtime.Event()
        self.ran = False
        self.result: tuple[bool, Any] = (True, None)

    def __call__(self) -> None:
        try:
            if self.fn is not None:
                self.result = (True, self.fn())
        except BaseException as exc:  # noqa: BLE001 - handed to the caller of `call`
            self.result = (False, exc)
        finally:
            self.ran = True
            self.reached.set()


def _parked() -> None:
    """`_next`'s answer to a transient executor's thread when its queue ran empty: end."""


_PARKED: Task = _parked


class SerialExecutor:
    """One daemon thread (`name`, started at the first task that waits) running its tasks one at
    a time, in order; what one raises is logged. `linger`: seconds the thread waits once the
    queue ran empty (a burst does not wake it); `every`: `(seconds, task)` also run between
    tasks; `on_idle` when the queue ran empty; `on_drop` with each task `close` drops; `on_end`
    once, last (on its thread if it has one, else the closing thread). `transient`: the thread
    ends once the queue ran empty, and the next task that waits starts another (a connection's
    writer: a thread per blocked burst, none while idle)."""

    def __init__(
        self,
        name: str,
        *,
        linger: float = 0.0,
        every: tuple[float, Task] | None = None,
        on_idle: Task | None = None,
        on_drop: Callable[[Task], object] | None = None,
        on_end: Task | None = None,
        transient: bool = False,
    ) -> None:
        self.name = name
        self._transient = transient and every is None
        self._linger = linger
        self._every = every
        self._on_idle = on_idle
        self._on_drop = on_drop
        self._on_end = on_end
        self._lock = runtime.Lock()
        self._cond = runtime.Condition(self._lock)
        self._tasks: collections.deque[Task] = collections.deque()
        self._busy = False  # a task (or `on_end`) runs
        self._sleeping = False  # the thread waits on `_cond`: a submit must wake it
        self._closing = False  # no more tasks are taken
        self._dropping = False  # `close` dropped what was queued: end after the running one
        self._ended = False  # `on_end` ran (or is running)
        self._hurry = runtime.Event()  # a flush or close is due: linger no longer
        self._thread: runtime.Thread | None = None
        self._due = runtime.monotonic()  # when `every`'s task runs next (at once, first)
        if every is not None:
            self._thread = runtime.Thread(target=self._run, name=name, daemon=True)
            self._thread.start()

    @property
    def closed(self) -> bool:
        """Whether `close` or `finish` was called (the thread may still be finishing)."""
        return self._closing

    @property
    def pending(self) -> int:
        return len(self._tasks)

    def on_own_thread(self) -> bool:
        return self._thread is runtime.current_thread()

    # -- giving it work ----------------------------------------------------------------

    def start(self) -> None:
        """Start the thread now (otherwise the first task that has to wait starts it)."""
        with self._cond:
            if self._thread is None and not self._closing:
                self._start()

    def submit(self, task: Task, *, inline: Callable[[], Task | None] | None = None) -> bool:
        """Run `task` after every task submitted before; `False` if closed. When idle, `inline()`
        runs instead, on this thread under the lock (no blocking, no submit), returning `None` or
        the task to run next; what it raises is raised here, as is `RuntimeError` when no thread
        can be started for it (the task is then not taken)."""
        with self._lock:  # (the plain lock under `_cond`: no Python-level `__enter__`)
            if self._closing:
                return False
            if inline is not None and not self._busy and not self._tasks:
                rest = inline()
                if rest is None:
                    return True
                task = rest
            self._tasks.append(task)
            if self._sleeping:
                self._cond.notify()
            elif self._thread is None and not self._busy:
                try:
                    self._start()
                except RuntimeError:  # no thread (a machine's bound): not taken, said so
                    self._tasks.pop()
                    self._thread = None
                    raise
            return True

    def call(self, fn: Callable[[], T]) -> T:
        """Run `fn()` on the executor's thread after what is queued; its result or error.
        `RuntimeError` on its own thread or once closed."""
        if self.on_own_thread():
            raise RuntimeError(f"call() on {self.name}'s own thread would wait for itself")
        mark = _Mark(fn)
        if not self.submit(mark):
            raise RuntimeError(f"{self.name} is closed")
        mark.reached.wait()
        if not mark.ran:
            raise RuntimeError(f"{self.name} closed before running the call")
        ok, value = mark.result
        if not ok:
            raise value
        result: T = value
        return result

    def flush(self, *, timeout: float | None) -> bool:
        """Block until every task submitted before ran (at most `timeout` s); whether they all did.
        `RuntimeError` on its own thread."""
        if self.on_own_thread():
            raise RuntimeError(f"flush() on {self.name}'s own thread would wait for itself")
        mark = _Mark()
        if not self.submit(mark):
            return self.join(timeout) and not self._dropping
        self._hurry.set()
        return mark.reached.wait(timeout) and mark.ran

    # -- ending it -----------------------------------------------------------------------

    def finish(self) -> None:
        """Take no more tasks; those queued still run, then the thread ends."""
        with self._cond:
            self._closing = True
            self._hurry.set()
            end_here = self._ends_now()
        if end_here:
            self._end()

    def close(self, *, timeout: float | None = 0.0) -> bool:
        """Take no more tasks; let those queued run for `timeout` s, then drop the rest (to
        `on_drop`); whether it ended in time. Idempotent; on its own thread it only finishes."""
        self.finish()
        if timeout != 0:
            if self.on_own_thread():
                return False
            if self.join(timeout):
                return True
        with self._cond:
            self._dropping = True
            dropped = list(self._tasks)
            self._tasks.clear()
            end_here = self._ends_now()
            self._cond.notify_all()
        for task in dropped:
            self._drop(task)
        if end_here:
            self._end()
        return self._ended and not self._busy

    def join(self, timeout: float | None) -> bool:
        if self.on_own_thread():
            return False  # (it cannot end while it runs this)
        deadline = None if timeout is None else runtime.monotonic() + timeout
        with self._cond:
            if not self._cond.wait_for(lambda: self._ended and not self._busy, timeout):
                return False
        if self._thread is not None:  # (its last steps: gone once this returns)
            self._thread.join(
                None if deadline is None else max(0.0, deadline - runtime.monotonic())
            )
            return not self._thread.is_alive()
        return True

    # -- plumbing ------------------------------------------------------------------------

    def _start(self) -> None:  # (hold `_cond`)
        self._thread = runtime.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def _ends_now(self) -> bool:
        """Whether the caller runs `on_end` now (hold `_cond`): closed, idle, no thread."""
        if not self._closing or self._busy or self._ended or self._tasks:
            return False
        if self._thread is not None:
            self._cond.notify_all()
            return False
        self._ended = self._busy = True
        return True

    def _drop(self, task: Task) -> None:
        if isinstance(task, _Mark):
            task.reached.set()  # (not `ran`)
        elif self._on_drop is not None:
            try:
                self._on_drop(task)
            except Exception:
                logger.exception("%s: handling a dropped task failed", self.name)

    def _end(self) -> None:
        try:
            if self._on_end is not None:
                self._on_end()
        except Exception:
            logger.exception("%s: its last step failed", self.name)
        finally:
            with self._cond:
                self._busy = False
                self._cond.notify_all()

    def _next(self) -> Task | None:
        """The next task (hold `_cond`), waiting for one; `None`: the executor ended."""
        while True:
            if self._every is not None and not self._busy and not self._closing:
                period, tick = self._every
                now = runtime.monotonic()
                if now >= self._due:
                    self._due = now + period
                    self._busy = True
                    return tick
            if self._tasks and not self._busy:
                self._busy = True
                return self._tasks.popleft()
            if self._closing and not self._tasks and not self._busy:
                self._ended = self._busy = True
                return None
            if self._transient and not self._busy:  # idle: this thread ends, a submit starts one
                self._thread = None
                return _PARKED
            self._sleeping = True
            try:
                if self._every is None:
                    self._cond.wait()
                else:
                    self._cond.wait(max(0.0, self._due - runtime.monotonic()))
            finally:
                self._sleeping = False

    def _run(self) -> None:
        with self._cond:
            task = self._next()
        while task is not None:
            if task is _PARKED:
                return
            self._run_one(task)
            with self._cond:
                self._busy = False
                idle = not self._tasks and not self._closing
                if idle and self._on_idle is not None:
                    task = self._on_idle
                    self._busy = True
                elif not (idle and self._linger):
                    task = self._next()
                    continue
            if idle and self._on_idle is not None:
                self._run_one(task)
                with self._cond:
                    self._busy = False
            if self._linger and self._hurry.wait(self._linger):
                self._hurry.clear()
            with self._cond:
                task = self._next()
        self._end()

    def _run_one(self, task: Task) -> None:
        try:
            task()
        except BaseException:  # (the thread must outlive any task)
            logger.exception("%s: a task failed", self.name)
