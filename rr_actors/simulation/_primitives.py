"""The stdlib's threads, locks, events, conditions and queues, on the scheduler.

Each behaves as its `threading` (or `queue`) namesake, for the methods the protocol code
uses, with plain fields (one task runs at a time). What would block a real thread
suspends the task instead:

```
 Lock.acquire (taken) ─┐                         ┌─ Lock.release ─ wake the first waiter
 Event.wait (clear) ───┤                         ├─ Event.set ──── wake every waiter
 Condition.wait ───────┼─► Scheduler.block ◄─────┼─ Condition.notify(n)
 SimpleQueue.get ──────┤   (until woken, or its  ├─ SimpleQueue.put ─ wake the first
 Thread.join ──────────┤    deadline, virtual)   ├─ the thread ended
 sleep ────────────────┘                         └─ (nothing: its deadline)
```

A woken task takes the lock (or item) only if still free when it runs (as a barging real
thread could take it first). Every non-blocking operation is a choice point.
"""

from __future__ import annotations

import collections
import itertools
import os
import queue
import sys
from collections.abc import Callable
from types import TracebackType
from typing import Any

from rr_actors.simulation._processes import Process
from rr_actors.simulation._scheduler import Scheduler, Task, short_path

__all__ = [
    "Condition",
    "Event",
    "Lock",
    "RLock",
    "SimpleQueue",
    "Thread",
    "Timer",
    "current_thread",
    "get_ident",
    "queue_class",
    "sleep",
]


def _made_at() -> tuple[str, int]:
    """Where the object being made was made (its maker's caller): file and line, for
    reports (`_where`: made into text only then, not for each of the run's objects)."""
    frame = sys._getframe(2)
    while frame.f_back is not None and frame.f_code.co_filename.startswith(_SIMULATION):
        frame = frame.f_back  # (the seam's wrapper, a primitive made by another)
    return frame.f_code.co_filename, frame.f_lineno


_SIMULATION = os.path.dirname(os.path.abspath(__file__)) + os.sep
"""This package's folder: a birthplace is the first frame outside it."""


def _where(made: tuple[str, int]) -> str:
    return f"{short_path(made[0])}:{made[1]}"


def _deadline(sched: Scheduler, timeout: float | None) -> float | None:
    return None if timeout is None or timeout < 0 else sched.now + timeout


class Lock:
    """`threading.Lock`: any task may release it."""

    __slots__ = ("_holder", "_locked", "_made", "_sched", "_waiters", "maker")

    def __init__(self, sched: Scheduler) -> None:
        self._sched = sched
        maker = sched.running
        self.maker = None if maker is None else maker.process  # (`Scheduler.end`)
        self._locked = False
        self._holder: Task | None = None  # who holds it (for reports; `let_go`)
        self._waiters: collections.deque[Task] = collections.deque()
        self._made = _made_at()

    def describe(self) -> str:
        holder = "" if self._holder is None else f", taken by {self._holder!r}"
        return f"made at {_where(self._made)}{holder}"

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        sched = self._sched
        sched.gap -= 1  # (`Scheduler.pause`, inline: the commonest operation of a run)
        if sched.gap < 0:
            sched.yield_now()
        if self._locked:
            if not blocking:
                return False
            if not self._wait(sched, _deadline(sched, timeout)):
                return False
        self._locked = True
        holder = self._holder = sched.running
        if holder is not None:
            holder.held.append(self)
        return True

    def _wait(self, sched: Scheduler, deadline: float | None) -> bool:
        """Wait until it is free (then the caller takes it); whether it is."""
        task = sched.current()
        while self._locked:
            self._waiters.append(task)
            if not sched.block((self, "acquire"), deadline):
                if task in self._waiters:
                    self._waiters.remove(task)
                if self._locked:
                    return False
        return True

    def release(self) -> None:
        if not self._locked:
            raise RuntimeError("release unlocked lock")
        self._free()
        sched = self._sched
        sched.gap -= 1  # (`Scheduler.pause`, inline)
        if sched.gap < 0:
            sched.yield_now()

    def _free(self) -> None:
        self._locked = False
        holder, self._holder = self._holder, None
        if holder is not None:
            held = holder.held
            if held and held[-1] is self:  # (most: the last one taken)
                held.pop()
            elif self in held:
                held.remove(self)
        waiters = self._waiters
        while waiters:
            task = waiters.popleft()
            if not task.killed:
                self._sched.wake(task)
                break

    def let_go(self) -> None:
        """Its holder's process ended (`Scheduler.end`): free it, as if released."""
        if self._locked:
            self._free()

    def locked(self) -> bool:
        return self._locked

    __enter__ = acquire

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if not self._locked:  # (`release`, inline: `RLock` has its own `__exit__`)
            raise RuntimeError("release unlocked lock")
        self._free()
        sched = self._sched
        sched.gap -= 1
        if sched.gap < 0:
            sched.yield_now()

    # (what `Condition` needs of its lock)
    def _release_save(self) -> int:
        self.release()
        return 1

    def _acquire_restore(self, _count: int) -> None:
        self.acquire()

    def _is_owned(self) -> bool:
        return self._locked


