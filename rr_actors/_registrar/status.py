"""Status notifications, climbing every dependency path to the top (rule 9, thesis 4.2.4).

```
 send_status(id) ──► notify(resource): server's on_status once ──► the consumer
                       registrars, in one pass per process (`fanout.py`: the desk runs
                       the callbacks of plain ids there) ──► on_status_notice, for the
                       others: each client's callback, and for a dependency,
                       notify(its parent resource) ──► ... top
 acknowledgements: counted where they arrive (SharedJoin), the last one answers the sender
```

A `FATAL` its provider sends about a resource marks it `failed` in the catalog first
(`Catalog.mark_failed`, stored): no equal request matches it any more, a new call loads
a new resource, and the dead one stays with its consumers until they release it. A
`FATAL` that climbs from a dependency does not mark the resources above it: their
provider hears it (`on_status`) and decides, repairs it (the mission's robot manager
restarts a motor driver) or sends `FATAL` about it itself.

A `send_status` is one event (a UUID): a callback reached twice through a diamond of
dependencies runs once. Callbacks run on worker threads, so a callback may call `call`,
`unload` or `send_status` on any registrar without deadlock.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import time
import uuid
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rr_actors import events
from rr_actors._catalog import Resource
from rr_actors._core.directory import DIRECTORY, LocalPeer, Reply
from rr_actors._core.loops import OnLoop
from rr_actors._core.replies import CallbackReply, SharedJoin
from rr_actors._registrar.fanout import DESK, Routes, process
from rr_actors._registrar.messages import SendStatus, StatusBatch, StatusNotice
from rr_actors._registrar.state import NO_REPLY, Shared, consumers_by_origin
from rr_actors._types import Query, Status, StatusCallback, StatusUpdate
from rr_actors.errors import ConfigError, RrError

if TYPE_CHECKING:
    from rr_actors._registrar.flights import Flights
    from rr_actors._registrar.holdings import Holdings

__all__ = ["StatusRelay"]

logger = logging.getLogger("rr_actors")

_SEEN_EVENTS = 4096  # (event, resource) pairs remembered to run each callback once


class StatusRelay:
    """Delivers statuses: this registrar's own, and those passing through it."""

    def __init__(self, shared: Shared, flights: Flights, holdings: Holdings) -> None:
        self.registrar = shared
        self.flights = flights
        self.holdings = holdings
        self.seen_events: collections.OrderedDict[tuple[str, str], None] = collections.OrderedDict()
        self.routes = Routes()

    def on_send_status(self, asked: SendStatus, reply: Reply) -> None:
        query_id, status, message = asked.query_id, asked.status, asked.message
        shared = self.registrar
        resource = shared.catalog.resource_of(query_id)
        update = StatusUpdate(query_id, status, message, f"{shared.name}/{resource.server}")
        event = str(uuid.uuid4())
        told = (
            (events.StatusSent(shared.name, query_id, status, message, event),)
            if shared.events.active
            else ()
        )
        if status is Status.FATAL and not resource.failed:
            # Dead: no equal request matches it any more (rule 1), before anyone hears
            # of it; durable as a load is (a write that fails stays pending in memory),
            # with its StatusSent in the same write.
            shared.catalog.mark_failed(resource.id)
            if shared.commit(*told) is not None:
                shared.publish(*told)
        else:
            shared.publish(*told)
        refused: list[ConfigError] = []  # (parts that could not be sent: too large)

        def then() -> None:  # (the thread of the last acknowledgement)
            if refused:
                reply.set_error(refused[0])
            else:
                reply.set_result(None)

        self.notify(resource, update, event, query_id, then, refused=refused)

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
    ) -> None:
        """Run this server's `on_status` once and pass the status on to every consumer.

        `hop` is the number of registrars the notices reach on the way from the sender
        (its own consumers are hop 1); `sent_at` is when the status was sent (wall clock).
        A notice that cannot be sent at all (over its receiver's `max_message_bytes`) is
        logged and added to `refused` (if given): it is not a consumer gone, it is a
        status lost, and its sender must hear of it.

        `then()` runs once every callback and consumer on the way acknowledged, on the
        thread of the last acknowledgement (a reader thread, a worker, another registrar's
        actor, or this one): it must not touch this actor's state, and must come back
        through the mailbox (`Shared.come_back`) if it has to.
        """
        key = (event, resource.id)
        if key in self.seen_events:
            then()
            return
        self.seen_events[key] = None
        if len(self.seen_events) > _SEEN_EVENTS:
            self.seen_events.popitem(last=False)
        join = SharedJoin(then)  # acknowledgements: no trip back through this mailbox
        sent = time.time() if sent_at is None else sent_at
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
                server.on_status, query, dataclasses.replace(update, query_id=query_id), join
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
        )  # (each part sent gets its own reply)
        if in_process:
            DESK.deliver(batch, join, None, (self.registrar.name, self.flights.redeliver))
        for relay, parts, batched in self.routes.plan(elsewhere):
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
        join: SharedJoin,
        refused: list[ConfigError] | None = None,
    ) -> None:
        """Send `batch`'s status to registrar `origin` alone, as a `StatusNotice`."""
        done = join.add()
        routes = self.routes

        def answered(_value: Any, error: BaseException | None) -> None:
            if error is not None:
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
                )
            )
        except RrError as exc:
            reply.set_error(exc)

    def send_batch(
        self,
        relay: str,
        batch: StatusBatch,
        join: SharedJoin,
        refused: list[ConfigError] | None = None,
    ) -> None:
        """Send `batch` to registrar `relay` (any thread); its answer completes a part of
        `join`. Sent to a relay that fails, each part goes again to its own registrar (the
        desk there delivers what had reached it once)."""
        done = join.add()
        routes = self.routes

        def answered(value: Any, error: BaseException | None) -> None:
            if error is None:
                if isinstance(value, dict):
                    routes.learn(value)
            else:
                routes.forget([relay, *(origin for origin, _ in batch.parts)])
                if batch.parts != ((relay, batch.parts[0][1]),):  # (not its own part alone)
                    for part in batch.parts:
                        self.send_batch(part[0], batch.part((part,), NO_REPLY), join, refused)
                else:
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
        """A status part was not delivered to `target` (any thread). One gone is its death
        watch's business; one that could not be sent (a `ConfigError`: over its receiver's
        `max_message_bytes`) is a status lost: logged, and told its sender (`refused`)."""
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
        self, callback: StatusCallback, query: Query, update: StatusUpdate, join: SharedJoin
    ) -> None:
        """Run a status callback on a worker thread (a coroutine one: on its loop); its
        part of `join` is done after it."""
        done = join.add()
        if isinstance(callback, OnLoop):
            callback.submit(query, update, then=lambda _error: done(), key=query.id)
            return

        def run() -> None:
            try:
                callback(query, update)
            except Exception:
                logger.exception("status callback for %s raised", query.id)
            finally:
                done()

        try:
            self.registrar.workers.submit(run)
        except RuntimeError:  # no thread could start: skip the callback, keep serving
            logger.exception("no worker thread for the status callback of %s", query.id)
            done()

    def on_status_batch(self, batch: StatusBatch, reply: Reply) -> None:
        """A relay: deliver a status to the consumer registrars of this process in one
        pass; answer (once) with the process each one reached is in."""
        homes: dict[str, str] = {self.registrar.name: process()}
        join = SharedJoin(lambda: reply.set_result(homes))
        DESK.deliver(batch, join, homes, (self.registrar.name, self.flights.redeliver))
        join.seal()

    def on_status_notice(self, message: StatusNotice, reply: Reply) -> None:
        """Consumer side: run the client callbacks, climb to the dependent resources."""
        if self.flights.parked(message):
            return
        catalog = self.registrar.catalog
        join = SharedJoin(lambda: reply.set_result(None))
        for query_id in message.query_ids:
            record = catalog.clients.get(query_id)
            if record is None:
                continue
            update = StatusUpdate(query_id, message.status, message.message, message.source)
            if self.registrar.events.active:
                latency = max(0.0, time.time() - message.sent_at)
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
            callback = self.holdings.callback_of(query_id)
            if callback is not None:
                self.run_callback(callback, record.query, update, join)
            if record.parent is not None and record.parent in catalog.resources:
                parent = catalog.resources[record.parent]
                self.notify(
                    parent,
                    update,
                    message.event,
                    None,
                    join.add(),
                    hop=message.hop + 1,
                    sent_at=message.sent_at,
                )
        join.seal()
