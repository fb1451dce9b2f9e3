"""One thread per process watches every manager process it started.

```
 ManagerProcess.start ── watch(handle) ──► the watcher thread "rr-watch" (one per process)
                                            a selector: each handle's sentinel, control
                                            pipe and exit watch (`handle.waitables`)
                                            a heap: each handle's `wake_at()` (heartbeat)
          a waitable ready, or a `wake_at` due ──► handle.turn(woke): read its pipe, judge
                                                   its silence, Ping / Probe / kill
          turn says it ended ──► handle.finish(exitcode) on a thread "rr-exit-<name>"
                                 (on_exit ─► the supervisor's mailbox)
```

What a turn does is the handle's (`ManagerProcess.turn`, `heartbeat.Heartbeat`); only who
waits is here. A thread per manager held the interpreter lock with a thousand of them
(issue 69); one thread and one `epoll` set cost the same for ten managers or a thousand.
A handle whose turn raises is logged, killed and reported failed (`watch_failed`); the
others' watch goes on. The end of a manager runs on a thread of its own: reaping it may
wait for the forkserver, and its exit handler is not to hold up the others' heartbeats.
The thread ends when it watches nothing (a process that starts no manager has none).
A simulation never comes here: its managers (`rr_actors.simulation`) watch themselves.
"""

from __future__ import annotations

import contextlib
import heapq
import itertools
import logging
import os
import selectors
from typing import Any, Protocol

from rr_actors._core import runtime

__all__ = ["WATCHER", "Watched", "Watcher"]

logger = logging.getLogger("rr_actors")


class Watched(Protocol):
    """What the watcher asks of a handle (`ManagerProcess`); the watcher thread alone calls
    `turn`, `wake_at` and `watch_failed`, a thread of its own `finish`."""

    name: str
    waitables: list[Any]
    """Descriptors (ints or objects with `fileno()`) whose readiness wakes it; `turn` may
    remove some (a pipe at its end), never add."""

    def wake_at(self) -> float | None:
        """Monotonic seconds at which to take its turn unwoken (`None`: only when woken)."""
        ...

    def turn(self, woke: list[Any]) -> tuple[bool, int | None]:
        """One turn (`woke`: its waitables that are ready, maybe none): whether it ended,
        and its exit code if known."""
        ...

    def watch_failed(self, error: BaseException) -> None:
        """Its turn raised `error`: kill it; from now on `turn` only watches its exit."""
        ...

    def finish(self, exitcode: int | None) -> None:
        """It ended: reap it and report its exit."""
        ...


class _Loop:
    """One run of the watcher thread: its selector, its wake-up pipe, its heap."""

    def __init__(self) -> None:
        self.selector = selectors.DefaultSelector()
        self.wake_r, self.wake_w = os.pipe()
        os.set_blocking(self.wake_r, False)
        os.set_blocking(self.wake_w, False)
        self.selector.register(self.wake_r, selectors.EVENT_READ, None)
        self.added: list[Watched] = []  # (under the watcher's lock)
        self.watched: dict[Watched, list[Any]] = {}  # handle -> its registered waitables
        self.failed: set[Watched] = set()  # handles whose turn raised once
        self.due: dict[Watched, float] = {}  # handle -> the `wake_at` in the heap for it
        self.heap: list[tuple[float, int, Watched]] = []
        self.order = itertools.count()  # (ties in the heap: no handle is compared)

    def wake(self) -> None:
        with contextlib.suppress(BlockingIOError):  # (full: it wakes all the same)
            os.write(self.wake_w, b"\0")

    def close(self) -> None:
        self.selector.close()
        os.close(self.wake_r)
        os.close(self.wake_w)