class RLock(Lock):
    """`threading.RLock`: taken again by its owner, released by its owner only."""

    __slots__ = ("_count",)

    def __init__(self, sched: Scheduler) -> None:
        super().__init__(sched)
        self._count = 0

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        sched = self._sched
        me = sched.running
        if self._locked and self._holder is me:
            self._count += 1
            return True
        if not super().acquire(blocking, timeout):
            return False
        self._count = 1
        return True

    __enter__ = acquire

    def release(self) -> None:
        if not self._locked or self._holder is not self._sched.running:
            raise RuntimeError("cannot release un-acquired lock")
        self._count -= 1
        if not self._count:
            super().release()

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.release()

    def let_go(self) -> None:
        self._count = 0
        super().let_go()

    def _release_save(self) -> int:
        count, self._count = self._count, 1
        self.release()
        return count

    def _acquire_restore(self, count: int) -> None:
        self.acquire()
        self._count = count

    def _is_owned(self) -> bool:
        return self._locked and self._holder is self._sched.running


class Condition:
    """`threading.Condition` over a simulated `Lock` or `RLock` (a new `RLock` if none)."""

    __slots__ = ("_lock", "_made", "_sched", "_waiters", "acquire", "release")

    def __init__(self, sched: Scheduler, lock: Lock | None = None) -> None:
        self._sched = sched
        self._lock = RLock(sched) if lock is None else lock
        self.acquire = self._lock.acquire
        self.release = self._lock.release
        self._waiters: collections.deque[list[Any]] = collections.deque()  # [task, notified]
        self._made = _made_at()

    def describe(self) -> str:
        return f"made at {_where(self._made)}"

    def __enter__(self) -> bool:
        return self._lock.acquire()

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._lock.release()

    def wait(self, timeout: float | None = None) -> bool:
        if not self._lock._is_owned():
            raise RuntimeError("cannot wait on un-acquired lock")
        sched = self._sched
        waiter: list[Any] = [sched.current(), False]
        self._waiters.append(waiter)
        saved = self._lock._release_save()  # (a choice point: a notify may come first)
        try:
            if not waiter[1]:
                sched.block((self, "wait"), _deadline(sched, timeout))
        finally:
            if not waiter[1]:
                self._waiters.remove(waiter)
            self._lock._acquire_restore(saved)
        notified: bool = waiter[1]
        return notified

    def wait_for(self, predicate: Callable[[], Any], timeout: float | None = None) -> Any:
        endtime = None
        waittime = timeout
        result = predicate()
        while not result:
            if waittime is not None:
                if endtime is None:
                    endtime = self._sched.now + waittime
                else:
                    waittime = endtime - self._sched.now
                    if waittime <= 0:
                        break
            self.wait(waittime)
            result = predicate()
        return result

    def notify(self, n: int = 1) -> None:
        if not self._lock._is_owned():
            raise RuntimeError("cannot notify on un-acquired lock")
        waiters = self._waiters
        while waiters and n > 0:
            waiter = waiters.popleft()
            if waiter[0].killed:
                continue
            waiter[1] = True
            self._sched.wake(waiter[0])
            n -= 1
        sched = self._sched
        sched.gap -= 1  # (`Scheduler.pause`, inline)
        if sched.gap < 0:
            sched.yield_now()

    def notify_all(self) -> None:
        self.notify(len(self._waiters))


