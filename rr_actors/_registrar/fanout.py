"""A status fanned out in one pass per process: the routes, the desk and its runner.

```
 provider: notify(resource) ──► its consumer registrars, by process (`Routes.plan`):
   this process ──────────────► DESK.deliver(parts), on the provider's actor thread
   another process, known ────► one StatusBatch to that process's relay (a registrar
                                there, the same one each time: notices keep their order)
   not known yet ─────────────► a StatusBatch to the consumer registrar itself; every
                                answer says which process each registrar it reached is
                                in (`Routes.learn`)
 a StatusBatch at a relay ────► DESK.deliver(parts), on the relay's actor thread
 DESK.deliver, per consumer registrar:
   of this process ──► each id it holds with a status callback, loaded, not a
                       dependency, its answer not due ──► the callback, queued on the
                       process's status runner (no trip through that registrar's mailbox)
                       every other id (a dependency to climb, an answer on its way) ──►
                       a StatusNotice through its mailbox, as before (`status.py`)
   moved elsewhere ──► a StatusBatch of its part, forwarded to it
 acknowledgements: one `SharedJoin` per batch, answered once when every callback ran
```

The runner runs the callbacks of the whole process in the order they arrived, on as few
worker threads as keeps them going: one while each callback returns at once; another as
soon as every one of them is inside a callback when more arrive (a callback that calls
`send_status`), or once one has run a callback for `SLICE` seconds (a slow or hung
callback holds its own thread, never the others' callbacks).

Each consumer registrar publishes what the desk reads of it (`StatusTargets`): its actor
is the only writer (one dict assignment each), the desk reads single entries. A status is
one event: the desk delivers each (event, id) pair once, so a batch sent again after its
relay failed does not run a callback twice.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
import uuid
import weakref
from collections.abc import Callable, Iterable
from typing import Any, Protocol

from rr_actors import events
from rr_actors._core.bus import Publisher
from rr_actors._core.directory import DIRECTORY, LocalPeer
from rr_actors._core.replies import CallbackReply, SharedJoin
from rr_actors._core.workers import Workers
from rr_actors._platform import fork
from rr_actors._registrar.messages import StatusBatch, StatusNotice
from rr_actors._types import Query, StatusCallback, StatusUpdate
from rr_actors.errors import RrError

__all__ = ["DESK", "SLICE", "Desk", "Routes", "StatusTargets", "process"]

logger = logging.getLogger("rr_actors")

SLICE = 0.05
"""Seconds a status callback may run before the callbacks queued behind it go on
without it, on another worker thread."""

_SEEN = 16_384
"""(event, query id) pairs a desk remembers, to deliver each once."""

_PROCESS = uuid.uuid4().hex


def process() -> str:
    """This process's key in the answers to status batches (a new one after a fork)."""
    return _PROCESS


Parts = tuple[tuple[str, tuple[str, ...]], ...]
"""(consumer registrar, its query ids) of one status, one entry per registrar."""


class Due(Protocol):
    """The ids whose call answers are on their way (`calls.DueAnswers`): read by any thread."""

    def __contains__(self, query_id: str) -> bool: ...


class StatusTargets:
    """What the desk reads of one registrar: the ids a status reaches without its mailbox.

    `entries` maps each id it holds with a status callback (loaded, not a dependency) to
    its query and callback. Only the registrar's actor writes it (the `Consumer` role),
    one assignment or `pop` at a time; the desk of its process reads single entries on
    another registrar's actor thread.
    """

    __slots__ = ("__weakref__", "due", "entries", "events", "name")

    def __init__(self, name: str, published: Publisher[events.Event], due: Due) -> None:
        self.name = name
        self.events = published
        self.due = due
        self.entries: dict[str, tuple[Query, StatusCallback]] = {}


class _Call:
    """One status callback to run, and the part of its batch's join it completes."""

    __slots__ = ("callback", "done", "query", "update")

    def __init__(
        self,
        callback: StatusCallback,
        query: Query,
        update: StatusUpdate,
        done: Callable[..., None],
    ) -> None:
        self.callback = callback
        self.query = query
        self.update = update
        self.done = done

    def __call__(self) -> None:
        try:
            self.callback(self.query, self.update)
        except Exception:
            logger.exception("status callback for %s raised", self.query.id)
        finally:
            self.done()


class _Drainer:
    """One worker's turn at the runner's queue."""

    __slots__ = ("abandoned", "inside")

    def __init__(self) -> None:
        self.abandoned = False  # it overran `SLICE`: it no longer takes calls
        self.inside = False  # it runs a callback now


