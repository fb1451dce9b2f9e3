"""The consumer side of a registrar actor, its calls in flight: one `InFlight` per query id.

```
 in_flight: query id ──► InFlight(attempt, unsettled_at, parked)        (flight.py)
   attempt       answers.py on_pending: hold_attempt ──► take_attempt when its outcome came
   unsettled_at  answers.py on_call_failed: reset(id, provider) (it may hold the id)
                 ──► reconciling.py settle_listed ──► kept_for_retry (the provider kept it)
                 ──► answers.py record_answer: reset(id, None) (a retry was answered)
                 ──► releases.py give_back_unsettled (this registrar stops)
   parked        a notice (Revoke, ResponseUpdated, StatusNotice) whose answer is due:
                 parked(notice) ──► answered(id, attempt) ──► redeliver(notice)
 due.outcomes (call outcomes handed over by callers' threads) ──► take_outcomes ──► redeliver
```

`redeliver` is the actor's dispatch (a callable it is given), not a role: a notice held
back, or an outcome taken, is handled as if it had just arrived. The record of one call
is `flight.py`'s; what an answer does is `answers.py`'s.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from rr_actors._registrar.calls import CallAttempt, DueAnswers
from rr_actors._registrar.flight import InFlight
from rr_actors._registrar.listing import Listing
from rr_actors._registrar.messages import ResponseUpdated, Revoke, StatusNotice, give_back
from rr_actors._registrar.state import Shared
from rr_actors.errors import RrError

__all__ = ["Flights", "Notice"]

Notice = StatusNotice | Revoke | ResponseUpdated
"""What a provider tells a consumer about queries it holds."""


class Flights:
    """What is known of this registrar's calls whose outcome is not settled yet.

    Attributes:
        due: the query ids whose answers are on their way (shared with callers' threads).
        redeliver: handles a message as the actor does (its dispatch).
        in_flight: query id -> what is known of its call in flight (`InFlight`: a
            durable attempt this actor answers after its commit, the provider of a call
            that failed as it died or stopped, the notices that overtook its answer).
        kept_for_retry: query id -> provider, of calls that failed as the provider died
            or stopped and that it still held when a `Reconcile` with it was answered
            since: a retry with the id finds it there. Never retried, the id is released
            by the provider's next `Reconcile` (which does not list it) or given back
            when this registrar stops (rule 12).
    """

    def __init__(self, shared: Shared, due: DueAnswers, redeliver: Callable[[Any], None]) -> None:
        self.registrar = shared
        self.due = due
        self.redeliver = redeliver
        self.in_flight: dict[str, InFlight] = {}
        self.kept_for_retry: dict[str, str] = {}

    # -- one call's record --------------------------------------------------------------

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

    # -- durable attempts ---------------------------------------------------------------

    def hold_attempt(self, query_id: str, attempt: CallAttempt) -> None:
        """`attempt`'s `Pending` was committed: this actor answers it (a same-id retry's
        replaces it)."""
        self.flight(query_id).attempt = attempt

    def attempt_of(self, query_id: str) -> CallAttempt | None:
        """The durable attempt of `query_id` this actor answers, if any."""
        flight = self.in_flight.get(query_id)
        return None if flight is None else flight.attempt

    def take_attempt(self, query_id: str, attempt: CallAttempt) -> bool:
        """`attempt`'s outcome came: whether it was the durable attempt in flight (its
        `Pending` wrote the record; not a same-id retry's), which is then taken off."""
        flight = self.in_flight.get(query_id)
        if flight is None or flight.attempt is not attempt:
            return False
        flight.attempt = None
        self.landed(query_id)
        return True

    # -- calls that failed as their provider died (unsettled, then kept for a retry) ----

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

    def reset(self, query_id: str, provider: str | None) -> None:
        """A new outcome of `query_id`'s call: where it may be held now (`settle`), and
        it is no longer one its provider kept for a retry."""
        self.settle(query_id, provider)
        self.kept_for_retry.pop(query_id, None)

    def was_unsettled(self, query_id: str) -> bool:
        """Whether a call with `query_id` failed as its provider died (a retry follows)."""
        flight = self.in_flight.get(query_id)
        return flight is not None and flight.unsettled_at is not None

    def held_at(self, serving_rr: str) -> bool:
        """Whether `serving_rr` may hold the id of a call that failed as it died."""
        return serving_rr in self.unsettled().values() or serving_rr in self.kept_for_retry.values()

    def settle_listed(
        self, serving_rr: str, listing: Listing | None, unknown: Iterable[str] = ()
    ) -> None:
        """`serving_rr` answered `listing`'s `Reconcile`: settle the failed calls it
        listed (it holds those it knew, `kept_for_retry`: a retry finds them), forget
        those it kept before that the list left out (it released them). Without a
        listing (`serving_rr` is gone for good): all of them. `unknown`: the listed ids
        it answered it does not know."""
        for query_id, provider in list(self.kept_for_retry.items()):
            if provider == serving_rr and (listing is None or query_id not in listing.held):
                del self.kept_for_retry[query_id]
        lost = set(unknown)
        for query_id, provider in self.unsettled().items():
            if provider == serving_rr and (
                listing is None or query_id in listing.held or query_id in listing.left_out
            ):
                self.settle(query_id, None)
                if listing is not None and query_id in listing.held and query_id not in lost:
                    self.kept_for_retry[query_id] = serving_rr

    def give_back_unsettled(self) -> None:
        """This registrar stops: give back the ids of calls that failed as their provider
        died, which it would no longer retry (also those the provider kept for a retry
        when it reconciled)."""
        for query_id, serving_rr in self.unsettled().items():
            give_back(serving_rr, query_id, self.registrar.name)
            self.settle(query_id, None)
        for query_id, serving_rr in self.kept_for_retry.items():
            give_back(serving_rr, query_id, self.registrar.name)
        self.kept_for_retry.clear()

    # -- notices that overtake the answer they are about --------------------------------

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

    def parked_ids(self) -> frozenset[str]:
        """The query ids with notices held back (`rr_actors.testing.pending_work`)."""
        return frozenset(q for q, f in self.in_flight.items() if f.parked)

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
