"""Spare manager processes: started ahead of need, so that a restart does not wait for one.

```
 SparePool (root supervisor)                       spare process (child.standby)
   refill() ──► filler thread ── Spare.start() ──►  fork, bootstrap, warm up
                                                    ──► Warm()
   take() ───► the warmest spare ── ManagerProcess.start(spare=...) ──► Start(...)
   close() ──► every idle spare: EOF on its pipe ──► exits
```

A restart hands the manager's arguments to a process that already runs and has paid
its first-use costs (`_warm_up`): those are off the restart path.
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

from rr_actors._platform import PLATFORM
from rr_actors._platform.base import ExitWatch
from rr_actors._process.child import standby
from rr_actors._process.control import PROCESS_PREFIX, Start, Warm, WarmUp, fork
from rr_actors._transport.messenger import Address
from rr_actors.config import RegistrarConfig

logger = logging.getLogger("rr_actors")

FORK_TIMEOUT = 5.0
"""Seconds a spare's fork may take (a stopped forkserver) before the filler gives up."""

REAP_GRACE = 0.5
"""Seconds `Spare.close` waits for the forkserver to reap a spare that has exited."""


class Spare:
    """A manager process started ahead of need, idle until it is given a manager to run."""

    def __init__(self, process: BaseProcess, conn: Connection, *, lean: bool = False) -> None:
        self.process = process
        self.conn = conn
        self.warm = False
        self.lean = lean  # not warming up until told (`warm_up`)

    @classmethod
    def start(cls, *, lean: bool = False) -> Spare:
        """Start a spare process, once forked (`lean`: it warms up only when told;
        `TimeoutError`: not forked within `FORK_TIMEOUT` seconds)."""
        process, parent_conn = fork(
            standby,
            lambda conn, forker: (conn, forker, not lean),
            f"{PROCESS_PREFIX}spare",
            FORK_TIMEOUT,
        )
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
        announced: bool = False,
    ) -> bool:
        """Hand manager `name`'s arguments to the spare; `False` if it is not usable."""
        if not self.process.is_alive():
            self.close()
            return False
        try:
            self.conn.send(Start(setup, config, address, forward, tally, announced))
        except (OSError, ValueError):
            self.close()
            return False
        self.process.name = f"{PROCESS_PREFIX}{name}"
        return True

    def close(self, timeout: float = 5.0) -> None:
        """Release an unused spare: it sees EOF and exits; killed after `timeout` seconds
        (its exit seen by the exit watch too: a stopped forkserver holds it `REAP_GRACE`)."""
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
    """Up to `size` idle spare processes, started by a thread of its own (`delay`: seconds
    from a `refill` to the start of the next spare)."""

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
        """Fork the processes of `starts` manager starts in order ahead of their turn
        (unwarmed; each `take` counts one); `ahead(0)` ends it, the spares left warm up."""
        with self._cond:
            self._ahead = starts or None
            self._taken = 0
            if not starts:
                # under the lock: a taken spare gets its `Start` after its `WarmUp`
                for spare in self._idle:
                    spare.warm_up()
        if starts:
            self._refill_at(time.monotonic())

    def refill(self) -> None:
        """Top the pool up `delay` seconds from now (each call postpones a refill not under
        way: in a crash loop no warm-up competes with the restarts)."""
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
        if self._ahead is None:
            return self.size
        return min(self.size, max(0, self._ahead - max(self._taken, 1)))

    def _fill(self) -> None:
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
