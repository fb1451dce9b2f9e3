"""Status notifications: sent, fanned out in one pass per process, climbing every dependency
path to the top (rule 9, thesis 4.2.4).

```
 send_status(id) ─► StatusRelay.notify(resource): a FATAL marks it failed first; its
   server's on_status once (on the Runner, never given up on); then its consumer
   registrars, by process (Routes.plan):
   this process ──────────► DESK.deliver(parts), on this actor's thread
   another process, known ─► one StatusBatch to that process's relay
   not known yet ─────────► a StatusBatch to the consumer (its answer says where it is)
 DESK.deliver, per consumer registrar of its process (StatusTargets)
   an id with a callback, loaded, not a dependency ─► the callback, on the Runner
   any other id ─► a StatusNotice ─► on_status_notice ─► callbacks; a dependency ─►
     notify(its parent resource) ─► ... to the top
 acknowledgements: one SharedJoin per status; one sent to another process waits in
   Unacknowledged until acknowledged; each answer to that id's Unload carries them
```

Why a `FATAL` marks only its own resource, how each status reaches an id once, and how
the `Runner` orders, coalesces and gives up on callbacks: docs/explanation/inside.md,
"Statuses".
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import heapq
import logging
import weakref
from collections.abc import Callable, Iterable
from typing import Any

from rr_actors import events
from rr_actors._catalog import ClientRecord, Resource
from rr_actors._core import hlc, runtime, traces
from rr_actors._core.bus import Publisher
from rr_actors._core.directory import DIRECTORY, LocalPeer, Reply
from rr_actors._core.loops import OnLoop
from rr_actors._core.replies import CallbackReply, SharedJoin, waited, when_waiting
from rr_actors._core.workers import Job, Workers
from rr_actors._platform import forkserver
from rr_actors._registrar.calls import DueAnswers
from rr_actors._registrar.consumer import ConsumerRecord
from rr_actors._registrar.messages import SendStatus, StatusBatch, StatusNotice, StatusOnItsWay
from rr_actors._registrar.state import NO_REPLY, consumers_by_origin
from rr_actors._types import Query, Status, StatusCallback, StatusDelivery, StatusUpdate
from rr_actors.errors import ConfigError, RrError, UnknownQueryError

logger = logging.getLogger("rr_actors")


_SEEN_EVENTS = 4096  # (event, resource) pairs remembered to run each callback once


class StatusRecord(ConsumerRecord):
    """The registrar's record as its status relay and the parts above see it."""

    unacked: Unacknowledged  # (an `Unload`'s answer carries those of its id: provider.py)
    status: StatusRelay