class Watcher:
    """Starts the watcher thread when it is given a handle, lets it end with the last."""

    def __init__(self) -> None:
        self._lock = runtime.Lock()
        self._loop: _Loop | None = None
        self._pid = os.getpid()

    def watch(self, handle: Watched) -> None:
        """Watch `handle` from now until it ended (`finish` ran or runs)."""
        with self._lock:
            loop = self._loop
            if loop is None or self._pid != os.getpid():  # (a fork has no thread of ours)
                loop = self._loop = _Loop()
                self._pid = os.getpid()
                runtime.Thread(target=self._run, args=(loop,), name="rr-watch", daemon=True).start()
            loop.added.append(handle)
            loop.wake()

    def _run(self, loop: _Loop) -> None:
        while True:
            with self._lock:
                added, loop.added = loop.added, []
                if not added and not loop.watched:
                    self._loop = None
                    loop.close()
                    return
            for handle in added:
                self._add(loop, handle)
            woke = self._wait(loop)
            for handle, ready in woke.items():
                self._turn(loop, handle, ready)

    def _add(self, loop: _Loop, handle: Watched) -> None:
        registered = loop.watched[handle] = []
        for waitable in handle.waitables:
            try:
                loop.selector.register(waitable, selectors.EVENT_READ, (handle, waitable))
            except (OSError, ValueError) as exc:  # (closed already: it ended)
                logger.debug("manager %s: %r cannot be watched (%s)", handle.name, waitable, exc)
                continue
            registered.append(waitable)
        self._schedule(loop, handle)

    def _wait(self, loop: _Loop) -> dict[Watched, list[Any]]:
        """Wait until a waitable is ready or a `wake_at` is due; which handles take a turn,
        with their ready waitables."""
        heap, due = loop.heap, loop.due
        while heap and due.get(heap[0][2]) != heap[0][0]:
            heapq.heappop(heap)  # (an earlier `wake_at` of a handle, or an ended one)
        timeout = None if not heap else max(0.0, heap[0][0] - runtime.monotonic())
        woke: dict[Watched, list[Any]] = {}
        for key, _ in loop.selector.select(timeout):
            if key.data is None:
                with contextlib.suppress(BlockingIOError):
                    os.read(loop.wake_r, 4096)
                continue
            handle, waitable = key.data
            woke.setdefault(handle, []).append(waitable)
        now = runtime.monotonic()
        while heap and heap[0][0] <= now:
            wake_at, _, handle = heapq.heappop(heap)
            if due.get(handle) == wake_at:
                del due[handle]
                woke.setdefault(handle, [])
        return woke

    def _turn(self, loop: _Loop, handle: Watched, ready: list[Any]) -> None:
        try:
            ended, exitcode = handle.turn(ready)
        except Exception as exc:
            if handle in loop.failed:  # (its exit's watch raised too: it was killed)
                logger.exception("watching manager %s failed again: taken as ended", handle.name)
                ended, exitcode = True, None
            else:
                logger.exception("watching manager %s failed: killing it", handle.name)
                loop.failed.add(handle)
                ended, exitcode = self._failed(handle, exc)
        if ended:
            self._forget(loop, handle)
            runtime.Thread(
                target=_finish, args=(handle, exitcode), name=f"rr-exit-{handle.name}", daemon=True
            ).start()
            return
        registered = loop.watched[handle]
        for waitable in [w for w in registered if w not in handle.waitables]:
            registered.remove(waitable)  # (its pipe's end read)
            with contextlib.suppress(KeyError, OSError, ValueError):
                loop.selector.unregister(waitable)
        self._schedule(loop, handle)

    @staticmethod
    def _failed(handle: Watched, error: BaseException) -> tuple[bool, int | None]:
        try:
            handle.watch_failed(error)
        except Exception:
            logger.exception("killing manager %s failed", handle.name)
            return True, None
        return False, None

    @staticmethod
    def _schedule(loop: _Loop, handle: Watched) -> None:
        wake_at = handle.wake_at()
        if wake_at is None:
            loop.due.pop(handle, None)
        elif loop.due.get(handle) != wake_at:
            loop.due[handle] = wake_at
            heapq.heappush(loop.heap, (wake_at, next(loop.order), handle))

    @staticmethod
    def _forget(loop: _Loop, handle: Watched) -> None:
        for waitable in loop.watched.pop(handle, []):
            with contextlib.suppress(KeyError, OSError, ValueError):
                loop.selector.unregister(waitable)
        loop.due.pop(handle, None)
        loop.failed.discard(handle)


def _finish(handle: Watched, exitcode: int | None) -> None:
    try:
        handle.finish(exitcode)
    except Exception:
        logger.exception("ending manager %s failed", handle.name)


WATCHER = Watcher()
"""This process's watcher (`ManagerProcess.start` hands it each manager)."""
