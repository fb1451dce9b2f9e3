"""The consumer side of a registrar actor: the queries it holds at servers (its clients).

```
 caller thread ──Load──► provider          (calls.py: the call protocol)
      │  durable: Pending ──► on_pending: record written as pending, then the Load leaves
      ▼
 answer ──► ClientLoaded (plain) ─┐ due.outcomes, taken before each message (take_outcomes)
        └─► DurableLoaded ────────┤ (the mailbox): on_client_loaded: decide() ─► Action,
 failure/withdrawal ──► CallFailed ─┘ its step; answer waiting notices;
                                    on_call_failed: forget the record
 Revoke / ResponseUpdated ──► held back while the answer they are about is on its way

 in_flight: query id ──► InFlight(attempt, unsettled_at, parked)   (flight.py)
```

A client record is one query this registrar holds (`ClientRecord`); a dependency's record
names the resource of this registrar that owns it (rule 5). Releasing one is the one
place a record is forgotten (`forget`); giving an id back to a provider is
`messages.give_back`. A release its provider died during (it may or may not have run it)
is forgotten here and completed by the reconcile after the provider's restart, which no
longer lists the id (`unreleased`).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Iterable
from typing import Any

import pykka

from rr_actors._catalog import ClientRecord, ResourceState
from rr_actors._core.directory import Reply
from rr_actors._core.replies import Join
from rr_actors._registrar import outcomes
from rr_actors._registrar.calls import AttemptState, CallAttempt, DueAnswers
from rr_actors._registrar.display import ClientTexts
from rr_actors._registrar.endpoints import ClientActor, Clients
from rr_actors._registrar.fanout import DESK, StatusTargets
from rr_actors._registrar.flight import Action, InFlight, decide
from rr_actors._registrar.loading import check_picklable
from rr_actors._registrar.messages import (
    CallFailed,
    ClientLoaded,
    DurableLoaded,
    ListClientQueries,
    OpenClient,
    Pending,
    Release,
    ResponseUpdated,
    Revoke,
    SetStatusCallback,
    StatusNotice,
    Unload,
    give_back,
)
from rr_actors._registrar.state import NO_REPLY, Shared
from rr_actors._types import Query, StatusCallback
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
    UnknownQueryError,
)

__all__ = ["Consumer", "Listing", "Notice"]

logger = logging.getLogger("rr_actors")

Notice = StatusNotice | Revoke | ResponseUpdated
"""What a provider tells a consumer about queries it holds."""

GONE = (RegistrarUnavailableError, RegistrarStoppedError)
"""Errors of a provider that died or was stopped: what was sent may or may not have run."""


@dataclasses.dataclass(frozen=True)
class Listing:
    """What one `Reconcile` told a provider, as it was when the list left.

    Its answer ("the ids of the list I do not know") is about the catalog as it was
    then: only records that were answered before it left are settled by it.

    Attributes:
        held: the ids listed (client records, calls due, calls that failed as the
            provider died), sorted.
        due: of those, the calls whose answer was on its way.
        left_out: ids whose release failed as the provider died, not listed: the
            provider releases them (`Consumer.unreleased`).
        epoch: the list's number (`Consumer.epoch`); an answer recorded with this
            number or a later one came after the list left.
    """

    held: tuple[str, ...]
    due: frozenset[str]
    left_out: frozenset[str]
    epoch: int


class Consumer:
    """Holds this registrar's queries at servers, and what waits for their answers.

    Attributes:
        due: the query ids whose answers are on their way (shared with callers' threads).
        clients: its client actors (shared with its handle, which looks them up).
        status_callbacks: query id -> the client status callback of that query.
        targets: what the status desk of this process reads of it (`fanout.py`): the
            ids with a status callback that a status reaches without this mailbox.
        in_flight: query id -> what is known of its call in flight (`InFlight`: a
            durable attempt this actor answers after its commit, the provider of a call
            that failed as it died or stopped, the notices that overtook its answer).
        releasing: query ids whose `Unload` is on its way.
        unreleased: query id -> provider, of ids this registrar released whose `Unload`
            failed as the provider died or stopped (it may or may not have run it). Their
            records are forgotten; a `Reconcile` does not list them, so the provider
            releases any it still holds (its `unload` runs once) and none is reported
            `FATAL`. Held until such a `Reconcile` was answered.
        kept_for_retry: query id -> provider, of calls that failed as the provider died
            or stopped and that it still held when a `Reconcile` with it was answered
            since: a retry with the id finds it there. Never retried, the id is released
            by the provider's next `Reconcile` (which does not list it) or given back
            when this registrar stops (rule 12).
        epoch: how many `Reconcile` lists this registrar has built (`listing`).
        answered_in: query id -> the `epoch` in which its answer was recorded (ids
            answered before the first list, or restored, have none: 0).
        texts: makes its records' request display texts (`display.py`).
    """

    def __init__(
        self,
        shared: Shared,
        due: DueAnswers,
        redeliver: Callable[[Any], None],
        clients: Clients,
    ) -> None:
        self.registrar = shared
        self.due = due
        self.redeliver = redeliver
        self.clients = clients
        self.status_callbacks: dict[str, StatusCallback] = {}
        self.targets = StatusTargets(shared.name, shared.events, due)
        DESK.serve(shared.peer, self.targets)
        self.in_flight: dict[str, InFlight] = {}
        self.releasing: set[str] = set()
        self.unreleased: dict[str, str] = {}
        self.kept_for_retry: dict[str, str] = {}
        self.epoch = 0
        self.answered_in: dict[str, int] = {}
        self.texts = ClientTexts(shared)

    # -- the calls in flight (`flight.py`) -------------------------------------------

    def flight(self, query_id: str) -> InFlight:
        """The in-flight record of `query_id`, made if it has none."""
        flight = self.in_flight.get(query_id)
        if flight is None:
            flight = self.in_flight[query_id] = InFlight()
        return flight

    def landed(self, query_id: str) -> None:
        """Forget the in-flight record of `query_id` if nothing is left of it."""
        flight = self.in_flight.get(query_id)
        if flight is not None and flight.idle():
            del self.in_flight[query_id]

    def take_attempt(self, query_id: str, attempt: CallAttempt) -> bool:
        """`attempt`'s outcome came: whether it was the durable attempt in flight (its
        `Pending` wrote the record; not a same-id retry's), which is then taken off."""
        flight = self.in_flight.get(query_id)
        if flight is None or flight.attempt is not attempt:
            return False
        flight.attempt = None
        self.landed(query_id)
        return True

    def unsettled(self) -> dict[str, str]:
        """Query id -> provider, of the calls that failed as their provider died or
        stopped (it may hold the id; a retry may come): held until reconciled."""
        return {q: f.unsettled_at for q, f in self.in_flight.items() if f.unsettled_at}

    def settle(self, query_id: str, provider: str | None) -> None:
        """Set (or, with `None`, clear) where `query_id`'s failed call may be held."""
        if provider is not None:
            self.flight(query_id).unsettled_at = provider
        elif query_id in self.in_flight:
            self.in_flight[query_id].unsettled_at = None
            self.landed(query_id)

    def was_unsettled(self, query_id: str) -> bool:
        """Whether a call with `query_id` failed as its provider died (a retry follows)."""
        flight = self.in_flight.get(query_id)
        return flight is not None and flight.unsettled_at is not None

    # -- holding and forgetting queries -----------------------------------------------

    def forget(self, query_id: str, *, commit: bool = True, reason: str = "unload") -> None:
        """Forget a query this registrar held: its record and its status callback.

        With `commit=False` the caller commits (once, after forgetting several).
        `reason` is what its `QueryForgotten` says (an answered one's only).
        """
        record = self.registrar.catalog.clients.get(query_id)
        if record is not None:
            if record.loaded:
                outcomes.forgotten(self.registrar, record.query, reason)
            self.registrar.catalog.remove_client(query_id)
            self.status_callbacks.pop(query_id, None)
            self.targets.entries.pop(query_id, None)
            self.answered_in.pop(query_id, None)
            if commit:
                self.registrar.commit()

    def drop_pending(self, query: Query, *, forget_record: bool = True) -> None:
        """An answer this registrar does not keep: give `query`'s id back to its provider
        and forget its pending record, if it has one (with `forget_record`)."""
        give_back(query.serving_rr, query.id, self.registrar.name)
        record = self.registrar.catalog.clients.get(query.id)
        if forget_record and record is not None and not record.loaded:
            self.registrar.catalog.remove_client(query.id)
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

    def withdraw_pending(self, error: RrError) -> None:
        """This registrar stops: give up its durable calls in flight; their callers get `error`.

        The `Abandon` first, then the record, so a crash in between leaves nothing at the
        provider.
        """
        for record in list(self.registrar.catalog.clients.values()):
            flight = self.in_flight.get(record.query.id)
            attempt = None if flight is None else flight.attempt
            if attempt is not None:
                self.take_attempt(record.query.id, attempt)
            if record.parent is None and not record.loaded and attempt is not None:
                give_back(record.query.serving_rr, record.query.id, self.registrar.name)
                self.on_call_failed(
                    CallFailed(
                        record.query.id,
                        attempt,
                        withdrawn=True,
                        provider=record.query.serving_rr,
                        server=record.query.server,
                        why="registrar stopped",
                    ),
                    NO_REPLY,
                )
                attempt.fail(error)

    def release_dependencies(self, rid: str, then: Callable[[], None]) -> None:
        """Release every query resource `rid` holds as a dependency; then `then()`."""
        join = Join(then)
        for record in self.registrar.catalog.dependencies(rid):
            self.release_client(record, join.add())
        join.seal()

    def release_client(self, record: ClientRecord, then: Callable[[], None]) -> None:
        """Unload one query this registrar holds; the record goes whatever the answer.

        A provider that cannot be reached keeps the id until it reconciles with this
        registrar after its restart (`reconcile`), which releases it (`unreleased`).
        """
        query = record.query

        def answered(_: Any, error: BaseException | None) -> None:
            self.releasing.discard(query.id)
            if error is not None and not isinstance(error, UnknownQueryError):
                logger.warning("releasing %s at %s failed: %s", query.id, query.serving_rr, error)
            if isinstance(error, GONE):
                self.unreleased[query.id] = query.serving_rr
            self.forget(query.id, reason="stop" if record.parent is None else "dependency")
            then()

        self.releasing.add(query.id)
        self.registrar.send(
            query.serving_rr, lambda reply: Unload(query.id, self.registrar.name, reply), answered
        )

    def client(self, target_rr: str, server: str) -> pykka.ActorRef[ClientActor]:
        """The client actor for `target_rr/server`, started on first use (thesis 4.3.3)."""
        assert self.registrar.ref is not None
        return self.clients.start(self.registrar.ref, self.registrar.name, target_rr, server)

    # -- answers ----------------------------------------------------------------------

    def on_pending(self, message: Pending, reply: Reply) -> None:
        query_id = message.record.query.id
        if query_id not in self.registrar.catalog.clients:  # (else a retry of one held)
            record = message.record
            if self.owner_gone(record):  # a late sub-call: kept as a call of its own, so a
                record = ClientRecord(record.query, None)  # crash meanwhile gives it back
            self.registrar.catalog.add_client(record)
            self.texts.show(query_id)
            failed = self.registrar.commit()
            if failed is not None:  # not durable: the Load must not leave (rule 16)
                self.registrar.catalog.remove_client(query_id)
                self.registrar.commit()
                reply.set_error(failed)
                return
        self.flight(query_id).attempt = message.attempt
        reply.set_result(None)  # durable: the Load may leave now (rule 16)

    def on_client_loaded(self, message: ClientLoaded, _reply: Reply) -> None:
        """Record a call's answer (a `DurableLoaded` one too: it is a `ClientLoaded`)."""
        try:
            self.record_answer(message)
        finally:  # (also when recording failed: what waits for it must not wait for good)
            self.answered(message.record.query.id, message.attempt)

    def record_answer(self, message: ClientLoaded) -> None:
        """Decide what `message`'s answer does (`flight.decide`), and do it.

        A durable call's answer (`DurableLoaded`) is kept only while its caller still
        waits: the actor takes the attempt before it commits, so a caller whose time runs
        out meanwhile reads the answer instead. A caller that withdrew first told the
        provider an Abandon after its Load; a stop failed it: its answer is not kept.
        """
        query = message.record.query
        held = self.registrar.catalog.clients.get(query.id)
        retry = self.was_unsettled(query.id) or (held is not None and held.loaded)
        self.settle(query.id, None)  # (a retry of a call that failed as it died)
        self.kept_for_retry.pop(query.id, None)  # (... or that its provider kept)
        ours = self.take_attempt(query.id, message.attempt)  # (not a same-id retry's)
        durable = isinstance(message, DurableLoaded)
        withdrawn = durable and message.attempt.take() is not AttemptState.RECORDING
        try:
            action = decide(
                durable=durable,
                withdrawn=withdrawn,
                dependency=message.record.parent is not None,
                stopping=self.registrar.stopping,
                owner_gone=self.owner_gone(message.record),
            )
            self.act(action, message, ours=ours, retry=retry)
        except BaseException as exc:  # an attempt taken must be settled on every path
            if durable and not withdrawn:
                message.attempt.settle(error=exc)  # (no-op if it was)
            raise

    def act(self, action: Action, message: ClientLoaded, *, ours: bool, retry: bool) -> None:
        """Run `action` on `message`'s answer (`flight.Action` says what each does).

        `ours`: `message` is the attempt that wrote the pending record (not a same-id
        retry's). `retry`: the id was held or failed as its provider died before.
        """
        query = message.record.query
        match action:
            case Action.KEEP | Action.COMMIT:
                self.keep(message, retry=retry)
            case Action.LEAVE:
                pass  # its caller gave the id back; its CallFailed removes the record
            case Action.GIVE_BACK:
                self.drop_pending(query, forget_record=ours)
            case Action.REFUSE:
                self.drop_pending(query, forget_record=ours)
                error = RegistrarStoppedError(
                    f"registrar {self.registrar.name!r} stopped during the call"
                )
                outcomes.refused(self.registrar, query, error)
                message.attempt.settle(error=error)
            case Action.FORGET:  # its caller has the answer, given back here
                self.drop_pending(query, forget_record=ours)
                outcomes.answered(self.registrar, message.record, retry=False)
                outcomes.forgotten(self.registrar, query, "registrar stopped")
            case Action.RELEASE_LATE:
                outcomes.answered(self.registrar, message.record, retry=retry)
                outcomes.forgotten(self.registrar, query, "late dependency")
                self.give_back_late_dependency(message)

    def keep(self, message: ClientLoaded, *, retry: bool) -> None:
        """Record an answer (`Action.KEEP`), or commit a durable one and answer its
        caller (`Action.COMMIT`)."""
        catalog = self.registrar.catalog
        query = message.record.query
        durable = isinstance(message, DurableLoaded)
        if durable and self.unstorable(message):
            return
        if query.id in catalog.clients:  # written as pending before the load was sent
            catalog.client_loaded(query.id, query.response)
        else:
            catalog.add_client(message.record)
            self.texts.show(query.id)
        failed = self.registrar.commit()
        if failed is not None and durable:  # not kept
            give_back(query.serving_rr, query.id, self.registrar.name)
            self.forget(query.id)
            outcomes.refused(self.registrar, query, failed)
            message.attempt.settle(error=failed)
            return
        outcomes.answered(self.registrar, message.record, retry=retry)
        self.answered_in[query.id] = self.epoch  # (a reconcile's list left before?)
        if message.on_status is not None:
            self.status_callbacks[query.id] = message.on_status
            self.publish_target(query.id)
        if durable:
            message.attempt.settle(query.response)

    def unstorable(self, message: ClientLoaded) -> bool:
        """A durable call's response this catalog cannot store: give it back, fail the call.

        (A caller that records its own answer checks the response itself, see `calls.py`.)
        """
        query = message.record.query
        try:
            check_picklable(query.response, f"the response of '{query.serving_rr}/{query.server}'")
        except ConfigError as exc:
            self.drop_pending(query)
            outcomes.refused(self.registrar, query, exc)
            message.attempt.settle(error=exc)
            return True
        return False

    def owner_gone(self, record: ClientRecord) -> bool:
        """Whether `record` is a dependency of a resource that failed or is unloading.

        Its load returned (or raised) while a sub-call it started was still in flight:
        the resource's dependencies were released already, so this one would never be.
        """
        if record.parent is None:
            return False
        owner = self.registrar.catalog.resources.get(record.parent)
        return owner is None or owner.state is ResourceState.UNLOADING

    def give_back_late_dependency(self, message: ClientLoaded) -> None:
        """Release a dependency that arrived after its resource's own release (rule 4).

        The call itself succeeded (its caller has the response, or gets it now), but the
        id is given back at once: nothing could ever release it otherwise.
        """
        query = message.record.query
        logger.warning(
            "registrar %s: call %s to '%s/%s' returned after the load that made it had "
            "failed or was unloading; releasing it",
            self.registrar.name,
            query.id,
            query.serving_rr,
            query.server,
        )
        self.drop_pending(query)  # (a durable consumer wrote its record as pending)
        if isinstance(message, DurableLoaded):  # (taken by `record_answer`)
            message.attempt.settle(query.response)

    def on_call_failed(self, message: CallFailed, _reply: Reply) -> None:
        known = self.registrar.catalog.clients.get(message.query_id)
        outcomes.failed(
            self.registrar,
            message,
            retry=self.was_unsettled(message.query_id) or (known is not None and known.loaded),
        )
        flight = self.in_flight.get(message.query_id)
        current = None if flight is None else flight.attempt
        self.take_attempt(message.query_id, message.attempt)
        if current is None or current is message.attempt:
            # (set if it may hold the id: a retry may follow)
            self.settle(message.query_id, message.serving_rr)
            self.kept_for_retry.pop(message.query_id, None)  # (settled, or unsettled again)
        record = self.registrar.catalog.clients.get(message.query_id)
        try:
            if current is not None and current is not message.attempt:
                pass  # a stale failure of an earlier attempt: the record is a retry's
            elif record is not None and record.loaded and not message.withdrawn:
                pass  # a failed retry of an id this registrar holds: it still holds it
            elif record is not None:
                self.forget(message.query_id, reason="withdrawn")
        finally:
            self.answered(message.query_id, message.attempt)

    # -- notices that overtake the answer they are about ------------------------------

    def take_outcomes(self) -> None:
        """Record the call outcomes handed over so far, in order (`calls.py`)."""
        outcomes = self.due.outcomes
        while not outcomes.empty():
            self.redeliver(outcomes.get())

    def parked(self, notice: Notice) -> bool:
        """Hold `notice` if the answer to one of its queries is still on its way.

        It is handled again (`answered`) once that answer or the call's failure was. The
        caller that hands that outcome over wakes this actor for it (`DueAnswers.awaited`).
        """
        for query_id in notice.query_ids:
            if self.due.awaited(query_id):
                self.take_outcomes()  # (handed over before the mark was read?)
            if query_id in self.due:
                self.flight(query_id).parked.append(notice)
                return True
        return False

    def answered(self, query_id: str, attempt: CallAttempt) -> None:
        """`attempt`'s answer or failure was handled: handle what waited for it."""
        if not self.due.settle(query_id, attempt):
            return
        flight = self.in_flight.get(query_id)
        if flight is None or not flight.parked:
            return
        waiting, flight.parked = flight.parked, []
        self.landed(query_id)
        while waiting:
            notice = waiting.pop(0)
            try:
                self.redeliver(notice)
            except BaseException:  # the actor dies: `fail_waiting` answers the rest
                self.flight(query_id).parked[:0] = waiting
                raise

    def on_revoke(self, message: Revoke, _reply: Reply) -> None:
        if self.parked(message):
            return
        for query_id in message.query_ids:
            self.forget(query_id, commit=False, reason="revoked")
        self.registrar.commit()

    def on_response_updated(self, message: ResponseUpdated, reply: Reply) -> None:
        if self.parked(message):
            return
        for query_id in message.query_ids:
            self.registrar.catalog.client_loaded(query_id, message.response)
            if query_id in self.targets.entries:  # (its query says the new response)
                self.publish_target(query_id)
        self.registrar.commit()
        reply.set_result(None)

    def fail_waiting(self, error: RrError) -> None:
        """Answer the durable callers and the held notices still waiting here."""
        for flight in self.in_flight.values():
            if flight.attempt is not None:
                flight.attempt.fail(error)
        for flight in self.in_flight.values():
            for notice in flight.parked:
                if not isinstance(notice, Revoke):  # (a revoke wants no answer)
                    notice.reply.set_error(error)
            flight.parked.clear()
        for query_id in list(self.in_flight):
            self.landed(query_id)

    def stop_clients(self) -> None:
        self.clients.stop_all()

    # -- what reconciling (`reconciling.py`) asks of it --------------------------------

    def holds_at(self, serving_rr: str) -> bool:
        """Whether this registrar holds ids at `serving_rr` (records, failed calls, or
        releases to complete there)."""
        return (
            serving_rr in self.unsettled().values()
            or serving_rr in self.unreleased.values()
            or serving_rr in self.kept_for_retry.values()
            or any(
                record.query.serving_rr == serving_rr
                for record in self.registrar.catalog.clients.values()
            )
        )

    def listing(self, serving_rr: str, due: frozenset[str]) -> Listing:
        """The list of a `Reconcile` to `serving_rr` that leaves now, a new `epoch`.

        Args:
            serving_rr: the provider.
            due: the ids whose answer is due now, at any provider (listed too: harmless,
                reported unknown).
        """
        held = {
            query_id
            for query_id, record in self.registrar.catalog.clients.items()
            if record.query.serving_rr == serving_rr
        }
        held |= {q for q, provider in self.unsettled().items() if provider == serving_rr}
        held |= due
        left_out = frozenset(q for q, p in self.unreleased.items() if p == serving_rr)
        self.epoch += 1
        return Listing(tuple(sorted(held - left_out)), due, left_out, self.epoch)

    def answered_before(self, query_id: str, listing: Listing) -> bool:
        """Whether `query_id`'s answer was recorded before `listing` left."""
        return self.answered_in.get(query_id, 0) < listing.epoch

    def is_releasing(self, query_id: str) -> bool:
        """Whether the `Unload` of `query_id` is on its way."""
        return query_id in self.releasing

    def settle_listed(
        self, serving_rr: str, listing: Listing | None = None, unknown: Iterable[str] = ()
    ) -> None:
        """`serving_rr` answered `listing`'s `Reconcile`: settle the failed calls it listed
        (it holds those it knew, `kept_for_retry`: a retry finds them), forget those it
        kept before that the list left out (it released them) and the releases it left
        out (it released them). Without a listing (`serving_rr` is gone for good): all of
        them. `unknown`: the listed ids it answered it does not know."""

        def settled(query_id: str) -> bool:
            return listing is None or query_id in listing.held or query_id in listing.left_out

        for query_id, provider in list(self.kept_for_retry.items()):
            if provider == serving_rr and (listing is None or query_id not in listing.held):
                del self.kept_for_retry[query_id]
        lost = set(unknown)
        for query_id, provider in self.unsettled().items():
            if provider == serving_rr and settled(query_id):
                self.settle(query_id, None)
                if listing is not None and query_id in listing.held and query_id not in lost:
                    self.kept_for_retry[query_id] = serving_rr
        for query_id in [q for q, p in self.unreleased.items() if p == serving_rr]:
            if settled(query_id):
                del self.unreleased[query_id]

    def give_back_unsettled(self) -> None:
        """This registrar stops: give back the ids of calls that failed as their provider
        died, which it would no longer retry (also those the provider kept for a retry
        when it reconciled), and of releases that failed so."""
        for query_id, serving_rr in self.unsettled().items():
            give_back(serving_rr, query_id, self.registrar.name)
            self.settle(query_id, None)
        for query_id, serving_rr in self.kept_for_retry.items():
            give_back(serving_rr, query_id, self.registrar.name)
        self.kept_for_retry.clear()
        for query_id, serving_rr in self.unreleased.items():
            give_back(serving_rr, query_id, self.registrar.name)
        self.unreleased.clear()

    # -- operations the handle asks for ----------------------------------------------

    def on_release(self, message: Release, reply: Reply) -> None:
        query_id = message.query_id
        record = self.registrar.catalog.clients.get(query_id)
        if record is None or not record.loaded:
            raise UnknownQueryError(f"unknown or released query id {query_id!r}")
        query = record.query

        def answered(_: Any, error: BaseException | None) -> None:
            self.releasing.discard(query_id)
            if isinstance(error, GONE):  # it may or may not have run it: reconciling
                reply.set_error(self.release_later(query, error))  # completes it
                return
            # The provider released the id unless it failed otherwise: it was unknown
            # there, or its unload callback overran `unload_timeout` (a CallTimeoutError
            # only the provider's answer carries here; the caller's own is its handle's).
            released = error is None or isinstance(error, UnknownQueryError | CallTimeoutError)
            if not released:
                reply.set_error(error)  # type: ignore[arg-type]  # e.g. its backup is full
                return
            if isinstance(error, UnknownQueryError):
                logger.warning("provider %s no longer knew %s", query.serving_rr, query.id)
            self.forget(query_id)
            if isinstance(error, CallTimeoutError):
                reply.set_error(error)
            else:
                reply.set_result(None)

        self.releasing.add(query_id)
        self.registrar.send(
            query.serving_rr, lambda r: Unload(query_id, self.registrar.name, r), answered
        )

    def release_later(self, query: Query, error: BaseException) -> RrError:
        """The `Unload` of `query` failed as its provider died or stopped (`error`).

        This registrar gave the id up: it forgets it now (a second `unload` raises
        `UnknownQueryError`) and keeps it as `unreleased` until the provider's next
        `Reconcile` was answered, which does not list it: the provider releases it if it
        still holds it (its `unload` runs once), and nobody hears `FATAL` for it (its
        consumer asked to release it). Returns the error for the caller, which says so.
        """
        self.unreleased[query.id] = query.serving_rr
        self.forget(query.id, reason="unload unanswered")
        kind = (
            RegistrarStoppedError
            if isinstance(error, RegistrarStoppedError)
            else RegistrarUnavailableError
        )
        told = kind(
            f"{error}; query {query.id} is released: '{query.serving_rr}' releases it when "
            "it reconciles with this registrar after its restart (its unload runs once)"
        )
        told.__cause__ = error
        return told

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
