"""What stands between a publisher and a slow consumer: bounded queues and their threads.

A `Subscription` runs its callback on a thread of its own; a `Forwarder` ships batches to
another process from a thread of its own. Both take events from an `_Outbox`, a bounded
queue that drops instead of blocking and remembers the gap it made, and both linger a
moment after each batch so that a stream of events does not wake them once per event.
"""

from __future__ import annotations

import enum
import logging
import queue
import threading
from collections.abc import Callable
from types import TracebackType
from typing import Generic, TypeVar

from rr_actors._core.throttle import Throttle
from rr_actors.errors import ConfigError

__all__ = [
    "DEFAULT_MAXSIZE",
    "FORWARD_LINGER",
    "LINGER",
    "LOG_EVERY",
    "Forwarder",
    "Subscription",
]

logger = logging.getLogger("rr_actors")

E = TypeVar("E")

DEFAULT_MAXSIZE = 10_000
"""Events a subscription (or forwarder) holds before it drops new ones."""

LINGER = 0.001
"""Seconds a subscription's thread lets events pile up after a batch.

A publish wakes the consumer thread only when it waits for an event; while it lingers,
a burst of events (a call every 30-40 us) is put without waking anyone, and the next batch
takes them all. On one CPU, one wake-up per event cost a dedup-hit call about 20% with
one subscriber (`benchmarks/bench_core.py`); lingering costs each event up to this much
delivery latency.
"""

FORWARD_LINGER = 0.02
"""Seconds a forwarder's thread lets events pile up after it shipped a batch.

Longer than a subscription's `LINGER`: each batch a manager process ships wakes a thread
in it and two in the supervisor's process (the reader, the subscriber). Calls every
200-400 us into a manager process made a batch of 2-5 events with 1 ms, and an open
observer cost a dedup-hit call +30 to +70% (`benchmarks/bench_observer.py`). An event
after a quiet spell is shipped at once; only the events of a burst wait, at most this long.
"""


LOG_EVERY = 10.0
"""Seconds between two log lines about the same trouble of one subscriber or forwarder.

The first time a callback raises (or a queue overflows) is logged in full; what happens
again is counted, and reported in one line at most this often (and when it closes): a
callback that raises on every event must not write a traceback per event.
"""


class _Empty(enum.Enum):
    EMPTY = enum.auto()


class _Mark:
    """A place in a queue: set when the consumer got there (`stop`: and then end)."""

    __slots__ = ("reached", "stop")

    def __init__(self, *, stop: bool = False) -> None:
        self.reached = threading.Event()
        self.stop = stop


class _Outbox(Generic[E]):
    """A bounded queue that drops instead of blocking, and remembers the gap it made.

    `put` runs on any publishing thread and never blocks; one consumer thread `get`s.
    With several publishing threads at once the bound may be passed by as many events as
    there are threads (the size check and the put are not one step; a lock would cost
    every publish).
    """

    def __init__(self, owner: str, maxsize: int, notice: Callable[[int], E] | None) -> None:
        if isinstance(maxsize, bool) or not isinstance(maxsize, int) or maxsize < 1:
            raise ConfigError(f"maxsize must be a positive int, got {maxsize!r}")
        self._owner = owner
        self._maxsize = maxsize
        self._notice = notice
        self._items: queue.SimpleQueue[E | _Mark] = queue.SimpleQueue()
        self._lock = threading.Lock()  # gap and drop counts; the queue is thread-safe itself
        self._gap = 0
        self.dropped = 0
        self._warned = Throttle(LOG_EVERY)  # (gaps opened; `_reported`: drops already logged)
        self._reported = 0

    def put(self, item: E) -> None:
        if not self._gap and self._items.qsize() < self._maxsize:
            self._items.put(item)
        else:
            self._put_slowly(item)

    def _put_slowly(self, item: E) -> None:
        warn = first = False
        with self._lock:
            full = self._items.qsize() >= self._maxsize
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
                self._items.put(item)
        if warn and first:
            logger.warning(
                "%s falls behind: its queue of %d events is full; dropping events until it "
                "has room (they are counted and reported to it as one notice)",
                self._owner,
                self._maxsize,
            )
        elif warn:
            logger.warning(
                "%s falls behind again: %d events dropped in %d gaps since the last warning",
                self._owner,
                since,
                gaps - 1,
            )

    def drain(self) -> int:
        """Drop what is queued (its consumer gave up): count the events, pass the marks."""
        events = 0
        while True:
            try:
                item = self._items.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, _Mark):
                item.reached.set()
            else:
                events += 1
        with self._lock:
            self.dropped += events
        return events

    def _close_gap(self) -> None:
        """Put the notice for the events dropped since the last put (hold `_lock`)."""
        if self._gap:
            if self._notice is not None:
                self._items.put(self._notice(self._gap))
            self._gap = 0

    def put_mark(self, mark: _Mark) -> None:
        """Put `mark` after everything put so far (and after the notice of an open gap)."""
        with self._lock:
            self._close_gap()
            self._items.put(mark)

    def get(self) -> E | _Mark:
        """The next item, waiting for one; an open gap is closed first if the queue ran empty."""
        if self._items.empty() and self._gap:
            with self._lock:
                self._close_gap()
        return self._items.get()

    def get_nowait(self) -> E | _Mark | _Empty:
        """The next item, or `_Empty.EMPTY` (after closing an open gap) if there is none."""
        if self._items.empty():
            if self._gap:
                with self._lock:
                    self._close_gap()
            if self._items.empty():
                return _Empty.EMPTY
        return self._items.get()