class Event:
    """`threading.Event`."""

    __slots__ = ("_flag", "_made", "_sched", "_waiters")

    def __init__(self, sched: Scheduler) -> None:
        self._sched = sched
        self._flag = False
        self._waiters: list[Task] = []
        self._made = _made_at()

    def describe(self) -> str:
        return f"made at {_where(self._made)}"

    def is_set(self) -> bool:
        sched = self._sched
        sched.gap -= 1  # (`Scheduler.pause`, inline)
        if sched.gap < 0:
            sched.yield_now()
        return self._flag

    def set(self) -> None:
        self._flag = True
        waiters, self._waiters = self._waiters, []
        for task in waiters:
            self._sched.wake(task)
        sched = self._sched
        sched.gap -= 1  # (`Scheduler.pause`, inline)
        if sched.gap < 0:
            sched.yield_now()

    def clear(self) -> None:
        self._flag = False

    def wait(self, timeout: float | None = None) -> bool:
        sched = self._sched
        sched.gap -= 1  # (`Scheduler.pause`, inline)
        if sched.gap < 0:
            sched.yield_now()
        if self._flag:
            return True
        task = sched.current()
        self._waiters.append(task)
        if not sched.block((self, "wait"), _deadline(sched, timeout)) and task in self._waiters:
            self._waiters.remove(task)
        return self._flag


class SimpleQueue:
    """`queue.SimpleQueue`: unbounded, FIFO; `get` waits for an item."""

    __slots__ = ("_items", "_made", "_sched", "_waiters")

    def __init__(self, sched: Scheduler) -> None:
        self._sched = sched
        self._items: collections.deque[Any] = collections.deque()
        self._waiters: collections.deque[Task] = collections.deque()
        self._made = _made_at()

    def describe(self) -> str:
        return f"made at {_where(self._made)}"

    def put(self, item: Any, block: bool = True, timeout: float | None = None) -> None:
        self._items.append(item)
        waiters = self._waiters
        while waiters:
            task = waiters.popleft()
            if not task.killed:
                self._sched.wake(task)
                break
        sched = self._sched
        sched.gap -= 1  # (`Scheduler.pause`, inline)
        if sched.gap < 0:
            sched.yield_now()

    def put_nowait(self, item: Any) -> None:
        self.put(item)

    def get(self, block: bool = True, timeout: float | None = None) -> Any:
        sched = self._sched
        sched.gap -= 1  # (`Scheduler.pause`, inline)
        if sched.gap < 0:
            sched.yield_now()
        items = self._items
        if not items:
            if not block:
                raise queue.Empty
            deadline = _deadline(sched, timeout)
            task = sched.current()
            while not items:
                self._waiters.append(task)
                if not sched.block((self, "get"), deadline):
                    if task in self._waiters:
                        self._waiters.remove(task)
                    if not items:
                        raise queue.Empty
        return items.popleft()

    def get_nowait(self) -> Any:
        return self.get(False)

    def empty(self) -> bool:
        sched = self._sched
        sched.gap -= 1  # (`Scheduler.pause`, inline)
        if sched.gap < 0:
            sched.yield_now()
        return not self._items

    def qsize(self) -> int:
        return len(self._items)


def queue_class(sched: Scheduler, made: dict[type, type], cls: type) -> type:
    """`runtime.queue_class` in a simulation: a subclass of `cls` whose raw queue operations are a
    simulated `SimpleQueue`'s, bound per instance (no extra call); made once per class."""
    if cls in made:
        return made[cls]
    raw = {name: name for name in ("get", "get_nowait", "empty", "qsize")}  # (its, the queue's)
    raw["_put"] = "put"  # (what `LateQueue.put` calls)
    if not any("put" in vars(kind) for kind in cls.__mro__ if kind is not queue.SimpleQueue):
        raw["put"] = raw["put_nowait"] = "put"

    def init(self: Any, *args: Any, **kwargs: Any) -> None:
        simulated = SimpleQueue(sched)
        for name, operation in raw.items():
            setattr(self, name, getattr(simulated, operation))
        super(sub, self).__init__(*args, **kwargs)

    sub: type[Any] = type(cls.__name__, (cls,), {"__init__": init})
    made[cls] = sub
    return sub