class StatusRelay:
    def __init__(self, registrar: StatusRecord) -> None:
        self.registrar = registrar
        self.seen_events: collections.OrderedDict[tuple[str, str], None] = collections.OrderedDict()
        self.routes = Routes(registrar.unacked)

    def on_send_status(self, asked: SendStatus, reply: Reply) -> None:
        query_id, status, message = asked.query_id, asked.status, asked.message
        shared = self.registrar
        try:
            resource = shared.catalog.resource_of(query_id)
        except UnknownQueryError:
            held = shared.catalog.client(query_id)
            if held is None:
                raise
            raise UnknownQueryError(  # (a consumer's own id: only its provider sends)
                f"query id {query_id!r} is one {shared.name!r} holds at "
                f"{held.query.serving_rr}/{held.query.server}, not one it serves: only the "
                f"provider, {held.query.serving_rr!r}, sends statuses about it"
            ) from None
        update = StatusUpdate(query_id, status, message, f"{shared.name}/{resource.server}")
        event = runtime.new_id()
        told = (
            (events.StatusSent(shared.name, query_id, status, message, event, asked.patience),)
            if shared.events.active
            else ()
        )
        if status is Status.FATAL and not resource.failed:
            # no equal request matches it any more (rule 1), written with its StatusSent
            shared.catalog.mark_failed(resource.id)
            if shared.commit(*told) is not None:
                shared.publish(*told)
        else:
            shared.publish(*told)
        refused: list[ConfigError] = []  # (parts that could not be sent: too large)
        gave_up: list[str] = []  # (consumer ids whose callbacks were given up on)
        direct = tuple(resource.consumers)
        deadline = _deadline(asked.patience)

        def then() -> None:  # (the thread of the last acknowledgement)
            if refused:
                reply.set_error(refused[0])
            else:
                lost = dict.fromkeys(gave_up)  # (in order, each once; a set's lookups)
                reached = tuple(q for q in direct if q not in lost)  # (not given up on)
                reply.set_result(StatusDelivery(reached, tuple(lost)))
                if shared.events.active:  # (stamped on its actor: its process, while it lives)
                    told = (shared.name, query_id, event, reached, tuple(lost))
                    back = shared.come_back(lambda *_: shared.publish(events.StatusAnswered(*told)))
                    back.set_result(None)

        self.notify(
            resource,
            update,
            event,
            query_id,
            then,
            refused=refused,
            gave_up=gave_up,
            deadline=deadline,
        )

    def notify(
        self,
        resource: Resource,
        update: StatusUpdate,
        event: str,
        own_query_id: str | None,
        then: Callable[[], None],
        *,
        hop: int = 1,
        sent_at: float | None = None,
        refused: list[ConfigError] | None = None,
        gave_up: list[str] | None = None,
        deadline: float | None = None,
    ) -> None:
        """Run this server's `on_status` once and pass the status on to every consumer.
        `hop`: registrars from the sender (its consumers: 1); `sent_at`: wall clock. A notice
        over its receiver's `max_message_bytes` is logged, into `refused`; a callback not
        returned by `deadline` (monotonic) is given up on (`gave_up`). `then()` runs once all
        acknowledged, on the last one's thread (`Shared.come_back` to touch this actor)."""
        key = (event, resource.id)
        if key in self.seen_events:
            then()
            return
        self.seen_events[key] = None
        if len(self.seen_events) > _SEEN_EVENTS:
            self.seen_events.popitem(last=False)
        # (acknowledgements: no trip back through this mailbox)
        join = _Join(then, [] if gave_up is None else gave_up)
        sent = runtime.wall() if sent_at is None else sent_at
        server = self.registrar.servers.get(resource.server)
        query_id = own_query_id or next(iter(resource.consumers), resource.id)
        if server is not None and server.on_status is not None:
            query = Query(
                query_id,
                resource.server,
                self.registrar.name,
                resource.consumers.get(query_id, self.registrar.name),
                resource.request,
                resource.response,
            )
            self.run_callback(
                server.on_status,
                query,
                dataclasses.replace(update, query_id=query_id),
                join,
                resource.id,
            )
        in_process: list[tuple[str, tuple[str, ...]]] = []
        elsewhere: list[tuple[str, tuple[str, ...]]] = []
        for part in consumers_by_origin(resource).items():
            try:
                local = type(DIRECTORY.lookup(part[0])) is LocalPeer
            except RrError:  # gone: nothing to deliver
                continue
            (in_process if local else elsewhere).append(part)
        batch = StatusBatch(
            tuple(in_process),
            update.status,
            update.message,
            update.source,
            event,
            NO_REPLY,
            hop,
            sent,
            None if deadline is None else max(0.0, deadline - runtime.monotonic()),
        )  # (each part sent gets its own reply)
        if in_process:
            DESK.deliver(batch, join, None, (self.registrar.name, self.registrar.redeliver))
        for relay, parts, batched in self.routes.plan(elsewhere):
            self.registrar.unacked.leaving(parts, batch, relay)
            if batched:
                self.send_batch(relay, batch.part(parts, NO_REPLY), join, refused)
            else:
                self.send_notice(relay, parts[0][1], batch, join, refused)
        join.seal()

    def send_notice(
        self,
        origin: str,
        query_ids: tuple[str, ...],
        batch: StatusBatch,
        join: _Join,
        refused: list[ConfigError] | None = None,
    ) -> None:
        done = join.add()
        routes = self.routes
        unacked = self.registrar.unacked

        def answered(value: Any, error: BaseException | None) -> None:
            unacked.answered(((origin, query_ids),), batch.event)
            if error is None and isinstance(value, tuple):
                join.gave_up.extend(value)
            elif error is not None:
                routes.forget([origin])  # (ask it where it is again)
                self.not_sent(origin, batch, error, refused)
            done()

        reply = CallbackReply(answered)  # answered on the answering thread
        try:
            DIRECTORY.lookup(origin).tell(
                StatusNotice(
                    query_ids,
                    batch.status,
                    batch.message,
                    batch.source,
                    batch.event,
                    reply,
                    batch.hop,
                    batch.sent_at,
                    batch.patience,
                )
            )
        except RrError as exc:
            reply.set_error(exc)

    def send_batch(
        self,
        relay: str,
        batch: StatusBatch,
        join: _Join,
        refused: list[ConfigError] | None = None,
    ) -> None:
        """Send `batch` to registrar `relay` (any thread), a part of `join` and of `unacked`; a
        relay that fails: each part goes again to its own registrar."""
        done = join.add()
        routes = self.routes
        unacked = self.registrar.unacked

        def answered(value: Any, error: BaseException | None) -> None:
            if error is None:
                unacked.answered(batch.parts, batch.event)
                if isinstance(value, tuple):  # (homes, the ids given up on)
                    routes.learn(value[0])
                    join.gave_up.extend(value[1])
            else:
                routes.forget([relay, *(origin for origin, _ in batch.parts)])
                if batch.parts != ((relay, batch.parts[0][1]),):  # (not its own part alone)
                    for part in batch.parts:  # (still unacknowledged: each its own answer)
                        self.send_batch(part[0], batch.part((part,), NO_REPLY), join, refused)
                else:
                    unacked.answered(batch.parts, batch.event)
                    self.not_sent(relay, batch, error, refused)
            done()

        reply = CallbackReply(answered)  # answered on the answering thread
        try:
            DIRECTORY.lookup(relay).tell(batch.part(batch.parts, reply))
        except RrError as exc:
            reply.set_error(exc)

    def not_sent(
        self,
        target: str,
        batch: StatusBatch,
        error: BaseException,
        refused: list[ConfigError] | None,
    ) -> None:
        """A status part was not delivered to `target` (any thread): one gone is its death
        watch's business; one too large is a status lost, logged and told (`refused`)."""
        if not isinstance(error, ConfigError):
            return
        logger.warning(
            "registrar %s: the %s status could not reach registrar %s: %s",
            self.registrar.name,
            batch.status.name,
            target,
            error,
        )
        if refused is not None:
            refused.append(error)

    def run_callback(
        self,
        callback: StatusCallback,
        query: Query,
        update: StatusUpdate,
        join: SharedJoin,
        resource_id: str,
    ) -> None:
        """Run a server's `on_status` on the process's status runner, in a lane per resource,
        never given up on (rule 9); its part of `join` is done after it."""
        lane = f"on_status\0{self.registrar.name}\0{resource_id}"
        call = _Call(callback, query, update, join.add(), lane=lane)
        if isinstance(callback, OnLoop):
            DESK.runner.on_loop(call)
        else:
            DESK.runner.run((call,))

    def on_status_batch(self, batch: StatusBatch, reply: Reply) -> None:
        """A relay: deliver a status to this process's consumer registrars; answer their homes."""
        homes: dict[str, str] = {self.registrar.name: process()}
        gave_up: list[str] = []
        join = _Join(lambda: reply.set_result((homes, tuple(gave_up))), gave_up)
        DESK.deliver(batch, join, homes, (self.registrar.name, self.registrar.redeliver))
        join.seal()

    def on_status_notice(self, message: StatusNotice, reply: Reply) -> None:
        """Consumer side: run the client callbacks (each id once a status), climb up."""
        if self.registrar.flights.parked(message):
            return
        catalog = self.registrar.catalog
        gave_up: list[str] = []
        join = _Join(lambda: reply.set_result(tuple(gave_up)), gave_up)
        deadline = _deadline(message.patience)
        records: dict[str, ClientRecord | None] = {}

        def call_of(query_id: str) -> _Call | None:  # (under the desk's lock: `reach`)
            record = records[query_id] = catalog.client(query_id)
            if record is None:
                return None
            update = StatusUpdate(query_id, message.status, message.message, message.source)
            active = self.registrar.events.active
            if active:
                latency = max(0.0, runtime.wall() - message.sent_at)
                self.registrar.events.publish(
                    events.StatusDelivered(
                        self.registrar.name,
                        query_id,
                        message.status,
                        message.hop,
                        latency,
                        message.event,
                    )
                )
            callback = self.registrar.holdings.callback_of(query_id)
            # (on the callback's thread or loop: the publisher itself, not the turn's)
            told = (
                (self.registrar.published, self.registrar.name, message.event) if active else None
            )
            if callback is None:
                return None
            return _Call(callback, record.query, update, join.add(), told, deadline, gave_up)

        reached = DESK.reach(message.event, message.query_ids, call_of)
        DESK.arrived(self.registrar.peer, message)  # (after: its callbacks are queued)
        for query_id in reached:
            record = records[query_id]
            if record is None:
                continue
            update = StatusUpdate(query_id, message.status, message.message, message.source)
            climb = self.registrar.config.steps.climb  # (a copy passed in: `config.steps`)
            if climb is not None:
                above = [
                    catalog.resources[r]
                    for r in climb(record.parent, catalog.resources, message.status)
                    if r in catalog.resources
                ]
            elif record.parent is not None and record.parent in catalog.resources:
                above = [catalog.resources[record.parent]]
            else:
                above = []
            for parent in above:
                self.notify(
                    parent,
                    update,
                    message.event,
                    None,
                    join.add(),
                    hop=message.hop + 1,
                    sent_at=message.sent_at,
                    gave_up=gave_up,
                    deadline=deadline,
                )
        join.seal()


