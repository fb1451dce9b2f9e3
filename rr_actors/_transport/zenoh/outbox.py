"""The Zenoh carrier's sending side: one writer thread per destination key.

```
 ZenohMember.send / answer_to ─► Outboxes.get(key) ─► Outbox(key).send(header + frame)
 ZenohMember.send_when_served ─────────────────────► Outbox(key).run(task): in order
                                                          │ its writer thread (SerialExecutor)
                                                          ▼
          (a new outbox's first put: ping rr/<s>/ping/<zid> first; a task asks the
           network for a registrar not seen served, then puts, or fails its reply)
                                                 publisher.put ─► rr/<s>/reg/<name>
                                                                  rr/<s>/ans/<zid>
```

A sender never blocks on a peer and no answer is sent on an actor thread: one writer per
destination (a registrar's key for requests, a process's answer key for answers), so
messages from one process to one registrar keep their order (one writer, one Zenoh route,
one decode thread there). Puts are reliable and block on a full queue
(`CongestionControl.BLOCK`) on the writer thread only; Zenoh closes a link that stays
blocked longer than half the lease.

A process that leaves the system (`Outboxes.close`) first lets every writer put what it
was given, for `DRAIN_TIMEOUT` seconds at most, as a socket's close sends what was
written before it: the last messages of a registrar that stops (the `Abandon` of a call
it withdraws) go out before the session closes. What is still queued then is lost.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import threading
import time
from collections.abc import Callable

import zenoh

from rr_actors._core.serial import SerialExecutor, Task
from rr_actors._transport.messenger import Lost, run_lost
from rr_actors._transport.zenoh.wire import Keys

__all__ = ["DRAIN_TIMEOUT", "HEAL_TIMEOUT", "Outbox", "Outboxes"]

logger = logging.getLogger("rr_actors")

HEAL_TIMEOUT = 2.0
"""Seconds the first message to a process (just seen, or back from a healed link) waits
for its answer to a ping (then it is sent anyway)."""

DRAIN_TIMEOUT = 1.0
"""Seconds a process that leaves the system gives its writers, all together, to put what
they were given before it closes its session."""


class Outbox:
    """The writer of one destination key: its thread puts payloads in the order sent."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        ready: Callable[[], None] | None = None,
        *,
        declared: bool = True,
    ) -> None:
        self.key = key
        self.pinged: str | None = None  # the process a task of `run` pinged (its thread's)
        self._ready = ready  # runs on the writer thread before the first put
        self._session = session
        self._publisher: zenoh.Publisher | None = None
        if declared:
            self.declare()
        name = f"rr-zput-{key.rsplit('/', 1)[-1]}"
        self._queue = SerialExecutor(name, on_drop=self._lost)

    @property
    def closed(self) -> bool:
        return self._queue.closed

    def send(self, data: bytes, on_lost: Lost | None = None) -> bool:
        """Queue `data`; False (nothing sent) if the outbox is closed."""
        return self._queue.submit(functools.partial(self.put, data, on_lost))

    def run(self, task: Callable[[], None]) -> bool:
        """Queue `task` to run on the writer thread, in order with what is sent (it may
        wait there, and `put`); False if the outbox is closed. If the outbox closes
        before it runs, its `dropped()` (if it has one) is called instead."""
        return self._queue.submit(task)

    def declare(self) -> None:
        """Declare the publisher, if not yet (at creation, or on the writer thread)."""
        if self._publisher is None:
            self._publisher = self._session.declare_publisher(
                self.key,
                congestion_control=zenoh.CongestionControl.BLOCK,
                express=True,
                reliability=zenoh.Reliability.RELIABLE,
            )

    def put(self, data: bytes, on_lost: Lost | None = None) -> None:
        """Put `data` now (the writer thread only: `send`'s step, or a task of `run`);
        if the session closed, `on_lost` runs."""
        ready, self._ready = self._ready, None
        if ready is not None:
            ready()
        try:
            self.declare()
            assert self._publisher is not None
            self._publisher.put(data)
        except Exception as exc:  # noqa: BLE001 - the session closed: the frame is lost
            logger.debug("a put on %s failed: %s", self.key, exc)
            if on_lost is not None:
                run_lost([on_lost])

    def close(self, timeout: float = 0.0) -> None:
        """Stop sending: what is queued gets `timeout` seconds to be put (0: none), then
        what is still queued is lost (its `on_lost` runs)."""
        self._queue.close(timeout=timeout)  # (each dropped frame's `on_lost` runs: `_lost`)
        with contextlib.suppress(Exception):
            if self._publisher is not None:
                self._publisher.undeclare()  # type: ignore[no-untyped-call]

    @staticmethod
    def _lost(task: Task) -> None:
        if isinstance(task, functools.partial) and task.args[1] is not None:
            run_lost([task.args[1]])
        dropped = getattr(task, "dropped", None)
        if dropped is not None:
            run_lost([dropped])


