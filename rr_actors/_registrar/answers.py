"""The consumer side of a registrar actor, the answers: each call's outcome, recorded once.

```
 caller thread ──Load──► provider          (calls.py: the call protocol)
      │  durable: Pending ──► on_pending: record written as pending, then the Load leaves
      ▼                       (flights.py hold_attempt: this actor answers it)
 answer ──► ClientLoaded (plain) ─┐ due.outcomes, taken before each message
        └─► DurableLoaded ────────┤ (flights.py take_outcomes), or the mailbox:
 failure/withdrawal ──► CallFailed ─┘
 on_client_loaded ──► record_answer: decide() ──► Action (flight.py) ──► act: its step
        KEEP | COMMIT ──► keep: the record, then holdings.py held (status callback)
        GIVE_BACK | REFUSE | FORGET | RELEASE_LATE ──► drop_pending: the id given back
 on_call_failed ──► holdings.py forget (a withdrawn or failed record)
 both ──► flights.py answered: the notices held back behind this answer, handled now
```

An answer this registrar does not keep goes through one method, `drop_pending`: the id
given back to its provider (`messages.give_back`), its pending record forgotten.
"""

from __future__ import annotations

import logging

from rr_actors._catalog import ClientRecord, ResourceState
from rr_actors._core.directory import Reply
from rr_actors._registrar import outcomes
from rr_actors._registrar.calls import AttemptState
from rr_actors._registrar.display import ClientTexts
from rr_actors._registrar.flight import Action, decide
from rr_actors._registrar.flights import Flights
from rr_actors._registrar.holdings import Holdings
from rr_actors._registrar.loading import check_picklable
from rr_actors._registrar.messages import (
    CallFailed,
    ClientLoaded,
    DurableLoaded,
    Pending,
    give_back,
)
from rr_actors._registrar.state import Shared
from rr_actors._types import Query
from rr_actors.errors import ConfigError, RegistrarStoppedError

__all__ = ["Answers"]

logger = logging.getLogger("rr_actors")


class Answers:
    """Records the answers to this registrar's calls, and their failures.

    Attributes:
        texts: makes its records' request display texts (`display.py`).
    """

    def __init__(self, shared: Shared, flights: Flights, holdings: Holdings) -> None:
        self.registrar = shared
        self.flights = flights
        self.holdings = holdings
        self.texts = ClientTexts(shared)

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
        self.flights.hold_attempt(query_id, message.attempt)
        reply.set_result(None)  # durable: the Load may leave now (rule 16)

    def on_client_loaded(self, message: ClientLoaded, _reply: Reply) -> None:
        """Record a call's answer (a `DurableLoaded` one too: it is a `ClientLoaded`)."""
        try:
            self.record_answer(message)
        finally:  # (also when recording failed: what waits for it must not wait for good)
            self.flights.answered(message.record.query.id, message.attempt)

    def record_answer(self, message: ClientLoaded) -> None:
        """Decide what `message`'s answer does (`flight.decide`), and do it.

        A durable call's answer (`DurableLoaded`) is kept only while its caller still
        waits: the actor takes the attempt before it commits, so a caller whose time runs
        out meanwhile reads the answer instead. A caller that withdrew first told the
        provider an Abandon after its Load; a stop failed it: its answer is not kept.
        """
        query = message.record.query
        held = self.registrar.catalog.clients.get(query.id)
        retry = self.flights.was_unsettled(query.id) or (held is not None and held.loaded)
        # (a retry of a call that failed as it died, or that its provider kept)
        self.flights.reset(query.id, None)
        ours = self.flights.take_attempt(query.id, message.attempt)  # (not a same-id retry's)
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
                self.drop_pending(query, forget_record=ours, reason="registrar stopped")
                error = RegistrarStoppedError(
                    f"registrar {self.registrar.name!r} stopped during the call"
                )
                outcomes.refused(self.registrar, query, error)
                message.attempt.settle(error=error)
            case Action.FORGET:  # its caller has the answer, given back here
                outcomes.answered(self.registrar, message.record, retry=False)  # (before the
                outcomes.forgotten(self.registrar, query, "registrar stopped")  # commit)
                self.drop_pending(query, forget_record=ours, reason=None)
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
        told = outcomes.answer(self.registrar, message.record, retry=retry)
        failed = self.registrar.commit(*told)  # (written with its record)
        if failed is not None and durable:  # not kept
            give_back(query.serving_rr, query.id, self.registrar.name)
            self.holdings.forget(query.id)
            outcomes.refused(self.registrar, query, failed)
            message.attempt.settle(error=failed)
            return
        if failed is not None:  # kept in memory: written with the next write
            self.registrar.publish(*told)
        self.holdings.held(query.id, message.on_status)
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

    def drop_pending(
        self, query: Query, *, forget_record: bool = True, reason: str | None = "in doubt"
    ) -> None:
        """An answer this registrar does not keep: give `query`'s id back to its provider
        and forget its pending record, if it has one (with `forget_record`).

        `reason`: what its `QueryForgotten` says if a restore had listed the record (a
        call in flight when the last run died); `None`: the caller published it.
        """
        give_back(query.serving_rr, query.id, self.registrar.name)
        record = self.registrar.catalog.clients.get(query.id)
        if forget_record and record is not None and not record.loaded:
            self.holdings.forget(query.id, reason=reason)

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
        self.drop_pending(query, reason=None)  # (a durable consumer wrote it as pending)
        if isinstance(message, DurableLoaded):  # (taken by `record_answer`)
            message.attempt.settle(query.response)

    def on_call_failed(self, message: CallFailed, _reply: Reply) -> None:
        known = self.registrar.catalog.clients.get(message.query_id)
        outcomes.failed(
            self.registrar,
            message,
            retry=self.flights.was_unsettled(message.query_id)
            or (known is not None and known.loaded),
        )
        current = self.flights.attempt_of(message.query_id)
        self.flights.take_attempt(message.query_id, message.attempt)
        if current is None or current is message.attempt:
            # (set if it may hold the id: a retry may follow; settled, or unsettled again)
            self.flights.reset(message.query_id, message.serving_rr)
        record = self.registrar.catalog.clients.get(message.query_id)
        try:
            if current is not None and current is not message.attempt:
                pass  # a stale failure of an earlier attempt: the record is a retry's
            elif record is not None and record.loaded and not message.withdrawn:
                pass  # a failed retry of an id this registrar holds: it still holds it
            elif record is not None:
                self.holdings.forget(message.query_id, reason="withdrawn")
        finally:
            self.flights.answered(message.query_id, message.attempt)