# -- the fan-out -----------------------------------------------------------------------


SLICE = 0.05
"""Seconds a status callback may run before the callbacks of other ids queued behind it go
on without it, on another worker thread (wall clock)."""

_LINGER = 1.0
"""Seconds the runner's watchdog stays after the last callback ended."""

_HOMES = 4_096
"""Consumer registrars whose process a provider remembers (more: it learns anew)."""

_SEEN = 16_384
"""(event, query id) pairs a desk remembers, to deliver each once."""


def process() -> str:
    """This process's key in the answers to status batches (a new one after a fork)."""
    return DESK.key


Parts = tuple[tuple[str, tuple[str, ...]], ...]
"""(consumer registrar, its query ids) of one status, one entry per registrar."""


class StatusTargets:
    """What the desk reads of one registrar: the ids a status reaches without its mailbox
    (`entries`: id -> its query and callback, written by its `Holdings` only), and, per id,
    the notices a desk sent to its mailbox that have not reached it yet (`on_way`: in its
    mailbox or parked behind an answer; while any, that id's next status follows them)."""

    __slots__ = ("__weakref__", "_sent", "due", "entries", "events", "name", "on_way")

    def __init__(self, name: str, published: Publisher[events.Event], due: DueAnswers) -> None:
        self.name = name
        self.events = published
        self.due = due
        self.entries: dict[str, tuple[Query, StatusCallback]] = {}
        self.on_way: dict[str, int] = {}  # (the desk's lock)
        self._sent: dict[int, StatusNotice] = {}  # id(notice) -> those notices

    def sending(self, notice: StatusNotice) -> None:
        """(Holding the desk's lock.) `notice` goes to this registrar's mailbox now."""
        self._sent[id(notice)] = notice
        for query_id in notice.query_ids:
            self.on_way[query_id] = self.on_way.get(query_id, 0) + 1

    def arrived(self, notice: StatusNotice) -> None:
        """(Holding the desk's lock.) `notice` reached its ids (its callbacks are queued)."""
        if self._sent.pop(id(notice), None) is not notice:  # (not one a desk sent)
            return
        for query_id in notice.query_ids:
            left = self.on_way.pop(query_id, 1) - 1
            if left:
                self.on_way[query_id] = left


