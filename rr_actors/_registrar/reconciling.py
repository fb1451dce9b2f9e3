"""The consumer side of a registrar actor, reconciling: what it holds at a provider, checked.

```
 this registrar serves (again), or a provider asks (ReconcileAsk) ──► reconcile(provider)
      ──► Reconcile(the ids held there, as a `Listing`) ──► the provider releases the
          others, and names those it no longer knows ──► settle_reconciled: FATAL to
          those that were answered before the list left, then forgotten
 a provider gone for good (presence.py) ──► lose_provider: FATAL to its ids, forgotten
```

Rule 20 and rule 19 (`docs/explanation/failure-semantics.md`). The providers that asked
while setup ran are this role's state. What a list names is the other roles' state, asked
and settled through their methods: the records (`holdings.py`), the calls that failed as
their provider died and those it kept for a retry (`flights.py`), the releases that failed
so (`releases.py`):

```
 listing(provider): its client records, its unsettled calls, the calls due, and not
                    its unreleased ids (left out: the provider releases them)
 its answer ──► settle_listed ──► flights.settle_listed, releases.settle_listed
```
"""

from __future__ import annotations

import logging
import time
import uuid
from collections.abc import Callable, Iterable
from typing import Any

from rr_actors._core.directory import DIRECTORY, Reply
from rr_actors._core.replies import FutureReply
from rr_actors._registrar.calls import DueAnswers
from rr_actors._registrar.flights import Flights
from rr_actors._registrar.holdings import Holdings
from rr_actors._registrar.listing import Listing
from rr_actors._registrar.messages import Reconcile, ReconcileAsk, StatusNotice
from rr_actors._registrar.releases import Releases
from rr_actors._registrar.state import Phase, Shared
from rr_actors._types import Status

__all__ = ["Reconciling"]

logger = logging.getLogger("rr_actors")


