"""The consumer side of a registrar actor, what it holds: its client records, kept or forgotten.

```
 answers.py keep ──► held(id, on_status): its answer's epoch, its status callback
                      ──► publish_target: the status desk runs it without this mailbox
 SetStatusCallback ──► on_set_status_callback ──► publish_target
 Revoke ──► on_revoke ──┐ held back (flights.py `parked`) while the answer they are
 ResponseUpdated ───────┤ about is on its way; then: forget | the new response
 a release (releases.py), a withdrawn call or an answer not kept (answers.py), a lost id
 (reconciling.py), a restored call given up (restoring.py)
   ──► forget(id): the record, its status callback, its desk entry   (the one place);
       its QueryForgotten if it was answered or restored (a CatalogRestored listed it)
 OpenClient ──► client(target, server): its client actor, started on first use
```

A client record is one query this registrar holds (`ClientRecord`); a dependency's record
names the resource of this registrar that owns it (rule 5). The records themselves live
in the catalog; this role owns what goes with them in memory.
"""

from __future__ import annotations

import pykka

from rr_actors._core.directory import Reply
from rr_actors._registrar import outcomes
from rr_actors._registrar.calls import DueAnswers
from rr_actors._registrar.endpoints import ClientActor, Clients
from rr_actors._registrar.fanout import DESK, StatusTargets
from rr_actors._registrar.flights import Flights
from rr_actors._registrar.messages import (
    ListClientQueries,
    OpenClient,
    ResponseUpdated,
    Revoke,
    SetStatusCallback,
)
from rr_actors._registrar.state import Shared
from rr_actors._types import StatusCallback
from rr_actors.errors import UnknownQueryError

__all__ = ["Holdings"]


class Holdings:
    """The queries this registrar holds at servers: what goes with their records.

    Attributes:
        clients: its client actors (shared with its handle, which looks them up).
        status_callbacks: query id -> the client status callback of that query.
        targets: what the status desk of this process reads of it (`fanout.py`): the
            ids with a status callback that a status reaches without this mailbox.
        epoch: how many `Reconcile` lists this registrar has built (`new_epoch`).
        answered_in: query id -> the `epoch` in which its answer was recorded (ids
            answered before the first list, or restored, have none: 0).
        restored: the ids of the records a restore gave it, answered or not (a call in
            flight when the last run died): its `CatalogRestored` listed them.
    """

    def __init__(self, shared: Shared, flights: Flights, due: DueAnswers, clients: Clients) -> None:
        self.registrar = shared
        self.flights = flights
        self.clients = clients
        self.status_callbacks: dict[str, StatusCallback] = {}
        self.targets = StatusTargets(shared.name, shared.events, due)
        DESK.serve(shared.peer, self.targets)
        self.epoch = 0
        self.answered_in: dict[str, int] = {}
        self.restored = set(shared.catalog.clients)

    # -- holding and forgetting queries -------------------------------------------------

    def held(self, query_id: str, on_status: StatusCallback | None) -> None:
        """`query_id`'s answer was recorded now (in this `epoch`), with its status
        callback (if any)."""
        self.answered_in[query_id] = self.epoch  # (a reconcile's list left before?)
        if on_status is not None:
            self.status_callbacks[query_id] = on_status
            self.publish_target(query_id)

    def forget(self, query_id: str, *, commit: bool = True, reason: str | None = "unload") -> None:
        """Forget a query this registrar held: its record and its status callback.

        With `commit=False` the caller commits (once, after forgetting several).
        `reason` is what its `QueryForgotten` says, published (before the commit) for a
        record whose holding was told: one answered here (`held`: its `CallAnswered`),
        or one a restore listed (`CatalogRestored`), answered or not (issue 40: a
        restored call in flight was dropped unannounced). `None`: the caller published it.
        """
        record = self.registrar.catalog.clients.get(query_id)
        if record is not None:
            told = query_id in self.answered_in or query_id in self.restored
            self.restored.discard(query_id)
            if told and reason is not None:
                outcomes.forgotten(self.registrar, record.query, reason)
            self.registrar.catalog.remove_client(query_id)
            self.status_callbacks.pop(query_id, None)
            self.targets.entries.pop(query_id, None)
            self.answered_in.pop(query_id, None)
            if commit:
                self.registrar.commit()

    def callback_of(self, query_id: str) -> StatusCallback | None:
        """The client status callback of query `query_id`, if it has one."""
        return self.status_callbacks.get(query_id)

    def publish_target(self, query_id: str) -> None:
        """Let the status desk of this process run `query_id`'s callback without this
        mailbox (`fanout.py`): a loaded query with a callback that is not a dependency
        (a dependency's status climbs from here, on this actor)."""
        record = self.registrar.catalog.clients.get(query_id)
        callback = self.status_callbacks.get(query_id)
        if record is None or callback is None or record.parent is not None or not record.loaded:
            self.targets.entries.pop(query_id, None)
        else:
            self.targets.entries[query_id] = (record.query, callback)

    # -- the epochs of `Reconcile` lists (`reconciling.py`) -----------------------------

    def new_epoch(self) -> int:
        """A `Reconcile` list leaves now: its number (answers recorded from now on
        came after it)."""
        self.epoch += 1
        return self.epoch

    def answered_before(self, query_id: str, epoch: int) -> bool:
        """Whether `query_id`'s answer was recorded before the list of `epoch` left."""
        return self.answered_in.get(query_id, 0) < epoch

    # -- notices from its providers -----------------------------------------------------

    def on_revoke(self, message: Revoke, _reply: Reply) -> None:
        if self.flights.parked(message):
            return
        for query_id in message.query_ids:
            self.forget(query_id, commit=False, reason="revoked")
        self.registrar.commit()

    def on_response_updated(self, message: ResponseUpdated, reply: Reply) -> None:
        if self.flights.parked(message):
            return
        for query_id in message.query_ids:
            self.registrar.catalog.client_loaded(query_id, message.response)
            if query_id in self.targets.entries:  # (its query says the new response)
                self.publish_target(query_id)
        self.registrar.commit()
        reply.set_result(None)

    # -- operations the handle asks for -------------------------------------------------

    def on_set_status_callback(self, message: SetStatusCallback, reply: Reply) -> None:
        if message.query_id not in self.registrar.catalog.clients:
            raise UnknownQueryError(f"unknown or released query id {message.query_id!r}")
        self.status_callbacks[message.query_id] = message.callback
        self.publish_target(message.query_id)
        reply.set_result(None)

    def on_list_client_queries(self, _message: ListClientQueries, reply: Reply) -> None:
        reply.set_result([r.query for r in self.registrar.catalog.clients.values() if r.loaded])

    def on_open_client(self, message: OpenClient, reply: Reply) -> None:
        reply.set_result(self.client(message.target_rr, message.server))

    def client(self, target_rr: str, server: str) -> pykka.ActorRef[ClientActor]:
        """The client actor for `target_rr/server`, started on first use (thesis 4.3.3)."""
        assert self.registrar.ref is not None
        return self.clients.start(self.registrar.ref, self.registrar.name, target_rr, server)

    def stop_clients(self) -> None:
        self.clients.stop_all()