class _Join(SharedJoin):
    """A status's join in this process, and the consumer ids given up on in it (any thread)."""

    __slots__ = ("gave_up",)

    def __init__(self, then: Callable[[], None], gave_up: list[str]) -> None:
        super().__init__(then)
        self.gave_up = gave_up


def _counted(join: _Join, done: Callable[..., None]) -> Callable[[Any, Any], None]:

    def answered(value: Any, error: BaseException | None) -> None:
        if error is None and isinstance(value, tuple):
            join.gave_up.extend(value)
        done()

    return answered


class _Call:
    """One status callback to run, and the part of its batch's join it completes.
    `done` runs once (`settle`): as the callback returns, or given up on at `deadline`
    (monotonic; `None`: never). `merged`: the calls coalesced into it, `wake` their earliest
    deadline; `told`: what its `StatusHandled` needs (while events are published)."""

    __slots__ = (
        "began",
        "callback",
        "deadline",
        "done",
        "gave_up",
        "given_up",
        "lane",
        "merged",
        "opened",
        "query",
        "seq",
        "settled",
        "told",
        "update",
        "wake",
    )

    def __init__(
        self,
        callback: StatusCallback,
        query: Query,
        update: StatusUpdate,
        done: Callable[..., None],
        told: tuple[Publisher[events.Event], str, str] | None = None,
        deadline: float | None = None,
        gave_up: list[str] | None = None,
        lane: str | None = None,
    ) -> None:
        self.callback = callback
        self.lane = query.id if lane is None else lane  # (its calls run one at a time)
        self.query = query
        self.update = update
        self.done = done
        self.told = told
        self.deadline = deadline
        self.wake = deadline
        self.gave_up = gave_up
        self.seq = 0  # its place in the runner's arrival order
        self.began = 0  # (a coroutine's) the stamp at which it was handed to its loop
        self.opened = 0  # the stamp at which it first let its lane go (`Runner._waits`)
        self.settled = False  # its `done` ran, or is about to
        self.given_up = False  # settled as given up on
        self.merged: list[_Call] = []

    def settle(self, giving_up: bool) -> list[Callable[..., None]]:
        """(Holding the runner's lock.) Settle it and those merged, once each: `done`s to call."""
        dones: list[Callable[..., None]] = []
        for call in (*sorted(self.merged, key=_arrival), self):  # (in arrival order)
            if call.settled:
                continue
            call.settled = True
            if giving_up:
                call.given_up = True
                if call.gave_up is not None:
                    call.gave_up.append(call.query.id)
            dones.append(call.done)
        self.merged = []
        self.wake = None
        return dones

    def overdue(self, now: float) -> bool:
        return not self.settled and self.deadline is not None and now >= self.deadline

    def merge(self, calls: Iterable[_Call]) -> None:
        for queued in calls:
            self.merged.append(queued)
            self.merged.extend(queued.merged)
            queued.merged = []
        self.wake = _earliest(self, *self.merged)

    def lapse(self, now: float) -> list[Callable[..., None]]:
        """(Holding the runner's lock.) Give up on it (and those merged) if past its deadline,
        else on each merged call past its own: the `done`s to call."""
        if self.wake is None or now < self.wake:
            return []
        if self.overdue(now):
            return self.settle(True)
        dones: list[Callable[..., None]] = []
        for call in self.merged:
            if call.overdue(now):
                dones.extend(call.settle(True))
        self.wake = _earliest(self, *self.merged)
        return dones

    def __call__(self) -> None:
        began = self.begins()
        # a trace of its own: its run's span (made of its StatusHandled), else no span
        own = traces.own_trace(self.own())
        try:
            self.callback(self.query, self.update)
        except BaseException:  # (a SystemExit too: logged, and its drainer goes on)
            logger.exception("status callback for %s raised", self.query.id)
        finally:
            traces.detach(own)
            self.handled(began)

    def begins(self) -> int:
        return hlc.CLOCK.now() if self.told is not None else 0

    def own(self) -> tuple[str, str, str] | None:
        """The run `traces.own_trace` makes current for its callback (`None`: no span)."""
        told = self.told
        return (told[2], told[1], self.query.id) if told is not None else None

    def handled(self, began: int) -> None:
        if self.told is not None:
            publisher, name, status_id = self.told
            publisher.publish(
                events.StatusHandled(
                    name, self.query.id, self.update.status, status_id, self.seq, began, self.opened
                )
            )


def _arrival(call: _Call) -> int:
    return call.seq


def _earliest(*calls: _Call) -> float | None:
    deadlines = [c.deadline for c in calls if not c.settled and c.deadline is not None]
    return min(deadlines, default=None)


def _settled(dones: Iterable[Callable[..., None]]) -> None:
    for done in dones:
        try:
            done()
        except Exception:  # (a join's part: it does not raise; a bug's trace if it did)
            logger.exception("a status acknowledgement raised")


def _deadline(patience: float | None) -> float | None:
    return None if patience is None else runtime.monotonic() + patience