class _Consumer(Generic[E]):
    """The outbox, the thread, the waits and the close a subscription and a forwarder share."""

    def __init__(self, outbox: _Outbox[E], *, thread_name: str, what: str) -> None:
        self._outbox = outbox
        self._what = what
        self._thread = threading.Thread(target=self._run, name=thread_name, daemon=True)
        self._closing = threading.Lock()
        self._closed = False
        self._abandoned = False  # close() timed out: stop after the current item
        self._hurry = threading.Event()  # a wait or a close is due: linger no longer

    def _run(self) -> None:  # each consumer's loop (a subclass's)
        raise NotImplementedError

    def _linger(self, seconds: float) -> None:
        """Let a burst pile up for `seconds`, unless a wait or a close came meanwhile."""
        if self._hurry.wait(seconds):
            self._hurry.clear()

    def _reach_mark(self, *, timeout: float | None, caller: str) -> bool:
        """Wait until the thread handled everything put before this call."""
        if threading.current_thread() is self._thread:
            raise RuntimeError(f"{caller} on the {self._what}'s own thread would wait for itself")
        mark = _Mark()
        with self._closing:  # a mark put after the stop mark would never be reached
            closed = self._closed
            if not closed:
                self._outbox.put_mark(mark)
                self._hurry.set()
        if closed:
            self._thread.join(timeout)
            return not self._thread.is_alive() and not self._abandoned
        return mark.reached.wait(timeout)

    def _stop(self, *, timeout: float | None) -> None:
        with self._closing:
            if not self._closed:
                self._closed = True
                self._outbox.put_mark(_Mark(stop=True))
                self._hurry.set()
        if threading.current_thread() is self._thread:
            return  # closed from its own callback: it ends once that returns
        self._thread.join(timeout)
        if self._thread.is_alive() and not self._abandoned:
            self._abandoned = True
            dropped = self._outbox.drain()  # (counted in `dropped`)
            logger.warning(
                "%s did not finish within %s s; the %d events it had not handled yet are dropped",
                self._what,
                timeout,
                dropped,
            )