class Runner:
    """Runs the status callbacks of this process in arrival order (see the module doc)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._calls: collections.deque[_Call] = collections.deque()
        self._drainers = 0  # drainers that take calls (not abandoned)
        self._inside = 0  # of them, those inside a callback now
        self._workers = Workers("status")

    def run(self, calls: Iterable[_Call]) -> None:
        """Queue `calls`; start a drainer if none is free to take them."""
        with self._lock:
            self._calls.extend(calls)
            start = self._drainers == self._inside and bool(self._calls)
            if start:
                self._drainers += 1
        if start:
            self._start()

    def _start(self) -> None:
        """Start one drainer (counted already): its calls are skipped if no thread can."""
        drainer = _Drainer()
        try:
            self._workers.submit(
                lambda: self._drain(drainer),
                timeout=SLICE,
                on_overdue=lambda: self._overdue(drainer),
                quiet=True,
            )
        except RuntimeError:
            logger.exception("no worker thread for status callbacks: they are skipped")
            with self._lock:
                self._drainers -= 1
                skipped: list[_Call] = []
                if self._drainers == 0:  # nobody else will take them
                    skipped, self._calls = list(self._calls), collections.deque()
            for call in skipped:
                call.done()

    def _drain(self, drainer: _Drainer) -> None:
        """A worker's turn: run queued calls until none is left, or hand over after
        half a slice (the watchdog abandons a turn at `SLICE`)."""
        began = time.monotonic()
        while True:
            with self._lock:
                if drainer.abandoned:
                    return
                if not self._calls:
                    drainer.abandoned = True  # (a late watchdog finds nothing to do)
                    self._drainers -= 1
                    return
                if time.monotonic() - began > SLICE / 2:
                    drainer.abandoned = True  # the next drainer takes over its count
                    hand_over = True
                else:
                    hand_over = False
                    call = self._calls.popleft()
                    drainer.inside = True
                    self._inside += 1
            if hand_over:
                self._start()
                return
            try:
                call()
            finally:
                with self._lock:
                    drainer.inside = False
                    if not drainer.abandoned:
                        self._inside -= 1

    def _overdue(self, drainer: _Drainer) -> None:
        """A drainer ran longer than `SLICE` (the watchdog's thread): it stops taking
        calls once its callback returns, and another drainer takes the queue."""
        with self._lock:
            if drainer.abandoned:
                return
            drainer.abandoned = True
            self._drainers -= 1
            if drainer.inside:
                self._inside -= 1
            start = bool(self._calls) and self._drainers == self._inside
            if start:
                self._drainers += 1
        if start:
            self._start()


class Desk:
    """This process's status desk: delivers a status to its registrars in one pass."""

    def __init__(self) -> None:
        self.targets: weakref.WeakKeyDictionary[LocalPeer, StatusTargets] = (
            weakref.WeakKeyDictionary()
        )
        self._lock = threading.Lock()
        self._seen: collections.OrderedDict[tuple[str, str], None] = collections.OrderedDict()
        self.runner = Runner()

    def serve(self, peer: LocalPeer, targets: StatusTargets) -> None:
        """Read `targets` for the registrar behind `peer` (while the directory has it)."""
        with self._lock:
            self.targets[peer] = targets

    def deliver(self, batch: StatusBatch, join: SharedJoin, homes: dict[str, str] | None) -> None:
        """Deliver `batch`'s parts (on an actor thread); each adds its parts to `join`.

        `homes`, if given, gets the process of each registrar reached (the answer).
        """
        calls: list[_Call] = []
        for origin, ids in batch.parts:
            try:
                peer = DIRECTORY.lookup(origin)
            except RrError:  # gone: nothing to deliver (as a notice to it would fail)
                continue
            if type(peer) is not LocalPeer:  # (it moved to another process)
                self.forward(peer, batch, (origin, ids), join, homes)
                continue
            if homes is not None:
                homes[origin] = _PROCESS
            fresh = self.first_time(batch.event, ids)
            if not fresh:
                continue
            targets = self.targets.get(peer)
            slow = self.direct(targets, batch, fresh, join, calls) if targets else fresh
            if slow:
                reply = CallbackReply(join.add())
                try:
                    peer.tell(
                        StatusNotice(
                            slow,
                            batch.status,
                            batch.message,
                            batch.source,
                            batch.event,
                            reply,
                            batch.hop,
                            batch.sent_at,
                        )
                    )
                except RrError as exc:
                    reply.set_error(exc)
        if calls:
            self.runner.run(calls)

    def direct(
        self,
        targets: StatusTargets,
        batch: StatusBatch,
        ids: tuple[str, ...],
        join: SharedJoin,
        calls: list[_Call],
    ) -> tuple[str, ...]:
        """Queue the callbacks of the ids `targets` has; the others, to go through its
        registrar's mailbox."""
        slow: list[str] = []
        entries, due = targets.entries, targets.due
        publish = targets.events.active
        for query_id in ids:
            entry = entries.get(query_id)
            if entry is None or query_id in due:
                slow.append(query_id)
                continue
            query, callback = entry
            if publish:
                targets.events.publish(
                    events.StatusDelivered(
                        targets.name,
                        query_id,
                        batch.status,
                        batch.hop,
                        max(0.0, time.time() - batch.sent_at),
                        batch.event,
                    )
                )
            update = StatusUpdate(query_id, batch.status, batch.message, batch.source)
            calls.append(_Call(callback, query, update, join.add()))
        return tuple(slow)

    def forward(
        self,
        peer: Any,
        batch: StatusBatch,
        part: tuple[str, tuple[str, ...]],
        join: SharedJoin,
        homes: dict[str, str] | None,
    ) -> None:
        """Send `part` on to its registrar in another process; its answer joins ours."""
        done = join.add()

        def answered(value: Any, error: BaseException | None) -> None:
            if error is None and homes is not None and isinstance(value, dict):
                homes.update(value)
            done()

        reply = CallbackReply(answered)
        try:
            peer.tell(batch.part((part,), reply))
        except RrError as exc:
            reply.set_error(exc)

    def first_time(self, event: str, ids: tuple[str, ...]) -> tuple[str, ...]:
        """Those of `ids` that event `event` has not reached here yet (marked now)."""
        seen = self._seen
        fresh = []
        with self._lock:
            for query_id in ids:
                key = (event, query_id)
                if key not in seen:
                    seen[key] = None
                    fresh.append(query_id)
            while len(seen) > _SEEN:
                seen.popitem(last=False)
        return tuple(fresh)

    def forget_in_child(self) -> None:
        """In a forked child: the parent's registrars and threads are not here."""
        self._lock = threading.Lock()
        self.targets = weakref.WeakKeyDictionary()
        self._seen = collections.OrderedDict()
        self.runner = Runner()


DESK = Desk()
"""This process's status desk."""


class Routes:
    """Where a provider sends its statuses for registrars of other processes.

    `homes` maps a consumer registrar to its process (learned from the answers), and
    `relays` each process to the registrar there that gets this provider's batches for
    it (the first one learned, kept while it answers: one connection, one mailbox, so
    the batches keep their order). Hints only: a wrong one costs a forward at the other
    end. Written by the threads that answer, read by the provider's actor.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.homes: dict[str, str] = {}
        self.relays: dict[str, str] = {}

    def plan(self, parts: Iterable[tuple[str, tuple[str, ...]]]) -> list[tuple[str, Parts]]:
        """Group `parts` by process: (the relay, the parts it gets) for each."""
        groups: dict[str, list[tuple[str, tuple[str, ...]]]] = {}
        alone: list[tuple[str, Parts]] = []
        with self._lock:
            for part in parts:
                home = self.homes.get(part[0])
                if home is None:
                    alone.append((part[0], (part,)))
                else:
                    groups.setdefault(home, []).append(part)
            planned = []
            for home, members in groups.items():
                relay = self.relays.setdefault(home, members[0][0])
                planned.append((relay, tuple(members)))
        return planned + alone

    def learn(self, homes: dict[str, str]) -> None:
        """Registrars are in these processes (an answer said so)."""
        with self._lock:
            for name, home in homes.items():
                if self.homes.get(name, home) != home:  # it moved: not a relay there
                    self.drop(name)
                self.homes[name] = home

    def forget(self, names: Iterable[str]) -> None:
        """Registrars that did not answer: ask them again where they are."""
        with self._lock:
            for name in names:
                self.drop(name)

    def drop(self, name: str) -> None:
        """(Holding the lock.) Forget `name`'s home and any relay role it had."""
        self.homes.pop(name, None)
        for home in [home for home, relay in self.relays.items() if relay == name]:
            del self.relays[home]


def _forget_in_child() -> None:
    global _PROCESS  # one key per process
    _PROCESS = uuid.uuid4().hex
    DESK.forget_in_child()


fork.after_fork_in_child("the status desk", _forget_in_child)