class _Drainer:
    __slots__ = ("abandoned", "call", "job", "started")

    def __init__(self) -> None:
        self.abandoned = False  # done, or it overran `SLICE`: it takes no more calls
        self.job: Job | None = None
        self.call: _Call | None = None  # the call it runs now (its lane held for it)
        self.started = 0.0  # when that callback began (monotonic)


class Runner:
    """Runs this process's status callbacks in arrival order, each id's one at a time (a lane
    per id), on as few worker threads as keep them going; a watchdog gives up on one past
    `SLICE` or its deadline (docs/explanation/inside.md, "Statuses")."""

    def __init__(self) -> None:
        self._lock = runtime.Lock()
        self._lanes: dict[str, collections.deque[_Call]] = {}  # id -> its queued calls
        self._open: list[tuple[int, str]] = []  # heap: (its first call's seq, id) of open lanes
        self._holders: dict[str, _Drainer] = {}  # id -> the drainer that holds its lane
        self._running: dict[_Call, None] = {}  # calls in a callback (their lanes held or not)
        self._inside: set[_Drainer] = set()  # drainers in a callback, not given up
        self._drainers = 0  # drainers that take calls (not given up)
        self._arrived = 0  # calls queued so far (their `seq`)
        self._watching = False
        self._quiet_since = 0.0  # when the last callback ended with none running
        self._awaited: dict[_Call, None] = {}  # coroutine callbacks' calls not settled yet
        self._on_loop: dict[str, _Call] = {}  # id -> its coroutine call that holds its lane
        self._loop_lanes: dict[str, collections.deque[_Call]] = {}  # id -> queued behind it
        self._workers = Workers("status")

    def run(self, calls: Iterable[_Call]) -> None:
        """Queue `calls`; start a drainer if none is free. Behind a running callback its lane
        coalesces; behind one given up on, the call is given up on at once."""
        dones: list[Callable[..., None]] = []
        pending = False  # (a call behind a running callback, to give up on in time)
        with self._lock:
            for call in calls:
                self._arrived += 1
                call.seq = self._arrived
                query_id = call.lane
                lane = self._lanes.get(query_id)
                holder = self._holders.get(query_id)
                if holder is not None:  # (behind its running callback)
                    dones.extend(_queue_behind(self._lanes, call, holder.call))
                    pending = pending or (not call.settled and call.wake is not None)
                    continue
                if lane is not None:
                    lane.append(call)
                    continue
                self._lanes[query_id] = collections.deque((call,))
                heapq.heappush(self._open, (call.seq, query_id))
            start, watch = self._wanted(pending)
        self._kick(start, watch)
        _settled(dones)

    def on_loop(self, call: _Call) -> None:
        """Run a coroutine callback's `call` on its loop, each id's one at a time, coalesced
        behind its running call as on a thread (`_queue_behind`)."""
        dones: list[Callable[..., None]] = []
        with self._lock:
            self._arrived += 1  # (numbered with the threads' calls: `StatusHandled.arrived`)
            call.seq = self._arrived
            running = self._on_loop.get(call.lane)
            if running is not None:
                dones = _queue_behind(self._loop_lanes, call, running)
                start = None
                timed = not call.settled and call.wake is not None
            else:
                start = self._hold_on_loop(call)
                timed = call.deadline is not None
            watch = timed and not self._watching
            if watch:
                self._watching = True
        self._kick(False, watch)
        _settled(dones)
        if start is not None:
            self._submit(start)

    def _hold_on_loop(self, call: _Call) -> _Call:
        """(Holding the lock.) `call` holds its id's coroutine lane (watched for its deadline)."""
        self._on_loop[call.lane] = call
        if call.wake is not None:
            self._awaited[call] = None
        return call

    def _submit(self, call: _Call) -> None:
        callback = call.callback
        assert isinstance(callback, OnLoop)
        call.began = call.begins()  # (its lane is its: it begins as its loop takes it)
        callback.submit(
            call.query,
            call.update,
            then=functools.partial(self._returned, call),
            key=call.lane,
            waits=functools.partial(self._loop_waits, call),
            own=call.own(),
        )

    def _next_on_loop(self, call: _Call) -> _Call | None:
        """(Holding the lock.) `call` lets its id's coroutine lane go: the next call to submit."""
        query_id = call.lane
        if self._on_loop.get(query_id) is not call:
            return None
        del self._on_loop[query_id]
        lane = self._loop_lanes.get(query_id)
        if not lane:
            return None
        following = lane.popleft()
        if not lane:
            del self._loop_lanes[query_id]
        return self._hold_on_loop(following)

    def _loop_waits(self, call: _Call) -> None:
        """A coroutine callback's `call` waits for a registrar (`replies.let_go`): its id's next
        call may start beside it (it may be what it waits for)."""
        if not call.opened and call.told is not None:
            call.opened = hlc.CLOCK.now()
        with self._lock:
            following = self._next_on_loop(call)
        if following is not None:
            self._submit(following)

    def _returned(self, call: _Call, _error: BaseException | None) -> None:
        """A coroutine callback's `call` returned: publish, settle, submit its id's next call."""
        call.handled(call.began)
        with self._lock:
            self._awaited.pop(call, None)
            dones = call.settle(False)
            following = self._next_on_loop(call)
        _settled(dones)
        if following is not None:
            self._submit(following)

    def _wanted(self, pending: bool = False) -> tuple[bool, bool]:
        """(Holding the lock.) Whether to start a drainer, and the watchdog (counted now)."""
        start = bool(self._open) and self._drainers == len(self._inside)
        if start:
            self._drainers += 1
        watch = not self._watching and bool(self._open or self._inside or pending)
        if watch:
            self._watching = True
        return start, watch

    def _kick(self, start: bool, watch: bool) -> None:
        if watch:
            self._watch_start()
        if start:
            self._start()

    def _start(self) -> None:
        """Start one drainer (counted already): its calls are skipped if no thread can."""
        drainer = _Drainer()
        try:
            drainer.job = self._workers.submit(lambda: self._drain(drainer), quiet=True)
        except RuntimeError:
            logger.exception("no worker thread for status callbacks: they are skipped")
            skipped: list[Callable[..., None]] = []
            with self._lock:
                self._drainers -= 1
                if self._drainers == 0:  # nobody else will take them
                    for lane in self._lanes.values():
                        for call in lane:
                            skipped.extend(call.settle(False))
                    self._lanes.clear()
                    self._open.clear()
            _settled(skipped)

    def _take(self) -> _Call | None:
        if not self._open:
            return None
        _seq, query_id = heapq.heappop(self._open)
        lane = self._lanes[query_id]
        call = lane.popleft()
        if not lane:
            del self._lanes[query_id]
        return call

    def _let_go(self, drainer: _Drainer, call: _Call) -> None:
        query_id = call.lane
        if self._holders.get(query_id) is not drainer or drainer.call is not call:
            return
        del self._holders[query_id]
        lane = self._lanes.get(query_id)
        if lane:
            heapq.heappush(self._open, (lane[0].seq, query_id))

    def _waits(self, drainer: _Drainer, call: _Call) -> None:
        """`call`'s callback waits for a registrar (`replies.let_go`, any thread, repeatable):
        its lane opens, if its drainer still holds it."""
        if not call.opened and call.told is not None:
            call.opened = hlc.CLOCK.now()
        with self._lock:
            self._let_go(drainer, call)
            start, watch = self._wanted()
        self._kick(start, watch)

    def _drain(self, drainer: _Drainer) -> None:
        while True:
            with self._lock:
                if drainer.abandoned:
                    return
                call = self._take()
                if call is None:
                    drainer.abandoned = True
                    self._drainers -= 1
                    return
                drainer.call = call
                drainer.started = runtime.monotonic()
                self._holders[call.lane] = drainer
                self._running[call] = None
                self._inside.add(drainer)
            token = when_waiting(functools.partial(self._waits, drainer, call))
            try:
                call()
            finally:
                waited(token)
                with self._lock:
                    del self._running[call]
                    dones = call.settle(False)
                    self._inside.discard(drainer)
                    self._let_go(drainer, call)
                    if not self._inside:
                        self._quiet_since = runtime.monotonic()
                    # (given up: its thread ends; another takes the lane it opened)
                    start, watch = self._wanted() if drainer.abandoned else (False, False)
                _settled(dones)
                self._kick(start, watch)

    def _give_up(self, now: float) -> tuple[list[Callable[..., None]], bool]:
        """(Holding the lock.) Give up on running calls and queued calls of held lanes past their
        deadlines: their `done`s, and whether a deadline is still to come."""
        dones: list[Callable[..., None]] = []
        waiting = False
        for call in [*self._running, *self._awaited]:  # (running: on a thread, on a loop)
            dones.extend(call.lapse(now))
            if call.wake is None:
                self._awaited.pop(call, None)
            waiting = waiting or call.wake is not None
        held = [(d.call, self._lanes.get(q, ())) for q, d in self._holders.items()]
        held += [(c, self._loop_lanes.get(q, ())) for q, c in self._on_loop.items()]
        for running, lane in held:
            if running is None:
                continue
            stuck = running.given_up  # (what queued behind it waits no more)
            for call in lane:
                if call.settled:
                    continue
                dones.extend(call.settle(True) if stuck else call.lapse(now))
                waiting = waiting or call.wake is not None
        return dones, waiting

    def _watch_start(self) -> None:
        try:
            runtime.Thread(target=self._watch, name="rr-status-watchdog", daemon=True).start()
        except RuntimeError:  # callbacks then run unbounded until a later start works
            logger.exception("no thread to bound the time of status callbacks")
            with self._lock:
                self._watching = False

    def _watch(self) -> None:
        """The watchdog: every `SLICE`, give up drainers whose callback overran it and calls past
        their deadline; end after a second with nothing to do."""
        while True:
            runtime.sleep(SLICE)
            now = runtime.monotonic()
            overdue: list[_Drainer] = []
            with self._lock:
                dones, waiting = self._give_up(now)
                for drainer in list(self._inside):
                    if now - drainer.started >= SLICE:
                        overdue.append(drainer)
                        drainer.abandoned = True
                        self._drainers -= 1
                        self._inside.discard(drainer)
                start = bool(self._open) and self._drainers == len(self._inside)
                if start:
                    self._drainers += 1
                idle = not overdue and not self._inside and not self._open and not waiting
                ending = idle and now - self._quiet_since > _LINGER
                if ending:
                    self._watching = False
            _settled(dones)
            if ending:
                return
            for drainer in overdue:  # (its thread no longer counts in the pool)
                if drainer.job is not None:
                    drainer.job.abandon()
            if start:
                self._start()


