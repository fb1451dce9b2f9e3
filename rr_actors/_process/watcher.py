"""One thread, "rr-watch", waits for every manager process of this process (issue 69: a
thread each held the interpreter lock with a thousand of them), in one epoll set of their
`waitables` (sentinel, control pipe, exit watch) and a heap of their `wake_at()`s; in
each round every one ready and up to `ROUND` due take their `turn` (manager.py: read the
pipe, judge the silence): behind its pings, it still sees an exit within a round. An ended
one's `finish` runs on a thread of its own: reaping may wait for the forkserver. A turn
that raises is logged and its manager killed (`watch_failed`); the others' watch goes on.
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

logger = logging.getLogger("rr_actors")


class Watched(Protocol):
    """A manager process's handle (`ManagerProcess`), as the watcher takes its turns."""

    name: str
    waitables: list[Any]

    def wake_at(self) -> float | None: ...
    def turn(self, woke: list[Any]) -> tuple[bool, int | None]: ...
    def watch_failed(self, error: BaseException) -> None: ...
    def finish(self, exitcode: int | None) -> None: ...


class Watcher:
    """Starts the thread with a first manager; it ends when it watches none."""

    def __init__(self) -> None:
        self._lock = runtime.Lock()
        self._added: list[Watched] | None = None  # (`None`: no thread runs)
        self._nudged: list[Watched] = []  # watched ones whose turn is due now (`nudge`)
        self._wake = (-1, -1)  # the thread's wake-up pipe
        self._watched: dict[Watched, list[Any]] = {}  # handle -> what is registered
        self._due: dict[Watched, float] = {}  # handle -> its `wake_at` in the heap
        self._heap: list[tuple[float, int, Watched]] = []
        self._order = itertools.count()  # (heap ties: no handle is compared)
        self._selector: selectors.BaseSelector  # (made with the thread)

    def watch(self, handle: Watched) -> None:
        with self._lock:
            if self._added is None:
                self._added, self._wake = [], os.pipe()
                os.set_blocking(self._wake[1], False)
                self._selector = selectors.DefaultSelector()
                self._selector.register(self._wake[0], selectors.EVENT_READ, None)
                runtime.Thread(target=self._run, name="rr-watch", daemon=True).start()
            self._added.append(handle)
            with contextlib.suppress(BlockingIOError):  # (full: it wakes all the same)
                os.write(self._wake[1], b"\0")

    def nudge(self, handle: Watched) -> None:
        """Have `handle` take a turn now (its `wake_at` changed); nothing once it ended."""
        with self._lock:
            if self._added is None:
                return  # (no thread: it watches none)
            self._nudged.append(handle)
            with contextlib.suppress(BlockingIOError):
                os.write(self._wake[1], b"\0")

    def _run(self) -> None:
        while True:
            with self._lock:
                added, self._added = self._added or [], []
                nudged, self._nudged = self._nudged, []
                if not added and not self._watched:
                    self._added = None
                    self._selector.close()
                    os.close(self._wake[0])
                    os.close(self._wake[1])
                    return
            for handle in added:
                self._watched[handle] = []
                for waitable in handle.waitables:
                    with contextlib.suppress(OSError, ValueError):  # (closed: it ended)
                        self._selector.register(waitable, selectors.EVENT_READ, handle)
                        self._watched[handle].append(waitable)
            woke: dict[Watched, list[Any]] = {handle: [] for handle in added}
            woke.update((handle, []) for handle in nudged if handle in self._watched)
            for handle, ready in self._wait(woke).items():
                self._turn(handle, ready)

    def _wait(self, woke: dict[Watched, list[Any]]) -> dict[Watched, list[Any]]:
        """Add to `woke` (each an empty list: turns due now) each handle whose waitables
        are ready (with them) or whose `wake_at` is due, once one is."""
        heap, due = self._heap, self._due
        while heap and due.get(heap[0][2]) != heap[0][0]:
            heapq.heappop(heap)  # (an earlier `wake_at` of a handle, or an ended one's)
        timeout = heap[0][0] - runtime.monotonic() if heap and not woke else None
        for key, _ in self._selector.select(0 if woke else timeout):
            if key.data is None:
                os.read(self._wake[0], 4096)
            else:
                woke[key.data] = [*woke.get(key.data, []), key.fileobj]
        now, taken = runtime.monotonic(), 0
        while heap and heap[0][0] <= now and taken < ROUND:  # (the rest: the next round)
            wake_at, _, handle = heapq.heappop(heap)
            if due.get(handle) == wake_at:
                del due[handle]
                taken += handle not in woke
                woke.setdefault(handle, [])
        return woke

    def _turn(self, handle: Watched, ready: list[Any]) -> None:
        try:
            ended, exitcode = handle.turn(ready)
        except Exception as exc:
            logger.exception("watching manager %s failed: killing it", handle.name)
            ended, exitcode = False, None  # (from now on only its sentinel is watched)
            with contextlib.suppress(Exception):  # (logged above)
                handle.watch_failed(exc)
        watched = self._watched[handle]
        for waitable in [w for w in watched if ended or w not in handle.waitables]:
            watched.remove(waitable)  # (its pipe's end was read)
            with contextlib.suppress(KeyError, OSError, ValueError):
                self._selector.unregister(waitable)
        wake_at = None if ended else handle.wake_at()
        if wake_at is None:
            self._due.pop(handle, None)
        elif self._due.get(handle) != wake_at:
            self._due[handle] = wake_at
            heapq.heappush(self._heap, (wake_at, next(self._order), handle))
        if ended:
            del self._watched[handle]
            name = f"rr-exit-{handle.name}"
            runtime.Thread(target=handle.finish, args=(exitcode,), name=name, daemon=True).start()


ROUND = 32  # turns due by the clock taken in a round at most (see the module docstring)
WATCHER = Watcher()
"""This process's watcher (`ManagerProcess.start` hands it each manager)."""
os.register_at_fork(after_in_child=lambda: Watcher.__init__(WATCHER))  # (a child: no thread)
