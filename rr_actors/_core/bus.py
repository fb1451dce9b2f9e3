"""Publish events to subscribers that can never slow the publisher. Knows nothing of registrars.

```
 publishing thread                        │ subscriber threads (one per subscription)
                                          │
 if publisher.active:                     │
     publisher.publish(event) ──► INFO log line (`describe(event)`, `record.event`)
                              ├─► Subscription: bounded queue ──► its thread ──► callback(event)
                              ├─► Forwarder: bounded queue ─────► its thread ──► send([e1, e2,
                              ...])
                              └─► any other sink, called right here (must not block)
```

`Publisher.active` is one attribute read and a cached logger check, so nobody builds an
event that nobody hears. The sinks are a tuple replaced on every change (copy-on-write):
`publish` reads it once, without a lock. The queues and their gaps: `queues.py`.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable
from typing import Generic, TypeVar

from rr_actors._core import runtime
from rr_actors._core.queues import DEFAULT_MAXSIZE, Forwarder, Subscription

__all__ = ["DEFAULT_MAXSIZE", "Forwarder", "Publisher", "Sink", "Subscription"]

logger = logging.getLogger("rr_actors")

E = TypeVar("E")

Sink = Callable[[E], object]
"""`sink(event)`: called on the publishing thread; must return at once and not raise."""

_names = itertools.count(1)


class Publisher(Generic[E]):
    """Where events are published: to sinks and an INFO log line (`describe(event)`, the event
    in `record.event`). `notice(count)`: what a subscriber gets after losing `count` events;
    `tap` also gets each event (this one is `active` while it is). Publish only when `active`."""

    def __init__(
        self,
        *,
        logger: logging.Logger | None = None,
        describe: Callable[[E], str] = str,
        notice: Callable[[int], E] | None = None,
        tap: Publisher[E] | None = None,
    ) -> None:
        self._logger = logger
        self._describe = describe
        self._notice = notice
        self._lock = runtime.Lock()  # for writers of `_sinks`; `publish` reads without it
        self._sinks: tuple[Sink[E], ...] = ()
        self._upstream: Publisher[E] | None = None
        self._tap = tap
        self._watchers: tuple[Callable[[bool], object], ...] = ()
        self._notifying = runtime.Lock()

    @property
    def active(self) -> bool:
        """Whether anyone listens: a sink, INFO on the logger, or a listened upstream or tap."""
        if self._sinks:
            return True
        log = self._logger
        if log is not None and log.isEnabledFor(logging.INFO):
            return True
        upstream = self._upstream
        if upstream is not None and upstream.listened:
            return True
        tap = self._tap
        return tap is not None and bool(tap._sinks)

    def publish(self, event: E) -> None:
        """Log `event` at INFO (if enabled) and hand it to every sink, in order; never raises."""
        log = self._logger
        if log is not None and log.isEnabledFor(logging.INFO):
            self._log(log, event)
        self.deliver(event)
        tap = self._tap
        if tap is not None and tap._sinks:
            tap.deliver(event)

    def deliver(self, event: E) -> None:
        """Hand `event` to every sink (and upstream), without a log line (logged at its origin)."""
        for sink in self._sinks:
            try:
                sink(event)
            except Exception:
                logger.exception("event sink %r raised on %r", sink, event)
        upstream = self._upstream
        if upstream is not None:
            upstream.deliver(event)

    @property
    def listened(self) -> bool:
        """Whether a sink listens here or further up the relay (log lines do not count)."""
        if self._sinks:
            return True
        upstream = self._upstream
        return upstream is not None and upstream.listened

    def relay_to(self, upstream: Publisher[E] | None) -> None:
        """Hand every event published here on to `upstream`'s sinks, not its log (`None`: stop)."""
        self._upstream = upstream

    def watch_listeners(self, watcher: Callable[[bool], object]) -> Callable[[], None]:
        """Call `watcher(True)` at the first sink, `watcher(False)` after the last (on the thread
        that subscribes or closes); returns the function that stops the watching."""
        with self._lock:
            self._watchers = (*self._watchers, watcher)

        def unwatch() -> None:
            with self._lock:
                self._watchers = tuple(w for w in self._watchers if w is not watcher)

        return unwatch

    def _changed(self, before: bool, after: bool) -> None:
        if before == after:
            return
        with self._notifying:  # one at a time, each telling the state as it is then
            listened = bool(self._sinks)
            for watcher in self._watchers:
                try:
                    watcher(listened)
                except Exception:
                    logger.exception("event listener watcher %r raised", watcher)

    def _log(self, log: logging.Logger, event: E) -> None:
        try:
            line = self._describe(event)
        except Exception:
            logger.exception("describing the event %r failed", event)
            line = repr(event)
        # stacklevel 3: the record names the code that called `publish`
        log.info("%s", line, extra={"event": event}, stacklevel=3)

    def subscribe(
        self,
        callback: Callable[[E], object],
        *,
        maxsize: int = DEFAULT_MAXSIZE,
        name: str | None = None,
        maxbytes: int | None = None,
        weigh: Callable[[E], int] | None = None,
    ) -> Subscription[E]:
        """A `Subscription` of `callback` to every event from now on (`ConfigError`: a bad
        argument); `maxbytes` bounds its queue's weight too, `weigh(event)` on the publisher."""
        subscription = Subscription(
            callback,
            name=name or f"subscriber-{next(_names)}",
            maxsize=maxsize,
            notice=self._notice,
            unsubscribe=self._unsubscribe,
            maxbytes=maxbytes,
            weigh=weigh,
        )
        self.add_sink(subscription._offer)
        return subscription

    def _unsubscribe(self, subscription: Subscription[E]) -> None:
        self.remove_sink(subscription._offer)

    def add_sink(self, sink: Sink[E]) -> None:
        """Call `sink(event)` for every event from now on, on the publishing thread (quick)."""
        with self._lock:
            before = bool(self._sinks)
            self._sinks = (*self._sinks, sink)
        self._changed(before, True)

    def remove_sink(self, sink: Sink[E]) -> None:
        """Stop calling `sink` (the first equal one); nothing if it is not there (a publish under
        way may still call it once)."""
        with self._lock:
            before = bool(self._sinks)
            sinks = list(self._sinks)
            if sink in sinks:
                sinks.remove(sink)
                self._sinks = tuple(sinks)
            after = bool(self._sinks)
        self._changed(before, after)