def _queue_behind(
    lanes: dict[str, collections.deque[_Call]], call: _Call, running: _Call | None
) -> list[Callable[..., None]]:
    """(Holding the runner's lock.) Queue `call` in its id's lane behind its `running`
    callback, coalesced if it is a consumer's (a server's own `on_status` runs once per
    status, rule 9); given up on at once if that one was: the `done`s to call."""
    lane = lanes.get(call.lane)
    if lane is None:
        lane = lanes[call.lane] = collections.deque()
    if call.update.status is not Status.FATAL and call.deadline is not None:
        _coalesce(lane, call)
    lane.append(call)
    if running is not None and running.given_up:
        return call.settle(True)
    return []


def _coalesce(lane: collections.deque[_Call], call: _Call) -> None:
    """(Holding the runner's lock.) `call`, not a `FATAL`, replaces the queued calls of
    `lane` that are not `FATAL`s (merged into it); the `FATAL`s stay, in order."""
    kept = [queued for queued in lane if queued.update.status is Status.FATAL]
    if len(kept) == len(lane):
        return
    call.merge(
        queued for queued in lane if queued.update.status is not Status.FATAL and not queued.settled
    )
    lane.clear()
    lane.extend(kept)


class Desk:
    def __init__(self) -> None:
        self.targets: weakref.WeakKeyDictionary[LocalPeer, StatusTargets] = (
            weakref.WeakKeyDictionary()
        )
        self._lock = runtime.RLock()  # (a callback's acknowledgement may reach it again)
        self._seen: collections.OrderedDict[tuple[str, str], None] = collections.OrderedDict()
        self.runner = Runner()
        self.key = runtime.urandom(16).hex()  # this process's (`process`)

    def serve(self, peer: LocalPeer, targets: StatusTargets) -> None:
        with self._lock:
            self.targets[peer] = targets

    def deliver(
        self,
        batch: StatusBatch,
        join: _Join,
        homes: dict[str, str] | None,
        here: tuple[str, Callable[[Any], None]],
    ) -> None:
        """Deliver `batch`'s parts (on an actor thread) as parts of `join` (given up: in
        `join.gave_up`); `homes` gets each reached registrar's process; `here`: the registrar
        running this and its `dispatch` (its own ids skip its mailbox)."""
        patience = batch.patience
        deadline = _deadline(patience)
        for origin, ids in batch.parts:
            try:
                peer = DIRECTORY.lookup(origin)
            except RrError:  # gone: nothing to deliver (as a notice to it would fail)
                continue
            if type(peer) is not LocalPeer:  # (it moved to another process)
                self.forward(peer, batch, (origin, ids), join, homes)
                continue
            if homes is not None:
                homes[origin] = self.key
            targets = self.targets.get(peer)
            with self._lock:  # (what goes direct, what to its mailbox: one step, rule 9)
                slow = self.direct(targets, batch, ids, join, deadline) if targets else ids
                if not slow:
                    continue
                reply = CallbackReply(_counted(join, join.add()))
                notice = StatusNotice(
                    slow,
                    batch.status,
                    batch.message,
                    batch.source,
                    batch.event,
                    reply,
                    batch.hop,
                    batch.sent_at,
                    patience,
                )
                if targets is not None:
                    targets.sending(notice)
                try:
                    if origin != here[0]:
                        peer.tell(notice)
                except RrError as exc:
                    self.arrived(peer, notice)
                    reply.set_error(exc)
                    continue
            if origin == here[0]:  # (its own: handled now, on this thread)
                here[1](notice)

    def direct(
        self,
        targets: StatusTargets,
        batch: StatusBatch,
        ids: tuple[str, ...],
        join: _Join,
        deadline: float | None = None,
    ) -> tuple[str, ...]:
        """(Holding the lock.) Queue the callbacks of the ids `targets` has, not reached yet;
        return the others."""
        slow: list[str] = []
        ready: dict[str, tuple[Query, StatusCallback]] = {}
        entries, due, on_way = targets.entries, targets.due, targets.on_way
        if any(q in due or q in on_way for q in ids):  # (an earlier notice of them may wait
            return ids  # in its mailbox, or parked behind a due answer: this one follows)
        publish = targets.events.active
        for query_id in ids:
            entry = entries.get(query_id)
            if entry is None:
                slow.append(query_id)
            else:
                ready[query_id] = entry

        def call_of(query_id: str) -> _Call:  # (under the desk's lock: `reach`)
            query, callback = ready[query_id]
            if publish:
                targets.events.publish(
                    events.StatusDelivered(
                        targets.name,
                        query_id,
                        batch.status,
                        batch.hop,
                        max(0.0, runtime.wall() - batch.sent_at),
                        batch.event,
                    )
                )
            update = StatusUpdate(query_id, batch.status, batch.message, batch.source)
            told = (targets.events, targets.name, batch.event) if publish else None
            return _Call(callback, query, update, join.add(), told, deadline, join.gave_up)

        self.reach(batch.event, tuple(ready), call_of)
        return tuple(slow)

    def forward(
        self,
        peer: Any,
        batch: StatusBatch,
        part: tuple[str, tuple[str, ...]],
        join: _Join,
        homes: dict[str, str] | None,
    ) -> None:
        done = join.add()

        def answered(value: Any, error: BaseException | None) -> None:
            if error is None and isinstance(value, tuple):  # (homes, the ids given up on)
                if homes is not None:
                    homes.update(value[0])
                join.gave_up.extend(value[1])
            done()

        reply = CallbackReply(answered)
        try:
            peer.tell(batch.part((part,), reply))
        except RrError as exc:
            reply.set_error(exc)

    def reach(
        self, event: str, ids: tuple[str, ...], call_of: Callable[[str], _Call | None]
    ) -> tuple[str, ...]:
        """Those of `ids` that event `event` has not reached here yet, marked now and, in the
        same step, the callback call `call_of(id)` makes for each queued: a later status to
        one of them, marked on another thread (an `Unload`'s answer), queues behind it."""
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
            threads = []
            for call in filter(None, map(call_of, fresh)):
                if isinstance(call.callback, OnLoop):  # a coroutine: on its loop, no worker
                    self.runner.on_loop(call)
                else:
                    threads.append(call)
            if threads:
                self.runner.run(threads)
        return tuple(fresh)

    def arrived(self, peer: LocalPeer, notice: StatusNotice) -> None:
        """`notice`, handled by registrar `peer` (not parked), reached its ids: their next
        statuses may go direct again (`StatusTargets.on_way`)."""
        with self._lock:
            targets = self.targets.get(peer)
            if targets is not None:
                targets.arrived(notice)

    def forget_in_child(self) -> None:
        """In a forked child: the parent's registrars and threads are not here."""
        self._lock = runtime.RLock()
        self.targets = weakref.WeakKeyDictionary()
        self._seen = collections.OrderedDict()
        self.runner = Runner()
        self.key = runtime.urandom(16).hex()  # one key per process


