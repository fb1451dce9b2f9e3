"""Spare manager processes: started ahead of need, so that a restart does not wait for one.

```
 SparePool (root supervisor)                       spare process (child.standby)
   refill() ──► filler thread ── Spare.start() ──►  fork, bootstrap, warm up
                                                    ──► Warm()
   take() ───► the warmest spare ── ManagerProcess.start(spare=...) ──► Start(...)
   close() ──► every idle spare: EOF on its pipe ──► exits
```

A restart hands the manager's arguments to a process that already runs: the process
start (forkserver fork and child bootstrap) and its first-use costs (`_warm_up`) are off
the restart path. The pool keeps `size` spares; a crash that comes right after a restart
then still finds one that has finished warming up (the one started last may not have).
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing.connection
import threading
import time
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any

from rr_actors._platform import PLATFORM, forkserver
from rr_actors._platform.base import ExitWatch
from rr_actors._process.child import standby
from rr_actors._process.control import PROCESS_PREFIX, Start, Warm, WarmUp, forker_pid, mp_context
from rr_actors._transport.messenger import Address
from rr_actors.config import RegistrarConfig

__all__ = ["Spare", "SparePool"]

logger = logging.getLogger("rr_actors")

FORK_TIMEOUT = 5.0
"""Seconds a spare's fork may take (a stopped forkserver): the filler thread gives up
then, so that `SparePool.close` does not wait for it longer."""

REAP_GRACE = 0.5
"""Seconds `Spare.close` waits for the forkserver to reap a spare that has exited."""


class Spare:
    """A manager process started ahead of need, idle until it is given a manager to run.

    A spare that is never used exits when [`close`][rr_actors._process.spare.Spare.close]d
    (or when its parent dies, like any manager process).
    """

    def __init__(self, process: BaseProcess, conn: Connection, *, lean: bool = False) -> None:
        self.process = process
        self.conn = conn
        self.warm = False
        self.lean = lean  # not warming up until told (`warm_up`)

    @classmethod
    def start(cls, *, lean: bool = False) -> Spare:
        """Start a spare process (returns once it was forked; it idles on its pipe).

        Args:
            lean: it warms up only when told (`warm_up`), not at once.

        Raises:
            TimeoutError: it was not forked within `FORK_TIMEOUT` seconds.
        """
        ctx = mp_context()
        parent_conn, child_conn = ctx.Pipe(duplex=True)
        process = ctx.Process(  # type: ignore[attr-defined]
            target=standby,
            args=(child_conn, forker_pid(ctx), not lean),
            name=f"{PROCESS_PREFIX}spare",
            daemon=True,
        )
        try:
            forkserver.start_within(process, FORK_TIMEOUT)
        except BaseException:
            parent_conn.close()
            raise
        finally:
            child_conn.close()
        return cls(process, parent_conn, lean=lean)

    def warm_up(self) -> None:
        """Have a lean spare warm up now (nothing for one that warmed up at its start)."""
        if self.lean:
            self.lean = False
            with contextlib.suppress(OSError, ValueError):
                self.conn.send(WarmUp())

    def check_warm(self) -> bool:
        """Whether it has finished warming up (reads its `Warm()` without blocking)."""
        if not self.warm:
            with contextlib.suppress(OSError, EOFError):
                if self.conn.poll(0):
                    self.warm = isinstance(self.conn.recv(), Warm)
        return self.warm

    def take(
        self,
        name: str,
        setup: bytes,
        config: RegistrarConfig,
        address: Address | None,
        *,
        forward: bool = False,
        tally: str | None = None,
    ) -> bool:
        """Hand manager `name`'s arguments to the spare; `False` if it is not usable."""
        if not self.process.is_alive():
            self.close()
            return False
        try:
            self.conn.send(Start(setup, config, address, forward, tally))
        except (OSError, ValueError):
            self.close()
            return False
        self.process.name = f"{PROCESS_PREFIX}{name}"
        return True

    def close(self, timeout: float = 5.0) -> None:
        """Release an unused spare: it sees EOF and exits; killed after `timeout` seconds.

        Its exit is seen by the platform's exit watch where there is one (a pidfd), not
        only by the process sentinel, which waits for the forkserver to reap it: a
        stopped forkserver (a hang) then holds each spare's close `REAP_GRACE` seconds,
        not twice `timeout`.
        """
        with contextlib.suppress(OSError):
            self.conn.close()
        pid = self.process.pid
        watch = None if pid is None else PLATFORM.watch_exit(pid)
        try:
            if not _exited(self.process, watch, timeout):
                with contextlib.suppress(OSError, ValueError):
                    self.process.kill()
                _exited(self.process, watch, timeout)
        finally:
            if watch is not None:
                watch.close()
        with contextlib.suppress(OSError, ValueError):  # its sentinel pipe, once reaped
            self.process.close()


