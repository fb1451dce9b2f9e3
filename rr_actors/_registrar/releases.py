"""The consumer side of a registrar actor, releasing: what it holds, given up.

```
 Release (the handle: unload) ──► on_release ──Unload──► provider ──► forget (holdings.py)
 a resource's teardown (teardown.py, provider.py, lifecycle.py)
   ──► release_dependencies(rid) ──► release_client each ──Unload──► ... ──► forget
 the provider died or stopped meanwhile (it may or may not have run it):
   ──► forgotten here, kept in `unreleased` ──► left out of its next `Reconcile`
       (reconciling.py), so it releases the id (its unload runs once) ──► settle_listed
 this registrar stops (lifecycle.py):
   withdraw_pending ──► Abandon, then CallFailed (answers.py): its durable calls in flight
   give_back_unsettled ──► the failed calls (flights.py) and the releases that failed
```

Giving an id back to a provider is `messages.give_back`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from rr_actors._catalog import ClientRecord
from rr_actors._core.directory import Reply
from rr_actors._core.replies import Join
from rr_actors._registrar.answers import Answers
from rr_actors._registrar.flights import Flights
from rr_actors._registrar.holdings import Holdings
from rr_actors._registrar.listing import Listing
from rr_actors._registrar.messages import CallFailed, Release, Unload, give_back
from rr_actors._registrar.state import NO_REPLY, Shared
from rr_actors._types import Query
from rr_actors.errors import (
    CallTimeoutError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
    UnknownQueryError,
)

__all__ = ["GONE", "Releases"]

logger = logging.getLogger("rr_actors")

GONE = (RegistrarUnavailableError, RegistrarStoppedError)
"""Errors of a provider that died or was stopped: what was sent may or may not have run."""


class Releases:
    """Releases the queries this registrar holds, and gives back what it gives up.

    Attributes:
        releasing: query ids whose `Unload` is on its way.
        unreleased: query id -> provider, of ids this registrar released whose `Unload`
            failed as the provider died or stopped (it may or may not have run it). Their
            records are forgotten; a `Reconcile` does not list them, so the provider
            releases any it still holds (its `unload` runs once) and none is reported
            `FATAL`. Held until such a `Reconcile` was answered.
    """

    def __init__(
        self, shared: Shared, flights: Flights, holdings: Holdings, answers: Answers
    ) -> None:
        self.registrar = shared
        self.flights = flights
        self.holdings = holdings
        self.answers = answers
        self.releasing: set[str] = set()
        self.unreleased: dict[str, str] = {}

    # -- releasing one query ------------------------------------------------------------

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
            self.holdings.forget(query.id, reason="stop" if record.parent is None else "dependency")
            then()

        self.releasing.add(query.id)
        self.registrar.send(
            query.serving_rr, lambda reply: Unload(query.id, self.registrar.name, reply), answered
        )

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
            self.holdings.forget(query_id)
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
        self.holdings.forget(query.id, reason="unload unanswered")
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

    # -- what reconciling (`reconciling.py`) asks of it ---------------------------------

    def is_releasing(self, query_id: str) -> bool:
        """Whether the `Unload` of `query_id` is on its way."""
        return query_id in self.releasing

    def unreleased_at(self, serving_rr: str) -> frozenset[str]:
        """The ids released while `serving_rr` died or stopped (`unreleased`)."""
        return frozenset(q for q, p in self.unreleased.items() if p == serving_rr)

    def settle_listed(self, serving_rr: str, listing: Listing | None) -> None:
        """`serving_rr` answered `listing`'s `Reconcile`: forget the releases it left
        out (it released them). Without a listing (`serving_rr` is gone for good): all."""
        for query_id in [q for q, p in self.unreleased.items() if p == serving_rr]:
            if listing is None or query_id in listing.held or query_id in listing.left_out:
                del self.unreleased[query_id]

    # -- this registrar stops -----------------------------------------------------------

    def withdraw_pending(self, error: RrError) -> None:
        """This registrar stops: give up its durable calls in flight; their callers get `error`.

        The `Abandon` first, then the record, so a crash in between leaves nothing at the
        provider.
        """
        for record in list(self.registrar.catalog.clients.values()):
            attempt = self.flights.attempt_of(record.query.id)
            if attempt is not None:
                self.flights.take_attempt(record.query.id, attempt)
            if record.parent is None and not record.loaded and attempt is not None:
                give_back(record.query.serving_rr, record.query.id, self.registrar.name)
                self.answers.on_call_failed(
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

    def give_back_unsettled(self) -> None:
        """This registrar stops: give back the ids of calls that failed as their provider
        died, which it would no longer retry (also those the provider kept for a retry
        when it reconciled: `flights.py`), and of releases that failed so."""
        self.flights.give_back_unsettled()
        for query_id, serving_rr in self.unreleased.items():
            give_back(serving_rr, query_id, self.registrar.name)
        self.unreleased.clear()