DESK = runtime.process_state(Desk(), Desk)
"""This process's status desk."""


class Routes:
    """Where a provider sends statuses for other processes: `homes` (consumer -> process),
    `relays` (process -> its registrar taking batches, kept while it answers: order holds).
    Hints: a wrong one costs a forward; an id with statuses unacknowledged keeps their way."""

    def __init__(self, unacked: Unacknowledged) -> None:
        self.unacked = unacked
        self._lock = runtime.Lock()
        self.homes: dict[str, str] = {}
        self.relays: dict[str, str] = {}

    def plan(self, parts: Iterable[tuple[str, tuple[str, ...]]]) -> list[tuple[str, Parts, bool]]:
        """By process: (the relay, its parts, whether as a batch); a registrar of an unknown process
        or with statuses unacknowledged, a batch (there: rule 9); one alone there, a notice."""
        groups: dict[str, list[tuple[str, tuple[str, ...]]]] = {}
        planned: list[tuple[str, Parts, bool]] = []
        with self._lock:
            for part in parts:
                home, way = self.homes.get(part[0]), self.unacked.way(part[1])
                if way or home is None:
                    planned.append((way or part[0], (part,), True))
                else:
                    groups.setdefault(home, []).append(part)
            for home, members in groups.items():
                if len(members) == 1:
                    planned.append((members[0][0], (members[0],), False))
                else:
                    relay = self.relays.setdefault(home, members[0][0])
                    planned.append((relay, tuple(members), True))
        return planned

    def learn(self, homes: dict[str, str]) -> None:
        with self._lock:
            if len(self.homes) > _HOMES:  # (registrars come and go: start over)
                self.homes.clear()
                self.relays.clear()
            for name, home in homes.items():
                if self.homes.get(name, home) != home:  # it moved: not a relay there
                    self.drop(name)
                self.homes[name] = home

    def forget(self, names: Iterable[str]) -> None:
        with self._lock:
            for name in names:
                self.drop(name)

    def drop(self, name: str) -> None:
        self.homes.pop(name, None)
        for home in [home for home, relay in self.relays.items() if relay == name]:
            del self.relays[home]


