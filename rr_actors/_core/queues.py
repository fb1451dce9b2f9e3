"""What stands between a publisher and a slow consumer: bounded queues and their threads.

A `Subscription` runs its callback, a `Forwarder` ships batches to another process, each on a thread
of its own (a `SerialExecutor`) behind an `_Outbox`: a bound that drops instead of blocking and
remembers the gap it made. Both linger a moment after each batch, so that a stream of events does
not wake them once per event.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from types import TracebackType
from typing import Generic, TypeVar, cast

from rr_actors._core import runtime
from rr_actors._core.serial import SerialExecutor, Task
from rr_actors._core.throttle import Throttle
from rr_actors.errors import ConfigError

logger = logging.getLogger("rr_actors")

E = TypeVar("E")

DEFAULT_MAXSIZE = 10_000
"""Events a subscription (or forwarder) holds before it drops new ones."""

LINGER = 0.001
"""Seconds a subscription's thread lets events pile up after a batch: a burst is put without
a wake-up per event, each event delayed at most this much.
"""

FORWARD_LINGER = 0.02
"""Seconds a forwarder's thread lets events pile up after a batch (each batch wakes three
threads in two processes); an event after a quiet spell is shipped at once.
"""


LOG_EVERY = 10.0
"""Seconds between two log lines about the same trouble of one subscriber or forwarder: the
first in full, the rest counted.
"""


class _Outbox(Generic[E]):
    """A consumer's thread behind a bound that drops (`put` never blocks) and remembers the gap
    for its notice; with `maxbytes`, what is queued weighs at most that (those puts lock)."""

    def __init__(
        self,
        what: str,
        maxsize: int,
        notice: Callable[[int], E] | None,
        handle: Callable[[E], object],
        *,
        thread_name: str,
        linger: float,
        idle: Callable[[], object] | None = None,
        end: Callable[[], object] | None = None,
        maxbytes: int | None = None,
        weigh: Callable[[E], int] | None = None,
    ) -> None:
        if isinstance(maxsize, bool) or not isinstance(maxsize, int) or maxsize < 1:
            raise ConfigError(f"maxsize must be a positive int, got {maxsize!r}")
        if (maxbytes is None) != (weigh is None) or (
            maxbytes is not None
            and (isinstance(maxbytes, bool) or not isinstance(maxbytes, int) or maxbytes < 1)
        ):
            raise ConfigError(f"maxbytes must be a positive int given with weigh, got {maxbytes!r}")
        self._what = what
        self._maxsize = maxsize
        self._maxbytes = maxbytes
        self._weigh = weigh
        self._bytes = 0  # the weight queued and not handled yet (with `maxbytes`)
        self._notice = notice
        self._handle = handle
        self._idle = idle
        self._lock = runtime.Lock()  # gap and drop counts
        self._gap = 0
        self.dropped = 0
        self._warned = Throttle(LOG_EVERY)  # (gaps opened; `_reported`: drops already logged)
        self._reported = 0
        self._abandoned = False  # a close timed out
        self.executor = SerialExecutor(
            thread_name, linger=linger, on_idle=self._ran_dry, on_drop=self._dropped, on_end=end
        )
        self.executor.start()

    def put(self, item: E) -> None:
        if self._weigh is not None:
            self._put_slowly(item, self._weigh(item))
        elif not self._gap and self.executor.pending < self._maxsize:
            self.executor.submit(functools.partial(self._handle, item))
        else:
            self._put_slowly(item)

    def _put_slowly(self, item: E, weight: int | None = None) -> None:
        warn = first = False
        with self._lock:
            full = self.executor.pending >= self._maxsize or (
                weight is not None and self._bytes + weight > cast(int, self._maxbytes)
            )
            if full:
                self.dropped += 1
                self._gap += 1
                if self._gap == 1 and self._warned.due():  # (at most every LOG_EVERY s)
                    warn, first = True, not self._warned.logged
                    gaps, self._warned.unlogged, self._warned.logged = (
                        self._warned.unlogged,
                        0,
                        True,
                    )
                    since, self._reported = self.dropped - 1 - self._reported, self.dropped - 1
            else:
                self._close_gap()
                if weight is None:
                    self.executor.submit(functools.partial(self._handle, item))
                else:
                    self._bytes += weight
                    self.executor.submit(functools.partial(self._handle_weighed, item, weight))
        if warn and first:
            logger.warning(
                "%s falls behind: its queue of %d events%s is full; dropping events until it "
                "has room (they are counted and reported to it as one notice)",
                self._what,
                self._maxsize,
                "" if self._maxbytes is None else f" or {self._maxbytes} bytes",
            )
        elif warn:
            logger.warning(
                "%s falls behind again: %d events dropped in %d gaps since the last warning",
                self._what,
                since,
                gaps - 1,
            )

    def _handle_weighed(self, item: E, weight: int) -> None:
        try:
            self._handle(item)
        finally:
            with self._lock:
                self._bytes -= weight

    def _close_gap(self) -> None:
        """Queue the notice for the events dropped since the last put (hold `_lock`)."""
        if self._gap:
            if self._notice is not None:
                self.executor.submit(functools.partial(self._handle, self._notice(self._gap)))
            self._gap = 0

    def close_gap(self) -> None:
        if self._gap:
            with self._lock:
                self._close_gap()

    def _ran_dry(self) -> None:
        if self._idle is not None:
            self._idle()
        self.close_gap()

    def _dropped(self, task: Task) -> None:
        if isinstance(task, functools.partial):  # (an event's, not a forwarder's ship)
            with self._lock:
                self.dropped += 1

    def wait(self, *, timeout: float | None, caller: str, first: Task | None = None) -> bool:
        """Wait until the thread handled everything put before this call (`first` last)."""
        if self.executor.on_own_thread():
            raise RuntimeError(f"{caller} on the {self._what}'s own thread would wait for itself")
        self.close_gap()
        if first is not None:
            self.executor.submit(first)
        return self.executor.flush(timeout=timeout)

    def stop(self, *, timeout: float | None, last: Task | None = None) -> None:
        """Handle what is queued (`last` last) within `timeout` s, then drop the rest."""
        if not self.executor.closed:
            self.close_gap()
            if last is not None:
                self.executor.submit(last)
        before = self.dropped
        if self.executor.close(timeout=timeout) or self.executor.on_own_thread():
            return  # (closed from its own callback: it ends once that returns)
        lost = self.dropped - before
        if lost and not self._abandoned:  # (none lost: nothing to warn of, as a close(0))
            self._abandoned = True
            logger.warning(
                "%s did not finish within %s s; the %d events it had not handled yet are dropped",
                self._what,
                timeout,
                lost,
            )


class Subscription(Generic[E]):
    """One subscriber's events: a bounded queue and a thread of its own that runs the callback.

    Made by `Supervisor.subscribe` and `ResourceRegistrar.subscribe`; the callback runs on
    its thread (`rr-events-<name>`) one event at a time in publish order. A full queue (or,
    with `maxbytes`, too heavy) drops new events, counted (`dropped`); the callback later
    gets one `EventsDropped` in their place. What it raises is logged (the first with its
    traceback, then a count at most every `LOG_EVERY` s). A context manager, or `close()`.

    Attributes:
        name: the subscription's name (in its thread's name and in log lines).
    """

    def __init__(
        self,
        callback: Callable[[E], object],
        *,
        name: str,
        maxsize: int,
        notice: Callable[[int], E] | None,
        unsubscribe: Callable[[Subscription[E]], None],
        maxbytes: int | None = None,
        weigh: Callable[[E], int] | None = None,
    ) -> None:
        if not callable(callback):  # (else each event would log the TypeError, for ever)
            raise ConfigError(f"callback must be callable, got {callback!r}")
        self.name = name
        self._callback = callback
        self._unsubscribe = unsubscribe
        self._raising = Throttle(LOG_EVERY)  # the callback's exceptions: logged first, then counted
        self._outbox = _Outbox(
            f"event subscriber {name!r}",
            maxsize,
            notice,
            self._deliver,
            thread_name=f"rr-events-{name}",
            linger=LINGER,  # a burst piles up meanwhile, without a wake-up per event
            end=lambda: self._report_raised(None),
            maxbytes=maxbytes,
            weigh=weigh,
        )
        self._offer = self._outbox.put  # the publisher's sink: never blocks

    @property
    def dropped(self) -> int:
        """Events dropped so far: for a full queue, or left by a `close()` that ran out of time."""
        return self._outbox.dropped

    @property
    def closed(self) -> bool:
        """Whether `close()` was called (its thread may still be finishing)."""
        return self._outbox.executor.closed

    def wait_delivered(self, *, timeout: float | None = 5.0) -> bool:
        """Block at most `timeout` s until every event published before was through the callback
        (or its notice); `False` if not, or closed. `RuntimeError` from its own callback."""
        return self._outbox.wait(timeout=timeout, caller="wait_delivered()")

    def close(self, *, timeout: float | None = 5.0) -> None:
        """Unsubscribe, deliver what was queued within `timeout` seconds (the rest dropped, with a
        WARNING), and end the thread. Idempotent; from the callback it returns first."""
        if not self.closed:
            self._unsubscribe(self)
        self._outbox.stop(timeout=timeout)

    def __enter__(self) -> Subscription[E]:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<Subscription {self.name!r} dropped={self.dropped} closed={self.closed}>"

    def _deliver(self, item: E) -> None:
        try:
            self._callback(item)
        except BaseException as exc:  # noqa: BLE001 - the thread must outlive any callback
            if self._raising.due():
                self._report_raised((item, exc))

    def _report_raised(self, latest: tuple[E, BaseException] | None) -> None:
        """Log the callback's exceptions: the first in full, later as a count (`None`: it ends)."""
        raising = self._raising
        if latest is not None and not raising.logged:
            raising.logged, raising.unlogged = True, 0
            item, exc = latest
            logger.error(
                "event subscriber %r: the callback raised on %r (later exceptions are "
                "counted, and logged once every %g s)",
                self.name,
                item,
                LOG_EVERY,
                exc_info=exc,
            )
        elif raising.unlogged:
            count, raising.unlogged = raising.unlogged, 0
            detail = "" if latest is None else f"; the latest: {type(latest[1]).__name__}"
            logger.error(
                "event subscriber %r: the callback raised %d more times%s",
                self.name,
                count,
                detail,
            )