class Reconciling:
    """Reconciles what this registrar holds at providers with what they hold for it.

    Attributes:
        due: the query ids whose answers are on their way (`DueAnswers`, shared with
            callers' threads and the other consumer roles).
        asked_to_reconcile: providers that asked for a `Reconcile` during setup.
        everyone: reconcile with every registrar of the system, not only the providers
            its catalog names (`reconcile_all`): set when it restores a backup.
    """

    def __init__(
        self,
        shared: Shared,
        flights: Flights,
        holdings: Holdings,
        releases: Releases,
        due: DueAnswers,
        redeliver: Callable[[Any], None],
    ) -> None:
        self.registrar = shared
        self.flights = flights
        self.holdings = holdings
        self.releases = releases
        self.due = due
        self.redeliver = redeliver
        self.asked_to_reconcile: set[str] = set()
        self.everyone = False

    def expect_reconcile(self, providers: Iterable[str]) -> None:
        """Reconcile with `providers` too once this registrar serves (`reconcile_all`)."""
        self.asked_to_reconcile.update(providers)

    def reconcile_all(self) -> None:
        """This registrar serves (again): reconcile with every provider it holds ids at.

        Also with those that asked while setup ran (`ReconcileAsk`), and, restored from a
        backup (`everyone`), with every registrar of the system it can reach now: its
        backup does not name every provider that may hold ids of it. An id it released
        while its provider was down (`Releases.unreleased`, kept in memory only), a call
        that failed as its provider died (`Flights.unsettled`), or a record lost with a
        save interval has no row left; killed before that provider's restart asked it to
        reconcile, it would hold such an id there for good. A provider it holds nothing
        at answers an empty list at once (and releases what it held for this one).
        """
        providers = {record.query.serving_rr for record in self.registrar.catalog.clients.values()}
        providers |= self.asked_to_reconcile
        if self.everyone:
            providers |= DIRECTORY.names() - {self.registrar.name}
        self.asked_to_reconcile.clear()
        for serving_rr in sorted(providers):
            self.reconcile(serving_rr)

    # -- what it holds at a provider --------------------------------------------------

    def holds_at(self, serving_rr: str) -> bool:
        """Whether this registrar holds ids at `serving_rr` (records, failed calls, or
        releases to complete there)."""
        return (
            self.flights.held_at(serving_rr)
            or bool(self.releases.unreleased_at(serving_rr))
            or any(
                record.query.serving_rr == serving_rr
                for record in self.registrar.catalog.clients.values()
            )
        )

    def listing(self, serving_rr: str, due: frozenset[str]) -> Listing:
        """The list of a `Reconcile` to `serving_rr` that leaves now, a new epoch.

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
        held |= {q for q, provider in self.flights.unsettled().items() if provider == serving_rr}
        held |= due
        left_out = self.releases.unreleased_at(serving_rr)
        epoch = self.holdings.new_epoch()
        return Listing(tuple(sorted(held - left_out)), due, left_out, epoch)

    def settle_listed(
        self, serving_rr: str, listing: Listing | None = None, unknown: Iterable[str] = ()
    ) -> None:
        """`serving_rr` answered `listing`'s `Reconcile` (`unknown`: the listed ids it
        does not know): settle the failed calls and the releases it listed or left out.
        Without a listing (`serving_rr` is gone for good): all of them."""
        self.flights.settle_listed(serving_rr, listing, unknown)
        self.releases.settle_listed(serving_rr, listing)

    def on_reconcile_ask(self, message: ReconcileAsk, _reply: Reply) -> None:
        if not message.holds_yours and not self.holds_at(message.serving_rr):
            return  # (told as every registrar of the system is: nothing to reconcile)
        if self.registrar.phase is Phase.SETTING_UP:  # its status callbacks are not attached yet
            self.asked_to_reconcile.add(message.serving_rr)
            return
        self.reconcile(message.serving_rr)

    def reconcile(
        self, serving_rr: str, then: Callable[[BaseException | None], None] | None = None
    ) -> None:
        """Tell `serving_rr` which ids this registrar holds there (`Reconcile`).

        The provider releases the others it holds for this registrar, and names the ones
        it no longer knows: their status callbacks get `FATAL` and they are forgotten.
        The list and the message leave while no call can start (`DueAnswers.frozen`), so
        a call sent later reaches the provider after it. The provider's "unknown" is
        about its catalog as the list found it, so it settles only the records answered
        before the list left (`Listing.epoch`): a call due then may send its `Load` after
        the `Reconcile` (its caller's thread may still be on its way to the carrier), and
        a retry of a call that failed as the provider died may be sent and answered
        after it; their own answers decide. Releases that failed as the provider died
        are left out of the list, so the provider releases them (`Releases.unreleased`).
        `then(error)` runs (on this actor) once the answer was handled: `None`, or why it
        failed (`presence.py` retries).
        """
        with self.due.frozen() as due:
            listing = self.listing(serving_rr, due)
            self.registrar.send(
                serving_rr,
                lambda reply: Reconcile(self.registrar.name, listing.held, reply),
                lambda unknown, error: self.reconciled(serving_rr, unknown, error, listing, then),
            )

    def reconciled(
        self,
        serving_rr: str,
        unknown: Any,
        error: BaseException | None,
        listing: Listing,
        then: Callable[[BaseException | None], None] | None = None,
    ) -> None:
        """The provider's answer to the `Reconcile` of `listing`: report and forget what
        it lost."""
        if error is not None:  # not reachable: it asks for a Reconcile when it is back
            logger.debug(
                "reconciling %s with %s failed: %s", self.registrar.name, serving_rr, error
            )
            if then is not None:
                then(error)
            return
        self.settle_reconciled(serving_rr, unknown, listing)
        if then is not None:
            then(None)

    def settle_reconciled(self, serving_rr: str, unknown: Any, listing: Listing) -> None:
        """Report and forget the ids `serving_rr` answered it no longer knows.

        Only records that were as `listing` found them: answered before it left, not due
        then or now, not being released. One answered after it (a retry, a call due) is
        held there by its own answer.
        """
        lost: dict[str, list[str]] = {}
        for query_id in unknown:
            record = self.registrar.catalog.clients.get(query_id)
            if (
                record is None
                or not record.loaded
                or record.query.serving_rr != serving_rr
                or query_id in listing.due
                or query_id in self.due
                or not self.holdings.answered_before(query_id, listing.epoch)
                or self.releases.is_releasing(query_id)
            ):
                continue
            lost.setdefault(record.query.server, []).append(query_id)
        # What was unsettled, was listed and survived the reconcile is held by the provider
        # now: a retry finds it; a call never retried is released at its next restart, or
        # given back when this registrar stops (`Flights.kept_for_retry`).
        # What was left out of the list, it released.
        self.settle_listed(serving_rr, listing, unknown)
        for server, ids in lost.items():
            logger.warning(
                "registrar %s: %s/%s no longer knows %d of the queries held there "
                "(its restart lost them, or they were held at a registrar of its name "
                "that yielded it, rule 22): FATAL, and they are forgotten",
                self.registrar.name,
                serving_rr,
                server,
                len(ids),
            )
            self.report_lost(f"{serving_rr}/{server}", tuple(ids), forgotten="unknown at reconcile")

    def lose_provider(self, serving_rr: str) -> None:
        """Provider `serving_rr` is gone and nobody will restart it (rule 19): the ids
        held there get `FATAL` (and up their dependents), then they are forgotten."""
        lost: dict[str, list[str]] = {}
        for query_id, record in list(self.registrar.catalog.clients.items()):
            if record.query.serving_rr == serving_rr and record.loaded:
                lost.setdefault(record.query.server, []).append(query_id)
        self.settle_listed(serving_rr)  # nobody holds them there any more
        for server, ids in sorted(lost.items()):
            logger.warning(
                "registrar %s: %s is gone and nobody will restart it: FATAL to the %d "
                "queries held at %s/%s, and they are forgotten",
                self.registrar.name,
                serving_rr,
                len(ids),
                serving_rr,
                server,
            )
            self.report_lost(
                f"{serving_rr}/{server}",
                tuple(ids),
                "the provider is gone and nobody will restart it",
                forgotten="provider lost",
            )

    def report_lost(
        self,
        source: str,
        ids: tuple[str, ...],
        why: str = (
            "the provider no longer knows this query (it lost it in a restart, or it was "
            "held at a registrar of its name that yielded it: rule 22)"
        ),
        *,
        forgotten: str,
    ) -> None:
        """`FATAL` to the status callbacks of `ids` (and up their dependents), then forget them.

        Delivered as a provider's `StatusNotice` would be (rule 9), on this thread: the
        callbacks and the dependents it reaches are taken from the records before they
        are forgotten, right after. `forgotten` is the reason their `QueryForgotten` says.
        """
        notice = StatusNotice(
            ids,
            Status.FATAL,
            why,
            source,
            str(uuid.uuid4()),
            FutureReply(),  # (nobody waits for the acknowledgements)
            sent_at=time.time(),
        )
        self.redeliver(notice)
        for query_id in ids:
            self.holdings.forget(query_id, commit=False, reason=forgotten)
        self.registrar.commit()