class Unacknowledged:
    """Statuses sent on to consumer ids in other processes, by id, and where, until answered (an
    id's `Unload` answer carries its own: rule 9; `way`). Actor enters, answering threads clear."""

    def __init__(self) -> None:
        self._lock = runtime.Lock()
        self._of: dict[str, dict[str, tuple[StatusOnItsWay, str]]] = {}  # id -> event -> (it, to)

    def leaving(self, parts: Parts, batch: StatusBatch, to: str) -> None:
        status = batch.on_its_way()
        with self._lock:
            for _origin, ids in parts:
                for query_id in ids:
                    self._of.setdefault(query_id, {})[status.event] = (status, to)

    def way(self, query_ids: Iterable[str]) -> str:  # ("": none unacknowledged)
        with self._lock:  # (the registrar the last status unacknowledged to one was sent to)
            ways = [next(reversed(self._of[q].values()))[1] for q in query_ids if q in self._of]
        return ways[0] if ways else ""

    def answered(self, parts: Parts, event: str) -> None:
        with self._lock:
            for _origin, ids in parts:
                for query_id in ids:
                    waiting = self._of.get(query_id)
                    if waiting is not None:
                        waiting.pop(event, None)
                        if not waiting:
                            del self._of[query_id]

    def of(self, query_id: str) -> tuple[StatusOnItsWay, ...]:
        """The statuses still on their way to `query_id`, in the order they left (kept)."""
        with self._lock:
            return tuple(status for status, _to in self._of.get(query_id, {}).values())


forkserver.after_fork_in_child("the status desk", DESK.forget_in_child)