class Forwarder(Generic[E]):
    """A sink that ships events in batches from its own thread (to another process, say).

    `publisher.add_sink(forwarder)`: each event is buffered, and its daemon thread
    (`rr-forward-<name>`) calls `send(batch)` (may block) with what piled up, at most
    `max_batch`, in order. A full buffer (`maxsize`) drops events, the next batch carrying
    `notice(count)`; a `send` that raises is logged and its batch counts as dropped.
    `ConfigError`: `maxsize` or `max_batch` is not a positive int."""

    def __init__(
        self,
        send: Callable[[list[E]], object],
        *,
        maxsize: int = DEFAULT_MAXSIZE,
        max_batch: int = 1_000,
        notice: Callable[[int], E] | None = None,
        name: str = "forwarder",
    ) -> None:
        if isinstance(max_batch, bool) or not isinstance(max_batch, int) or max_batch < 1:
            raise ConfigError(f"max_batch must be a positive int, got {max_batch!r}")
        self.name = name
        self._send = send
        self._max_batch = max_batch
        self._failed = 0  # events in batches whose send raised
        self._failing = False
        self._batch: list[E] = []  # taken from the queue, not shipped yet (its thread's)
        self._outbox = _Outbox(
            f"event forwarder {name!r}",
            maxsize,
            notice,
            self._take,
            thread_name=f"rr-forward-{name}",
            linger=FORWARD_LINGER,  # a burst piles up meanwhile, without a wake-up each
            idle=self._ship,
        )

    def __call__(self, event: E) -> None:
        """Buffer `event` for the next batch (never blocks)."""
        self._outbox.put(event)

    @property
    def dropped(self) -> int:
        """Events lost: for a full buffer, in a failed `send`, or left by a late `close()`."""
        return self._outbox.dropped + self._failed

    def wait_sent(self, *, timeout: float | None = 5.0) -> bool:
        """Block until every event given before was passed to `send` (or dropped), at most `timeout`
        seconds; `False` if the time ran out. `RuntimeError` from `send` itself."""
        return self._outbox.wait(timeout=timeout, caller="wait_sent()", first=self._ship)

    def close(self, *, timeout: float | None = 5.0) -> None:
        """Send what is buffered (within `timeout` seconds) and end the thread. Idempotent; remove
        it from its publisher first."""
        self._outbox.stop(timeout=timeout, last=self._ship)

    @property
    def executor(self) -> SerialExecutor:
        """Its thread's executor (joined once closed: `send` must not outlive the interpreter)."""
        return self._outbox.executor

    def __repr__(self) -> str:
        closed = self._outbox.executor.closed
        return f"<Forwarder {self.name!r} dropped={self.dropped} closed={closed}>"

    def _take(self, event: E) -> None:
        self._batch.append(event)
        if len(self._batch) >= self._max_batch:
            self._ship()

    def _ship(self) -> None:
        batch, self._batch = self._batch, []
        if not batch:
            return
        try:
            self._send(batch)
        except Exception:
            self._failed += len(batch)
            if not self._failing:
                logger.exception(
                    "event forwarder %r: send failed; its events are dropped until it works",
                    self.name,
                )
            self._failing = True
        else:
            self._failing = False