def _exited(process: BaseProcess, watch: ExitWatch | None, timeout: float) -> bool:
    """Wait up to `timeout` seconds for `process` to exit, then up to `REAP_GRACE` more
    for the forkserver to reap it; whether it exited."""
    waitables: list[Any] = [process.sentinel] if watch is None else [process.sentinel, watch]
    if not multiprocessing.connection.wait(waitables, timeout):
        return False
    process.join(REAP_GRACE)
    return True


class SparePool:
    """Up to `size` idle spare processes, started by a thread of its own.

    [`take`][rr_actors._process.spare.SparePool.take] may be called from any thread;
    [`refill`][rr_actors._process.spare.SparePool.refill] asks the filler thread to top the
    pool up once no refill was asked for `delay` seconds. The supervisor calls it once a
    start was published: a new spare's fork and warm-up then compete neither with the
    restart they follow nor with a crash that comes right after it (the other spare
    serves that one).

    Args:
        size: how many spares to keep (0: none, `take` always returns `None`).
        name: for the filler thread's name and log lines.
        delay: seconds from a `refill` to the start of the next spare.
    """

    def __init__(self, size: int, name: str, *, delay: float = 0.0) -> None:
        self.size = size
        self.name = name
        self.delay = delay
        self._cond = threading.Condition()
        self._idle: list[Spare] = []  # oldest first
        self._due: float | None = None  # when the filler starts spares (monotonic)
        self._ahead: int | None = None  # manager starts in order to come (`ahead`), or None
        self._taken = 0  # spares asked for (by `take`) since `ahead`
        self._closed = False
        self._thread: threading.Thread | None = None

    def take(self) -> Spare | None:
        """The warmest idle spare (the oldest that has warmed up), if there is one."""
        with self._cond:
            self._taken += 1  # (while ahead: one more start under way)
            if self._ahead is not None:
                self._due = time.monotonic()  # fork the next one's process now
                self._cond.notify_all()
            if not self._idle:
                return None
            spare = next((s for s in self._idle if s.check_warm()), self._idle[0])
            self._idle.remove(spare)
            return spare

    def ahead(self, starts: int) -> None:
        """Fork the processes of `starts` manager starts in order ahead of their turn.

        For the start of a tree (`Supervisor.start`): while a manager starts, the filler
        forks spares for the ones after it (up to `size`, no delay, and without their
        warm-up, which would compete with the starts): the next start then only waits
        for the manager's own start (restore, setup, serve), not also for a process.
        Each `take` counts one start. `ahead(0)` ends it: the spares left warm up
        now, and refills wait `delay` seconds as before.
        """
        with self._cond:
            self._ahead = starts or None
            self._taken = 0
            if not starts:
                # Forked ahead: warm up now, for a restart. Under the lock, so that a spare
                # `take` hands out gets its `Start` after its `WarmUp`, never at the same
                # time from another thread (a pipe's `send` is not thread-safe).
                for spare in self._idle:
                    spare.warm_up()
        if starts:
            self._refill_at(time.monotonic())

    def refill(self) -> None:
        """Have the filler thread start spares until there are `size`, `delay` s from now.

        Returns at once. Each call postpones a refill that is not under way yet: while
        (re)starts follow each other closely (a crash loop), no spare's warm-up competes
        with them; the pool is topped up once they have been quiet for `delay` seconds.
        """
        self._refill_at(time.monotonic() + self.delay)

    def _refill_at(self, due: float) -> None:
        with self._cond:
            if self._closed or self.size == 0:
                return
            self._due = due
            if self._thread is None:
                self._thread = threading.Thread(
                    target=self._fill, name=f"rr-spares-{self.name}", daemon=True
                )
                self._thread.start()
            self._cond.notify_all()

    def close(self, timeout: float = 10.0) -> None:
        """Stop refilling and release every idle spare (each sees EOF and exits)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
            thread = self._thread
        if thread is not None:
            thread.join(timeout)
        with self._cond:
            idle, self._idle = self._idle, []
        for spare in idle:
            spare.close()

    def _wanted(self) -> int:
        """Spares to keep: `size`; while ahead, no more than the starts after the current."""
        if self._ahead is None:
            return self.size
        return min(self.size, max(0, self._ahead - max(self._taken, 1)))

    def _fill(self) -> None:
        """The filler thread: when a refill is due, start spares until there are `size`."""
        while True:
            with self._cond:
                while not self._closed and (self._due is None or self._due > time.monotonic()):
                    self._cond.wait(None if self._due is None else self._due - time.monotonic())
                if self._closed:
                    return
                if len(self._idle) >= self._wanted():
                    self._due = None
                    continue
            try:
                spare = Spare.start(lean=self._ahead is not None)
            except Exception:
                logger.exception("%s: could not start a spare manager process", self.name)
                with self._cond:
                    self._due = None
                continue
            with self._cond:
                if self._closed:
                    closing: Spare | None = spare
                else:
                    self._idle.append(spare)
                    closing = None
                    if self._ahead is None:
                        spare.warm_up()  # (its start ran across the end of the ahead)
            if closing is not None:  # closed meanwhile
                closing.close()
                return