class Subscription(_Consumer[E]):
    """One subscriber's events: a bounded queue and a thread of its own that runs the callback.

    Made by `subscribe` (`Supervisor.subscribe`, `ResourceRegistrar.subscribe`). The
    callback runs on this subscription's own daemon thread (named `rr-events-<name>`),
    never on the publishing thread and never in a registrar's mailbox, one event at a
    time, in publish order. It may block or be slow: the publisher never waits for it.
    When its queue is full, new events are dropped and counted (`dropped`); once there
    is room again the callback gets one notice of the gap (`EventsDropped(count)` for
    rr_actors' events) where the lost events would have been.

    An exception from the callback is logged (logger `rr_actors`) and delivery goes on:
    the first with its traceback, later ones as a count, at most once every `LOG_EVERY`
    seconds (and when the subscription ends). Falling behind is likewise warned about
    once, then at most once every `LOG_EVERY` seconds with the events dropped meanwhile.

    Use it as a context manager (`with sup.subscribe(cb): ...`) or call `close()`.

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
    ) -> None:
        self.name = name
        self._callback = callback
        self._unsubscribe = unsubscribe
        self._raising = Throttle(LOG_EVERY)  # the callback's exceptions: logged first, then counted
        what = f"event subscriber {name!r}"
        super().__init__(_Outbox(what, maxsize, notice), thread_name=f"rr-events-{name}", what=what)
        self._offer = self._outbox.put  # the publisher's sink: never blocks
        self._thread.start()

    @property
    def dropped(self) -> int:
        """How many events this subscription dropped so far: because its queue was full,
        or because a `close()` that ran out of time left them unhandled."""
        return self._outbox.dropped

    @property
    def closed(self) -> bool:
        """Whether `close()` was called (its thread may still be finishing)."""
        return self._closed

    def wait_delivered(self, *, timeout: float | None = 5.0) -> bool:
        """Block until every event published before this call went through the callback.

        Dropped events count as gone through once their notice was delivered. Useful in
        tests and before a program exits.

        Args:
            timeout: the longest wait, in seconds (`None`: no bound).

        Returns:
            `True` when everything was delivered, `False` if `timeout` passed first (or
            the subscription was closed before it could deliver everything).

        Raises:
            RuntimeError: called from this subscription's own callback (it would wait
                for itself).
        """
        return self._reach_mark(timeout=timeout, caller="wait_delivered()")

    def close(self, *, timeout: float | None = 5.0) -> None:
        """Unsubscribe, deliver what was already queued, and end the thread.

        Events published after `close` started are not delivered. If the callback has
        not worked through the queue within `timeout`, the rest is dropped (a WARNING
        says so) and the thread ends after the event it is handling. Calling it again,
        or from the callback itself (which then returns first), is fine.

        Args:
            timeout: how long to wait for the queued events, in seconds (`None`: no bound).
        """
        if not self._closed:
            self._unsubscribe(self)
        self._stop(timeout=timeout)

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
        return f"<Subscription {self.name!r} dropped={self.dropped} closed={self._closed}>"

    def _run(self) -> None:
        outbox, callback = self._outbox, self._callback
        while True:
            item: E | _Mark | _Empty = outbox.get()  # idle: the next publish wakes it
            while not isinstance(item, _Empty):  # a batch: all that piled up
                if isinstance(item, _Mark):
                    item.reached.set()
                    if item.stop:
                        self._report_raised(None)
                        return
                else:
                    try:
                        callback(item)
                    except BaseException as exc:  # noqa: BLE001 - the thread must outlive any callback
                        if self._raising.due():
                            self._report_raised((item, exc))
                if self._abandoned:
                    self._report_raised(None)
                    return
                item = outbox.get_nowait()
            self._linger(LINGER)  # a burst piles up meanwhile, without a wake-up per event

    def _report_raised(self, latest: tuple[E, BaseException] | None) -> None:
        """Log the callback's exceptions: the first in full, later ones as a count
        (`latest`: the one that just happened; `None`: the subscription ends)."""
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


class Forwarder(_Consumer[E]):
    """A sink that ships events in batches from its own thread (to another process, say).

    Add it to a publisher (`publisher.add_sink(forwarder)`). It puts each event in a
    bounded buffer and returns; its daemon thread (named `rr-forward-<name>`) calls
    `send(batch)` with everything that piled up (at most `max_batch` events, in publish
    order). When the buffer is full, events are dropped and counted, and with a
    `notice` factory the next batch carries `notice(count)` where they were lost. A
    `send` that raises is logged (once per run of failures) and its batch counts as
    dropped.

    Args:
        send: called with a new list of events on the forwarder's thread (a manager
            process sends it over its pipe to the supervisor's process). It may block.
        maxsize: events the buffer holds before it drops new ones.
        max_batch: the most events one `send` gets.
        notice: `notice(count)` makes the item that marks a gap (`EventsDropped`), or
            `None` for no marker.
        name: for the thread's name and log lines.

    Raises:
        ConfigError: `maxsize` or `max_batch` is not a positive int.
    """

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
        what = f"event forwarder {name!r}"
        super().__init__(
            _Outbox(what, maxsize, notice), thread_name=f"rr-forward-{name}", what=what
        )
        self._thread.start()

    def __call__(self, event: E) -> None:
        """Buffer `event` for the next batch (on the publishing thread; never blocks)."""
        self._outbox.put(event)

    @property
    def dropped(self) -> int:
        """Events lost so far: dropped for a full buffer, in a batch whose `send` raised, or
        left unsent by a `close()` that ran out of time."""
        return self._outbox.dropped + self._failed

    def wait_sent(self, *, timeout: float | None = 5.0) -> bool:
        """Block until every event given before this call was passed to `send` (or dropped).

        Args:
            timeout: the longest wait, in seconds (`None`: no bound).

        Returns:
            `True` when done, `False` if `timeout` passed first.

        Raises:
            RuntimeError: called from `send` itself (it would wait for itself).
        """
        return self._reach_mark(timeout=timeout, caller="wait_sent()")

    def close(self, *, timeout: float | None = 5.0) -> None:
        """Send what is buffered (within `timeout` seconds) and end the thread. Idempotent.

        Remove it from its publisher first: events given after `close` are not sent.

        Args:
            timeout: how long to wait for the last batches, in seconds (`None`: no bound).
        """
        self._stop(timeout=timeout)

    def __repr__(self) -> str:
        return f"<Forwarder {self.name!r} dropped={self.dropped} closed={self._closed}>"

    def _run(self) -> None:
        outbox = self._outbox
        while True:
            item: E | _Mark | _Empty = outbox.get()
            batch: list[E] = []
            while not isinstance(item, _Empty):
                if isinstance(item, _Mark):
                    self._ship(batch)
                    batch = []
                    item.reached.set()
                    if item.stop:
                        return
                else:
                    batch.append(item)
                    if len(batch) >= self._max_batch:
                        self._ship(batch)
                        batch = []
                if self._abandoned:
                    return
                item = outbox.get_nowait()
            self._ship(batch)
            self._linger(FORWARD_LINGER)  # a burst piles up meanwhile, without a wake-up each

    def _ship(self, batch: list[E]) -> None:
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