_thread_numbers = itertools.count(1)


class Thread:
    """`threading.Thread`: runs `target(*args, **kwargs)` (or `run()`) as a task."""

    def __init__(
        self,
        sched: Scheduler,
        group: None = None,
        target: Callable[..., object] | None = None,
        name: str | None = None,
        args: tuple[Any, ...] = (),
        kwargs: dict[str, Any] | None = None,
        *,
        daemon: bool | None = None,
        process: Process | None = None,
    ) -> None:
        self._sched = sched
        self._process = process  # (`None`: the starting task's)
        self._target = target
        self._args = args
        self._kwargs = kwargs or {}
        self.name = name or f"Thread-{next(_thread_numbers)}"
        if daemon is None:
            current = sched.current_or_none()
            daemon = current is not None and current.daemon
        self.daemon = daemon
        self._task: Task | None = None
        self._joiners: list[Task] = []

    def __repr__(self) -> str:
        return f"<simulated Thread {self.name!r}>"

    def describe(self) -> str:
        return repr(self.name)

    def start(self) -> None:
        if self._task is not None:
            raise RuntimeError("threads can only be started once")
        self._task = self._sched.spawn(self._bootstrap, self.name, self.daemon, self, self._process)
        sched = self._sched
        sched.gap -= 1  # (`Scheduler.pause`, inline)
        if sched.gap < 0:
            sched.yield_now()

    def _bootstrap(self) -> None:
        try:
            self.run()
        finally:
            joiners, self._joiners = self._joiners, []
            for task in joiners:
                self._sched.wake(task)

    def run(self) -> None:
        if self._target is not None:
            self._target(*self._args, **self._kwargs)

    @property
    def ident(self) -> int | None:
        return None if self._task is None else self._task.number

    native_id = ident

    def is_alive(self) -> bool:
        return self._task is not None and not self._task.ended

    def join(self, timeout: float | None = None) -> None:
        if self._task is None:
            raise RuntimeError("cannot join thread before it is started")
        sched = self._sched
        task = sched.current()
        if task is self._task:
            raise RuntimeError("cannot join current thread")
        deadline = _deadline(sched, timeout)
        while not self._task.ended:
            self._joiners.append(task)
            if not sched.block((self, "join"), deadline):
                if task in self._joiners:
                    self._joiners.remove(task)
                return


class Timer(Thread):
    """`threading.Timer`: `function(*args, **kwargs)` after `interval` seconds, unless
    cancelled first."""

    def __init__(
        self,
        sched: Scheduler,
        interval: float,
        function: Callable[..., object],
        args: tuple[Any, ...] | None = None,
        kwargs: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(sched, name=f"Timer-{next(_thread_numbers)}")
        self.interval = interval
        self.function = function
        self.timer_args = args or ()
        self.timer_kwargs = kwargs or {}
        self.finished = Event(sched)

    def cancel(self) -> None:
        self.finished.set()

    def run(self) -> None:
        self.finished.wait(self.interval)
        if not self.finished._flag:
            self.function(*self.timer_args, **self.timer_kwargs)
        self.finished.set()


def current_thread(sched: Scheduler) -> Any:
    """`threading.current_thread()`: the simulated thread the caller runs on."""
    return sched.current().thread


def get_ident(sched: Scheduler) -> int:
    """`threading.get_ident()`: the number of the simulated thread the caller runs on."""
    return sched.current().number


def sleep(sched: Scheduler, seconds: float) -> None:
    """`time.sleep(seconds)` in virtual time (0: a choice point that always yields)."""
    sched.block((sched, "sleep"), sched.now + max(0.0, seconds))