class Outboxes:
    """The outboxes of one process's session, by destination key.

    Args:
        session: the open session.
        keys: the system's key expressions (a ping's).
    """

    def __init__(self, session: zenoh.Session, keys: Keys) -> None:
        self._session = session
        self._keys = keys
        self._lock = threading.Lock()
        self._outboxes: dict[str, Outbox] = {}
        self._closed = False

    def get(self, key: str, first_to: str | None = None, *, declared: bool = True) -> Outbox:
        """The outbox of `key`; the first put of a new one to process `first_to` waits
        until that process answers a ping (`until_answered`). A new one made with
        `declared=False` declares its publisher on its writer thread (`declare`, or its
        first put)."""
        outbox = self._outboxes.get(key)
        if outbox is not None and not outbox.closed:
            return outbox
        ready = functools.partial(self.until_answered, first_to) if first_to else None
        # (made before our lock is taken: no Zenoh call under it, its callbacks take it)
        fresh = Outbox(self._session, key, ready, declared=declared)
        with self._lock:
            outbox = self._outboxes.get(key)
            if self._closed:
                outbox = None  # (closed meanwhile: a writer made now would never end)
            elif outbox is None or outbox.closed:
                self._outboxes[key] = outbox = fresh
        if outbox is not fresh:
            fresh.close()
        if outbox is None:
            return fresh  # closed: it drops what it is given
        return outbox

    def pop(self, key: str) -> Outbox | None:
        """Forget the outbox of `key` (its destination went); the caller closes it."""
        with self._lock:
            return self._outboxes.pop(key, None)

    def retire(self, outbox: Outbox) -> None:
        """Forget `outbox` (if it is still its key's) and close it: what is queued on it
        is dropped (its `on_lost`, or `dropped()`, runs). Its destination is nobody's."""
        with self._lock:
            if self._outboxes.get(outbox.key) is outbox:
                del self._outboxes[outbox.key]
        outbox.close()

    def close(self, drain: float = 0.0) -> None:
        """Close every outbox: what is queued gets `drain` seconds, all outboxes together,
        to be put (their writers put in parallel); what is still queued then is lost."""
        with self._lock:
            self._closed = True
            outboxes = list(self._outboxes.values())
        deadline = time.monotonic() + drain
        for outbox in outboxes:
            outbox.close(max(0.0, deadline - time.monotonic()))

    def until_answered(self, zid: str) -> None:
        """Ping process `zid` until it answers (at most `HEAL_TIMEOUT` s; writer thread).

        When a link comes up (a host that joins, a healed link) the process's tokens may
        be here before what is sent to it gets through: a message put in between was lost
        without a word (a call right after the heal, or a host's first call right after
        it joined during a burst of refused handshakes, waited for its timeout). An
        answered ping went the way the next put goes; it costs one round trip, once per
        destination.
        """
        deadline = time.monotonic() + HEAL_TIMEOUT
        pause = threading.Event()
        while not self._closed and time.monotonic() < deadline:
            try:
                replies = self._session.get(self._keys.ping(zid), timeout=0.25)
                if any(reply.ok is not None for reply in replies):
                    return
            except Exception:  # noqa: BLE001 - the session closed: the put fails too
                return
            pause.wait(0.01)  # (no queryable seen yet: a get returns at once)
