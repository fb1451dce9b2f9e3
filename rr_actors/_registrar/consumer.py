"""The consumer side of a registrar actor: a call's life here, from its answer to its release.

```
 calls.py (the caller's thread) ─► ClientLoaded | DurableLoaded, CallFailed
 Answers   on_client_loaded ─► decide(durable, withdrawn, dependency, stopping,
   │         owner_gone) ─► Action (pure: tests/registrar/test_consumer.py's table)
   │           KEEP | COMMIT ─► keep: the record (committed with its CallAnswered;
   │           nothing was written before the Load left: presumed abort, `calls.py`)
   │           LEAVE | GIVE_BACK | REFUSE | FORGET | RELEASE_LATE ─► not_kept:
   │           the id given back to its provider (`messages.give_back`)
   │       on_call_failed ─► the record forgotten (kept: a failed retry of a held id)
   ▼
 Flights   in_flight: query id ─► InFlight, while a call is not settled:
   │         unsettled_at  the provider of a call that failed as it died or stopped (not
   │                       one its caller withdrew first: `retry_held_at`): it may hold
   │                       the id (a retry may come) ─► listed in the next Reconcile;
   │                       still held there ─► kept_for_retry (listed in each Reconcile
   │                       its life asks for, released by the first to its next life, or
   │                       given back when this one stops or the load that made it ends)
   │         parked        notices (StatusNotice, Revoke, ResponseUpdated) that
   │                       overtook their answer ─► handled again once it came
   │       take_outcomes: the outcomes callers handed over, before each message
   ▼
 Holdings  the client records' companions: status callbacks (the plain ones published
   │       to the status desk, `status.py`), the epoch each answer came in, the records
   │       a restore listed, the client actors; Revoke, ResponseUpdated, set a callback;
   │       forget(id): the one place a held id goes (its QueryForgotten, then committed)
   ▼
 Releases  Release (the handle's unload) ─Unload─► provider ─► the statuses its answer
   │       carries (on their way to the id, maybe overtaken: rule 9) delivered as their
   │       StatusNotices ─► forget ─► answered once their callbacks ran; a resource's
   │       dependencies (`provider.py`'s teardown) the same way; the provider died or
   │       stopped meanwhile ─► unreleased: left out of its next Reconcile, so it
   │       releases them (its unload runs once); this registrar stops ─► its durable
   │       calls withdrawn, the ids of failed calls and releases given back (Abandon):
   │       the stop goes on once each provider answered (or could not be reached)
   ▼
 Reconciling  it serves (again), or a provider asks (ReconcileAsk, `asked`; retried by
          `life.py`'s presence until answered) ─► Reconcile(the ids held there: a
          Listing, its epoch; and this run, `Shared.life`); restored, or restarted
          without a backup (LostEverything): with every registrar of the system ─► the
          provider releases the others (presumed abort), gives up their loads under way,
          refuses the earlier runs' Loads, names those it no longer knows ─► FATAL to
          each answered before the list left (and up its dependents), then forgotten
          (rule 20); a provider lost for good ─► lose_provider: the same (rule 19)
```

Each part owns its state and changes another's through its methods only, all on the
actor's thread: docs/explanation/inside.md, "The consumer's parts".
"""

from __future__ import annotations

import dataclasses
import enum
import logging
from collections.abc import Callable, Collection, Iterable
from typing import Any

import pykka

from rr_actors import events
from rr_actors._catalog import ClientRecord, ResourceState
from rr_actors._core import hlc as _hlc
from rr_actors._core import runtime, traces
from rr_actors._core.actor import Actor, refuse
from rr_actors._core.directory import DIRECTORY, Reply
from rr_actors._core.replies import FutureReply, Join
from rr_actors._registrar.calls import (
    AttemptState,
    CallAttempt,
    CallFailed,
    ClientLoaded,
    DueAnswers,
    DurableLoaded,
)
from rr_actors._registrar.display import ClientTexts
from rr_actors._registrar.messages import (
    Abandon,
    Fetch,
    FetchVia,
    ListClientQueries,
    LostEverything,
    OpenClient,
    Reconcile,
    ReconcileAsk,
    Release,
    ResponseUpdated,
    Revoke,
    SetStatusCallback,
    StatusNotice,
    Unload,
    UnloadOverran,
    check_picklable,
    give_back,
)
from rr_actors._registrar.state import NO_REPLY, Phase, Shared
from rr_actors._types import Query, Status, StatusCallback
from rr_actors.errors import (
    CallTimeoutError,
    CatalogWriteError,
    ConfigError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
    UnknownQueryError,
)

__all__ = [
    "GONE",
    "Action",
    "Answers",
    "ClientActor",
    "Clients",
    "Flights",
    "Holdings",
    "InFlight",
    "Listing",
    "Notice",
    "Reconciling",
    "Releases",
    "answer_event",
    "decide",
    "publish_answered",
    "publish_failed",
    "publish_forgotten",
    "publish_refused",
    "retry_held_at",
]

logger = logging.getLogger("rr_actors")


# -- one call in flight ----------------------------------------------------------------


@dataclasses.dataclass(eq=False)
class InFlight:
    """What a consumer knows of one query id whose call is not settled yet."""

    unsettled_at: str | None = None
    parked: list[StatusNotice | Revoke | ResponseUpdated] = dataclasses.field(default_factory=list)

    def idle(self) -> bool:
        """Whether nothing is left of it (the consumer then forgets the record)."""
        return self.unsettled_at is None and not self.parked


class Action(enum.Enum):
    """What the consumer does with one call's answer (`decide`)."""

    KEEP = "keep"
    """A plain call's answer: record it (its caller has it already)."""
    COMMIT = "commit"
    """A durable call's answer: commit its record, then answer its caller (or, if it
    cannot be stored or written, give the id back and fail the call)."""
    LEAVE = "leave"
    """A durable answer its caller withdrew: nothing here (the caller gave the id back,
    and nothing was written before its `Load` left)."""
    GIVE_BACK = "give back"
    """A durable answer withdrawn or failed by a stop, while this registrar stops: give
    the id back (the stop's `Abandon` may have gone first)."""
    REFUSE = "refuse"
    """A durable top-level answer while this registrar stops: give the id back; its
    caller gets `RegistrarStoppedError`."""
    FORGET = "forget"
    """A plain top-level answer while this registrar stops: give the id back (its caller
    has the answer; the stop would have released it)."""
    RELEASE_LATE = "release late"
    """A dependency whose resource failed or is unloading: give the id back at once
    (nothing could release it later); the call itself succeeded (rule 4)."""


def decide(
    *, durable: bool, withdrawn: bool, dependency: bool, stopping: bool, owner_gone: bool
) -> Action:
    """What the consumer does with a call's answer (pure: no state read or written).

    Args:
        durable: the answer is a `DurableLoaded` (this actor answers the caller).
        withdrawn: a durable answer whose attempt this actor could not take (its caller
            withdrew it, or a stop failed it); never for a plain answer.
        dependency: the call was made inside a load (its record has a parent).
        stopping: this registrar is stopping.
        owner_gone: the resource the dependency belongs to failed or is unloading.

    Returns:
        The `Action` to run.
    """
    if withdrawn:
        return Action.GIVE_BACK if stopping else Action.LEAVE
    if stopping and not dependency:
        return Action.REFUSE if durable else Action.FORGET
    if owner_gone:
        return Action.RELEASE_LATE
    return Action.COMMIT if durable else Action.KEEP


# -- calls in flight -------------------------------------------------------------------


Notice = StatusNotice | Revoke | ResponseUpdated
"""What a provider tells a consumer about queries it holds."""


class Flights:
    """This registrar's calls whose outcome is not settled yet, by query id."""

    def __init__(self, shared: Shared, due: DueAnswers, redeliver: Callable[[Any], None]) -> None:
        self.registrar = shared
        self.due = due  # the ids whose answers are on their way (callers' threads too)
        self.redeliver = redeliver  # handles a message as the actor does (its dispatch)
        self.in_flight: dict[str, InFlight] = {}
        self.kept_for_retry: dict[str, str] = {}  # query id -> the provider that kept it
        # query id -> the life of that provider that kept it (its `ReconcileAsk.life`;
        # "": not known), of the ids in `kept_for_retry`
        self.kept_in: dict[str, str] = {}
        # query id -> the resource whose load made it, of the unsettled or kept ids above
        # that a load made (a dependency): its retry can only come from that load
        self.dependency_of: dict[str, str] = {}

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

    def reset(self, query_id: str, provider: str | None, parent: str | None = None) -> None:
        """A new outcome of `query_id`'s call: where it may be held now (`settle`), and
        it is no longer one its provider kept for a retry; `parent`: the resource whose
        load made the call (`take_dependencies` gives the id back when that load ends)."""
        self.settle(query_id, provider)
        self.unkeep(query_id)
        if provider is not None and parent is not None:
            self.dependency_of[query_id] = parent

    def unkeep(self, query_id: str) -> str | None:
        """`query_id` is no longer kept for a retry: the provider that kept it, if any."""
        self.kept_in.pop(query_id, None)
        return self.kept_for_retry.pop(query_id, None)

    def kept_at(self, serving_rr: str, life: str) -> set[str]:
        """The ids `serving_rr` kept for a retry in its life `life` ("": not known), to
        list in a `Reconcile` to that life: it keeps them for a retry still. Those a
        known earlier life kept are left out: its restart since (a new life) releases
        them, as no retry came while it lived (rule 17). A provider asks more than once
        in one life (as it starts, and once its carrier serves it: rule 20), so "the
        next `Reconcile`" would release them too early, before the retry they are kept
        for (issue 51)."""
        return {
            query_id
            for query_id, provider in self.kept_for_retry.items()
            if provider == serving_rr and (not life or self.kept_in[query_id] in ("", life))
        }

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
        lost = set(unknown)
        for query_id, provider in list(self.kept_for_retry.items()):
            if provider != serving_rr:
                continue
            if listing is None or query_id not in listing.held or query_id in lost:
                self.unkeep(query_id)
            elif listing.life and not self.kept_in.get(query_id):
                self.kept_in[query_id] = listing.life  # (the life that keeps it, now known)
        for query_id, provider in self.unsettled().items():
            if provider == serving_rr and (
                listing is None or query_id in listing.held or query_id in listing.left_out
            ):
                self.settle(query_id, None)
                if listing is not None and query_id in listing.held and query_id not in lost:
                    self.kept_for_retry[query_id] = serving_rr
                    self.kept_in[query_id] = listing.life

    def take_dependencies(self, rid: str) -> list[tuple[str, str]]:
        """Resource `rid`'s load ended (it failed, or the resource is unloading): the ids
        of the calls it made that failed as their provider died or was cut off (also
        those the provider kept for a retry), with their providers, to give back; no
        retry can come from a load that ended, and nothing else would release them
        while this registrar and that provider live. It no longer counts them held."""
        taken = []
        for query_id, parent in list(self.dependency_of.items()):
            if parent != rid:
                continue
            del self.dependency_of[query_id]
            flight = self.in_flight.get(query_id)
            if flight is not None and flight.unsettled_at is not None:
                taken.append((query_id, flight.unsettled_at))
                self.settle(query_id, None)
            elif query_id in self.kept_for_retry:
                provider = self.unkeep(query_id)
                assert provider is not None
                taken.append((query_id, provider))
        return taken

    def take_unsettled(self) -> list[tuple[str, str]]:
        """This registrar stops: the ids of calls that failed as their provider died,
        which it would no longer retry (also those the provider kept for a retry when it
        reconciled), with their providers, to give back; it no longer counts them held."""
        taken = list(self.unsettled().items())
        for query_id, _serving_rr in taken:
            self.settle(query_id, None)
        taken += self.kept_for_retry.items()
        self.kept_for_retry.clear()
        self.kept_in.clear()
        return taken

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
        for call in self.due.durable_calls():
            call.attempt.fail(error)
        for flight in self.in_flight.values():
            for notice in flight.parked:
                if not isinstance(notice, Revoke):  # (a revoke wants no answer)
                    notice.reply.set_error(error)
            flight.parked.clear()
        for query_id in list(self.in_flight):
            self.landed(query_id)


# -- what a call's outcome tells -------------------------------------------------------


def answer_event(
    shared: Shared, record: ClientRecord, attempt: CallAttempt, *, retry: bool
) -> tuple[events.Event, ...]:
    """`CallAnswered` of `record` (none while nobody listens), to commit with its record;
    `attempt`: its call's (when it began, its trace context)."""
    if not shared.events.active:
        return ()
    query = record.query
    return (
        events.CallAnswered(
            shared.name,
            query.id,
            query.serving_rr,
            query.server,
            record.parent,
            retry,
            attempt.started,
            attempt.trace,
            attempt.caller_span,
        ),
    )


def publish_answered(
    shared: Shared, record: ClientRecord, attempt: CallAttempt, *, retry: bool
) -> None:
    """Publish `CallAnswered`: `record`'s answer is recorded (`retry`: its id was known)."""
    shared.publish(*answer_event(shared, record, attempt, retry=retry))


def publish_failed(shared: Shared, message: CallFailed, *, retry: bool) -> None:
    """Publish `CallWithdrawn` or `CallFailed` for a call's failure `message`.

    An error answer to an attempt its caller withdrew first (the provider's answer to
    the `Abandon` that followed its `Load`) publishes nothing: the withdrawal was the
    call's outcome.
    """
    if not shared.events.active:
        return
    if not message.withdrawn and message.attempt.state is AttemptState.WITHDRAWN:
        return
    attempt = message.attempt
    if message.withdrawn:
        shared.events.publish(
            events.CallWithdrawn(
                shared.name,
                message.query_id,
                message.provider,
                message.server,
                message.why,
                attempt.started,
                attempt.trace,
                attempt.caller_span,
            )
        )
        return
    error = message.error
    shared.events.publish(
        events.CallFailed(
            shared.name,
            message.query_id,
            message.provider,
            message.server,
            type(error).__name__ if error is not None else "",
            str(error) if error is not None else "",
            message.serving_rr is not None,
            retry,
            attempt.started,
            attempt.trace,
            attempt.caller_span,
        )
    )


def publish_refused(
    shared: Shared, query: Query, error: BaseException, attempt: CallAttempt
) -> None:
    """Publish `CallFailed`: a durable call's answer was not kept (given back), `error`."""
    if shared.events.active:
        shared.events.publish(
            events.CallFailed(
                shared.name,
                query.id,
                query.serving_rr,
                query.server,
                type(error).__name__,
                str(error),
                started=attempt.started,
                trace=attempt.trace,
                caller_span=attempt.caller_span,
            )
        )


Began = tuple[int, int, str, str]
"""How a release began: its `QueryForgotten`'s `unload_sent`, `reconciled`, `trace` and
`caller_span` (`Releases.send_unload`)."""

NOT_BEGUN: Began = (0, 0, "", "")


def publish_forgotten(shared: Shared, query: Query, reason: str, began: Began = NOT_BEGUN) -> None:
    """Publish `QueryForgotten`: the consumer no longer holds `query` (`reason`; `began`:
    its release's stamps, `Holdings.forget`)."""
    if shared.events.active:
        shared.events.publish(
            events.QueryForgotten(shared.name, query.id, query.serving_rr, reason, *began)
        )


def _nothing() -> None:
    """What a forgotten record's commit answers: nothing (`Holdings.forget`)."""


def _ignored(_error: BaseException) -> None:
    """A forgotten record whose write failed stays forgotten: written with the next one."""


# -- answers ---------------------------------------------------------------------------


class Answers:
    """Records the answers to this registrar's calls, and their failures."""

    def __init__(
        self, shared: Shared, flights: Flights, holdings: Holdings, texts: ClientTexts
    ) -> None:
        self.registrar = shared
        self.flights = flights
        self.holdings = holdings
        self.texts = texts

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
            self.act(action, message, retry=retry)
        except BaseException as exc:  # an attempt taken must be settled on every path
            if durable and not withdrawn:
                message.attempt.settle(error=exc)  # (no-op if it was)
            raise

    def act(self, action: Action, message: ClientLoaded, *, retry: bool) -> None:
        """Run `action` on `message`'s answer (`flight.Action` says what each does).

        `retry`: the id was held or failed as its provider died before.
        """
        query = message.record.query
        match action:
            case Action.KEEP | Action.COMMIT:
                self.keep(message, retry=retry)
            case Action.LEAVE:
                pass  # its caller gave the id back
            case Action.GIVE_BACK:
                self.not_kept(query)
            case Action.REFUSE:
                self.not_kept(query)
                error = RegistrarStoppedError(
                    f"registrar {self.registrar.name!r} stopped during the call"
                )
                publish_refused(self.registrar, query, error, message.attempt)
                message.attempt.settle(error=error)
            case Action.FORGET:  # its caller has the answer, given back here
                attempt = message.attempt  # (both before the commit)
                publish_answered(self.registrar, message.record, attempt, retry=False)
                publish_forgotten(self.registrar, query, "registrar stopped")
                self.not_kept(query)
            case Action.RELEASE_LATE:
                publish_answered(self.registrar, message.record, message.attempt, retry=retry)
                publish_forgotten(self.registrar, query, "late dependency")
                self.give_back_late_dependency(message)

    def keep(self, message: ClientLoaded, *, retry: bool) -> None:
        """Record an answer (`Action.KEEP`), or commit a durable one and answer its
        caller (`Action.COMMIT`)."""
        catalog = self.registrar.catalog
        query = message.record.query
        durable = isinstance(message, DurableLoaded)
        if durable and self.unstorable(message):
            return
        if query.id in catalog.clients:  # a retry of one held (or a record restored
            catalog.client_loaded(query.id, query.response)  # pending, an older backup)
        else:
            catalog.add_client(message.record)
            self.texts.added(message.record)
        told = answer_event(self.registrar, message.record, message.attempt, retry=retry)
        if durable:
            self.keep_durable(message, told)
            return
        if self.registrar.commit(*told) is not None:  # (written with its record)
            self.registrar.publish(*told)  # kept in memory: written with the next write
        self.holdings.held(query.id, message.on_status)

    def keep_durable(self, message: ClientLoaded, told: tuple[events.Event, ...]) -> None:
        """Commit a durable call's answer with its `CallAnswered` (with the rest of the
        turn), then answer its caller; not written: give the id back, fail the call."""
        query = message.record.query
        self.holdings.held(query.id, message.on_status)  # (a notice may come next)

        def undo(failed: CatalogWriteError) -> None:  # not kept
            give_back(query.serving_rr, query.id, self.registrar.name)
            self.holdings.forget(query.id, commit=False, reason=None)
            publish_refused(self.registrar, query, failed, message.attempt)
            message.attempt.settle(error=failed)

        def refuse(error: RrError) -> None:  # died before its commit: not kept either
            give_back(query.serving_rr, query.id, self.registrar.name)
            message.attempt.settle(error=error)

        def ok() -> None:
            message.attempt.settle(query.response)

        self.registrar.commit_then(*told, ok=ok, undo=undo, refuse=refuse)

    def unstorable(self, message: ClientLoaded) -> bool:
        """A durable call's response this catalog cannot store: give it back, fail the call.

        (A caller that records its own answer checks the response itself, see `calls.py`.)
        """
        query = message.record.query
        try:
            check_picklable(query.response, f"the response of '{query.serving_rr}/{query.server}'")
        except ConfigError as exc:
            self.not_kept(query)
            publish_refused(self.registrar, query, exc, message.attempt)
            message.attempt.settle(error=exc)
            return True
        return False

    def not_kept(self, query: Query) -> None:
        """An answer this registrar does not keep: give `query`'s id back to its provider
        (nothing was written for it before its `Load` left: presumed abort)."""
        give_back(query.serving_rr, query.id, self.registrar.name)

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
        self.not_kept(query)
        if isinstance(message, DurableLoaded):  # (taken by `record_answer`)
            message.attempt.settle(query.response)

    def on_call_failed(self, message: CallFailed, _reply: Reply) -> None:
        known = self.registrar.catalog.clients.get(message.query_id)
        publish_failed(
            self.registrar,
            message,
            retry=self.flights.was_unsettled(message.query_id)
            or (known is not None and known.loaded),
        )
        current = self.flights.due.durable_attempt(message.query_id)
        if current is None or current is message.attempt:
            # (set if it may hold the id: a retry may follow; settled, or unsettled again)
            self.flights.reset(message.query_id, retry_held_at(message), message.parent)
        record = self.registrar.catalog.clients.get(message.query_id)
        try:
            if current is not None and current is not message.attempt:
                pass  # a stale failure of an earlier attempt: a retry's is due
            elif record is not None and record.loaded and not message.withdrawn:
                pass  # a failed retry of an id this registrar holds: it still holds it
            elif record is not None:
                self.holdings.forget(message.query_id, reason="withdrawn")
        finally:
            self.flights.answered(message.query_id, message.attempt)


def retry_held_at(failed: CallFailed) -> str | None:
    """The provider that may hold the id of `failed`'s call for a retry, if any.

    One that died or stopped with the call on its way (`CallFailed.serving_rr`), unless
    the call's caller withdrew it first (its death then failed the `Load` of an attempt
    already given up, issue 51): that id was given back, no retry of it comes, and its
    `Abandon` may have died with the provider. It is not held for a retry, so the next
    `Reconcile` leaves it out and the restarted provider releases it (rules 17, 20).
    """
    if failed.withdrawn or failed.attempt.state is AttemptState.WITHDRAWN:
        return None
    return failed.serving_rr


# -- holdings --------------------------------------------------------------------------


class Holdings:
    """What goes with the client records of the queries this registrar holds."""

    def __init__(
        self,
        shared: Shared,
        flights: Flights,
        clients: Clients,
        targets: dict[str, tuple[Query, StatusCallback]],
    ) -> None:
        self.registrar = shared
        self.flights = flights
        self.clients = clients
        self.status_callbacks: dict[str, StatusCallback] = {}  # query id -> its callback
        self.targets = targets  # what the status desk of this process reads of it
        self.epoch = 0  # how many `Reconcile` lists it built (`new_epoch`)
        self.answered_in: dict[str, int] = {}  # query id -> its answer's epoch (none: 0)
        self.restored = set(shared.catalog.clients)  # listed by its `CatalogRestored`

    # -- holding and forgetting queries -------------------------------------------------

    def held(self, query_id: str, on_status: StatusCallback | None) -> None:
        """`query_id`'s answer was recorded now (in this `epoch`), with its status
        callback (if any)."""
        self.answered_in[query_id] = self.epoch  # (a reconcile's list left before?)
        if on_status is not None:
            self.status_callbacks[query_id] = on_status
            self.publish_target(query_id)

    def forget(
        self,
        query_id: str,
        *,
        commit: bool = True,
        reason: str | None = "unload",
        began: Began = NOT_BEGUN,
    ) -> None:
        """Forget a query this registrar held: its record and its status callback.

        With `commit=False` the caller commits (once, after forgetting several).
        `reason` is what its `QueryForgotten` says, published (before the commit) for a
        record whose holding was told: one answered here (`held`: its `CallAnswered`),
        or one a restore listed (`CatalogRestored`), answered or not (issue 40: a
        restored call in flight was dropped unannounced). `None`: the caller published it.
        `began`: for one forgotten on the answer to its release, the stamp its `Unload`
        left at and the stamp of the last `Reconcile` with its provider answered then
        (`Releases.reconciled`).
        """
        record = self.registrar.catalog.clients.get(query_id)
        if record is not None:
            told = query_id in self.answered_in or query_id in self.restored
            self.restored.discard(query_id)
            if told and reason is not None:
                publish_forgotten(self.registrar, record.query, reason, began)
            self.registrar.catalog.remove_client(query_id)
            self.status_callbacks.pop(query_id, None)
            self.targets.pop(query_id, None)
            self.answered_in.pop(query_id, None)
            if commit and self.registrar.in_turn:  # (with the rest of the turn: an answer
                self.registrar.commit_then(ok=_nothing, undo=_ignored, refuse=_ignored)
            elif commit:  # after it waits for it)
                self.registrar.commit()

    def callback_of(self, query_id: str) -> StatusCallback | None:
        """The client status callback of query `query_id`, if it has one."""
        return self.status_callbacks.get(query_id)

    def publish_target(self, query_id: str) -> None:
        """Let the status desk of this process run `query_id`'s callback without this
        mailbox (`status.py`): a loaded query with a callback that is not a dependency
        (a dependency's status climbs from here, on this actor)."""
        record = self.registrar.catalog.clients.get(query_id)
        callback = self.status_callbacks.get(query_id)
        if record is None or callback is None or record.parent is not None or not record.loaded:
            self.targets.pop(query_id, None)
        else:
            self.targets[query_id] = (record.query, callback)

    # -- the epochs of `Reconcile` lists (`Reconciling`) --------------------------------

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
        if self.registrar.saver.store is not None:  # refused, as an answer it cannot store is
            check_picklable(message.response, "the new response")  # (a ConfigError answer)
        for query_id in message.query_ids:
            self.registrar.catalog.client_loaded(query_id, message.response)
            if query_id in self.targets:  # (its query says the new response)
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
        """The client actor for `target_rr/server`, started on first use (thesis 4.3.3)."""
        ref = self.registrar.ref
        assert ref is not None
        client = self.clients.start(ref, self.registrar.name, message.target_rr, message.server)
        reply.set_result(client)


# -- releases --------------------------------------------------------------------------


GONE = (RegistrarUnavailableError, RegistrarStoppedError)
"""Errors of a provider that died or was stopped: what was sent may or may not have run."""


class Releases:
    """Releases the queries this registrar holds, and gives back what it gives up."""

    def __init__(
        self,
        shared: Shared,
        flights: Flights,
        holdings: Holdings,
        answers: Answers,
        redeliver: Callable[[Any], None],
    ) -> None:
        self.registrar = shared
        self.flights = flights
        self.holdings = holdings
        self.answers = answers
        self.redeliver = redeliver  # handles a message as the actor does (its dispatch)
        # ids whose `Unload` is on its way -> (the stamp it left at, `reconciled` then)
        self.releasing: dict[str, Began] = {}
        # provider -> the stamp of the last `Reconcile` with it answered (its list left)
        self.last_reconciled: dict[str, int] = {}
        # id -> provider, of releases that failed as it died or stopped (`release_later`)
        self.unreleased: dict[str, str] = {}

    # -- releasing one query ------------------------------------------------------------

    def release_dependencies(
        self,
        rid: str,
        then: Callable[[], None],
        only: Collection[str] | None = None,
        trace: str = "",
    ) -> None:
        """Release every query resource `rid` holds as a dependency (`only`: those of
        these query ids, a classroom's copy of `release_order`); then `then()`. `trace`:
        the traceparent of the `Unload` that unloads `rid` (its releases are its SERVER
        span's calls, `_core/traces.py`), `""`: untraced."""
        join = Join(then)
        for record in self.registrar.catalog.dependencies(rid):
            if only is None or record.query.id in only:
                self.release_client(record, join.add(), traces.under(trace) if trace else None)
        for query_id, serving_rr in self.flights.take_dependencies(rid):
            give_back(serving_rr, query_id, self.registrar.name)
        join.seal()

    def release_client(
        self,
        record: ClientRecord,
        then: Callable[[], None],
        begun: tuple[str, str] | None = None,
    ) -> None:
        """Unload one query this registrar holds; the record goes whatever the answer
        (`begun`: the trace context it is released in, as `send_unload`'s).

        A provider that cannot be reached keeps the id until it reconciles with this
        registrar after its restart (`reconcile`), which releases it (`unreleased`).
        """
        query = record.query

        def answered(on_its_way: Any, error: BaseException | None) -> None:
            began = self.releasing.pop(query.id, NOT_BEGUN)
            if error is not None and not isinstance(error, UnknownQueryError):
                logger.warning("releasing %s at %s failed: %s", query.id, query.serving_rr, error)
            if isinstance(error, GONE):
                self.unreleased[query.id] = query.serving_rr
            join = Join(then)
            self.deliver_on_its_way(query.id, on_its_way, join)
            self.holdings.forget(
                query.id, reason="stop" if record.parent is None else "dependency", began=began
            )
            join.seal()

        self.send_unload(query, answered, begun)

    def on_release(self, message: Release, reply: Reply) -> None:
        query_id = message.query_id
        record = self.registrar.catalog.clients.get(query_id)
        if record is None or not record.loaded:
            catalog = self.registrar.catalog
            if record is None and catalog.has_consumer(query_id):  # (a provider's own id)
                resource = catalog.resource_of(query_id)
                raise UnknownQueryError(
                    f"query id {query_id!r} is a consumer id of "
                    f"{self.registrar.name}/{resource.server}, held by "
                    f"{resource.consumers[query_id]!r}: only that registrar unloads it"
                )
            raise UnknownQueryError(f"unknown or released query id {query_id!r}")
        query = record.query

        def answered(on_its_way: Any, error: BaseException | None) -> None:
            began = self.releasing.pop(query_id, NOT_BEGUN)
            if isinstance(error, GONE):  # it may or may not have run it: reconciling
                reply.set_error(self.release_later(query, error, began))  # completes it
                return
            # The provider released the id unless it failed otherwise: it was unknown
            # there, or its unload callback overran `unload_timeout` (a CallTimeoutError
            # only the provider's `UnloadOverran` carries here; the caller's own is its
            # handle's).
            released = error is None or isinstance(error, UnknownQueryError | CallTimeoutError)
            if not released:
                reply.set_error(error)  # type: ignore[arg-type]  # e.g. its backup is full
                return
            if isinstance(error, UnknownQueryError):
                logger.warning("provider %s no longer knew %s", query.serving_rr, query.id)

            def answer() -> None:  # (once the statuses on their way were delivered)
                if isinstance(error, CallTimeoutError):
                    reply.set_error(error)
                else:
                    reply.set_result(None)

            join = Join(answer)
            self.deliver_on_its_way(query_id, on_its_way, join)
            self.holdings.forget(query_id, began=began)
            join.seal()

        self.send_unload(query, answered, message.begun)

    def send_unload(
        self,
        query: Query,
        answered: Callable[[Any, BaseException | None], None],
        begun: tuple[str, str] | None = None,
    ) -> None:
        """Ask `query`'s provider to release its id; `answered(on_its_way, error)` runs on
        the answer. An `UnloadOverran` (released, its `unload` overran) comes to it as its
        statuses on their way and its `CallTimeoutError`. The release begins now: its
        `QueryForgotten` gives this stamp and that of the last `Reconcile` with its
        provider answered before (`reconciled`): a release that left before the
        reconcile with the provider's restart was answered crossed the restart. `begun`:
        the trace context of the caller of `unload` (`_core/traces.py`), which the
        `Unload` and the `QueryForgotten` carry."""

        def opened(value: Any, error: BaseException | None) -> None:
            if isinstance(value, UnloadOverran):
                answered(value.on_its_way, value.error)
            else:
                answered(value, error)

        trace, caller_span = begun if begun is not None else ("", "")
        self.releasing.setdefault(
            query.id,
            (_hlc.CLOCK.now(), self.last_reconciled.get(query.serving_rr, 0), trace, caller_span),
        )
        self.registrar.send(
            query.serving_rr,
            lambda reply: Unload(query.id, self.registrar.name, reply, trace),
            opened,
        )

    def deliver_on_its_way(self, query_id: str, on_its_way: Any, join: Join) -> None:
        """Deliver the statuses the answer to `query_id`'s `Unload` carried, before the id
        is forgotten; each is a part of `join`, done once its callbacks ran.

        They are the statuses its provider sent on to it before it released the id,
        whose acknowledgements had not come (`StatusOnItsWay`s, `provider.py`'s
        `Unloading.on_unload`): on another connection than the answer, they may come
        after it and find the id forgotten. Each is handled as its `StatusNotice` would
        be (rule 9: its callback, and up a dependency's path); one that came its own way
        first is not delivered again, nor one that comes after (`status.py` takes each
        status to an id once).
        """
        for status in on_its_way or ():
            self.redeliver(status.notice((query_id,), self.registrar.come_back(join.add())))

    def release_later(
        self, query: Query, error: BaseException, began: Began = NOT_BEGUN
    ) -> RrError:
        """The `Unload` of `query` failed as its provider died or stopped (`error`).

        This registrar gave the id up: it forgets it now (a second `unload` raises
        `UnknownQueryError`) and keeps it as `unreleased` until the provider's next
        `Reconcile` was answered, which does not list it: the provider releases it if it
        still holds it (its `unload` runs once), and nobody hears `FATAL` for it (its
        consumer asked to release it). Returns the error for the caller, which says so.
        """
        self.unreleased[query.id] = query.serving_rr
        self.holdings.forget(query.id, reason="unload unanswered", began=began)
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

    # -- what `Reconciling` asks of it --------------------------------------------------

    def reconciled(self, serving_rr: str, listing: Listing) -> None:
        """`serving_rr` answered the `Reconcile` of `listing`: the releases that leave from
        now on began after it (their `QueryForgotten.reconciled`); an id it no longer
        knew was reported `FATAL` then, unless its release was on its way."""
        last = self.last_reconciled.get(serving_rr, 0)
        self.last_reconciled[serving_rr] = max(last, listing.at)

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

    def withdraw_pending(self, error: RrError, given_back: Join) -> None:
        """This registrar stops: give up its durable top-level calls in flight (those not
        answered yet); their callers get `error`, their ids are given back.

        Each provider's answer is a part of `given_back` (`give_back_before_stop`). One
        answered meanwhile finds its attempt failed: its id is given back too (`decide`).
        """
        for call in self.flights.due.durable_calls():
            if call.parent is not None or not call.attempt.fail_open(error):
                continue  # (a dependency: its load's end settles it; or its outcome comes)
            self.give_back_before_stop(call.serving_rr, call.query_id, given_back)
            self.answers.on_call_failed(
                CallFailed(
                    call.query_id,
                    call.attempt,
                    withdrawn=True,
                    provider=call.serving_rr,
                    server=call.server,
                    why="registrar stopped",
                ),
                NO_REPLY,
            )

    def give_back_unsettled(self, given_back: Join) -> None:
        """This registrar stops: give back the ids of calls that failed as their provider
        died, which it would no longer retry (also those the provider kept for a retry
        when it reconciled: `Flights`), and of releases that failed so. Each provider's
        answer is a part of `given_back` (`give_back_before_stop`)."""
        for query_id, serving_rr in self.flights.take_unsettled():
            self.give_back_before_stop(serving_rr, query_id, given_back)
        for query_id, serving_rr in self.unreleased.items():
            self.give_back_before_stop(serving_rr, query_id, given_back)
        self.unreleased.clear()

    def give_back_before_stop(self, serving_rr: str, query_id: str, given_back: Join) -> None:
        """Give `query_id` back to `serving_rr` (an `Abandon` that wants an answer); its
        answer, or the error of a provider that cannot be reached, is a part of
        `given_back`: the stop ends only after it (rule 12). Told and not waited for,
        an `Abandon` could reach the provider after its own stop (its supervisor stops it
        next), which would then hold the id for a consumer that stopped. A provider that
        cannot be reached releases it when it reconciles (its restart finds this
        registrar stopped: `Unloading.release_stopped`)."""
        done = given_back.add()

        def answered(_: Any, error: BaseException | None) -> None:
            if error is not None:
                logger.debug("giving %s back to %s failed: %s", query_id, serving_rr, error)
            done()

        self.registrar.send(
            serving_rr, lambda reply: Abandon(query_id, self.registrar.name, reply), answered
        )


# -- reconciling -----------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Listing:
    """What one `Reconcile` told a provider, as it was when the list left.

    Its answer ("the ids of the list I do not know") is about the catalog as it was
    then: only records answered before it left (`epoch`) are settled by it. `left_out`:
    the ids whose release failed as the provider died (it releases them). `at`: the
    stamp (`hlc`) it left at.
    """

    held: tuple[str, ...]
    due: frozenset[str]
    left_out: frozenset[str]
    epoch: int
    life: str = ""  # the provider's life it was sent to (its `ReconcileAsk.life`; "": not known)
    at: int = 0


class Reconciling:
    """Reconciles what this registrar holds at providers with what they hold for it.

    `everyone`: with every registrar of the system, not only the providers its catalog
    names (set when it restores a backup, or when its supervisor says it restarted
    without one: `LostEverything`); `asked_to_reconcile`: providers that asked while
    setup ran.
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

    def listing(
        self,
        serving_rr: str,
        due: frozenset[str],
        withdrawn: frozenset[str] = frozenset(),
        life: str = "",
    ) -> Listing:
        """The list of a `Reconcile` to `serving_rr` that leaves now, a new epoch (`due`:
        the ids whose answer is due now, at any provider: listed too, harmless, reported
        unknown). `withdrawn`: the ids of calls whose callers withdrew them and whose
        `CallFailed` this actor has not handled yet: given back, never listed, so the
        provider releases them if their `Abandon` died with its last run (rule 17).
        `life`: the provider's life that asked for it ("": not known); the ids it kept
        for a retry in that life are listed again (`Flights.kept_at`)."""
        held = {
            query_id
            for query_id, record in self.registrar.catalog.clients.items()
            if record.query.serving_rr == serving_rr
        }
        held |= {q for q, provider in self.flights.unsettled().items() if provider == serving_rr}
        held |= self.flights.kept_at(serving_rr, life)
        held |= due
        held -= withdrawn
        left_out = self.releases.unreleased_at(serving_rr)
        epoch = self.holdings.new_epoch()
        return Listing(tuple(sorted(held - left_out)), due, left_out, epoch, life, _hlc.CLOCK.now())

    def settle_listed(
        self, serving_rr: str, listing: Listing | None = None, unknown: Iterable[str] = ()
    ) -> None:
        """`serving_rr` answered `listing`'s `Reconcile` (`unknown`: the listed ids it
        does not know): settle the failed calls and the releases it listed or left out.
        Without a listing (`serving_rr` is gone for good): all of them."""
        self.flights.settle_listed(serving_rr, listing, unknown)
        self.releases.settle_listed(serving_rr, listing)

    def asked(self, message: ReconcileAsk) -> bool:
        """A provider asks for a `Reconcile` (`ReconcileAsk`): whether to send it now
        (`life.py`'s presence sends it, retried until answered). Not if nothing is held
        there and the ask went to every registrar; while setup runs, once it is done."""
        if not message.holds_yours and not self.holds_at(message.serving_rr):
            return False  # (told as every registrar of the system is: nothing to reconcile)
        if self.registrar.phase is Phase.SETTING_UP:  # its status callbacks are not attached yet
            self.asked_to_reconcile.add(message.serving_rr)
            return False
        return True

    def on_lost_everything(self, _message: LostEverything, _reply: Reply) -> None:
        """Its supervisor restarted it without a backup (`life.py`'s `lost_everything`):
        its last run's ids are held at providers no row names, for nobody now. It
        reconciles with every registrar of the system (now, or once setup is done), and
        from now on as one restored from a backup does (`everyone`): each provider
        releases the ids of it that the list does not name (rule 20)."""
        self.everyone = True
        if self.registrar.phase is Phase.SERVING:  # (during setup `on_ready` reconciles)
            self.reconcile_all()

    def reconcile(
        self,
        serving_rr: str,
        then: Callable[[BaseException | None], None] | None = None,
        life: str = "",
        ask: int = 0,
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
        failed (`life.py`'s presence retries). `life`: the provider's life that asked
        (its `ReconcileAsk.life`; "": not known); `ask`: its `ReconcileAsk.round`, echoed.
        """
        with self.due.frozen() as (due, withdrawn):
            listing = self.listing(serving_rr, due, withdrawn, life)
            self.registrar.send(
                serving_rr,
                lambda reply: Reconcile(
                    self.registrar.name, listing.held, reply, self.registrar.life, ask
                ),
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
        self.releases.reconciled(serving_rr, listing)
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
            runtime.new_id(),
            FutureReply(),  # (nobody waits for the acknowledgements)
            sent_at=runtime.wall(),
        )
        self.redeliver(notice)
        for query_id in ids:
            self.holdings.forget(query_id, commit=False, reason=forgotten)
        self.registrar.commit()


# -- client actors ---------------------------------------------------------------------


class ClientActor(Actor):
    """The consumer-side endpoint for one target server: it relays fetches."""

    def __init__(
        self,
        registrar_ref: pykka.ActorRef[Any],
        origin_rr: str,
        target_rr: str,
        server: str,
    ) -> None:
        super().__init__()
        self.registrar_ref = registrar_ref
        self.origin_rr = origin_rr
        self.target_rr = target_rr
        self.server = server

    def on_late(self, envelope: Any) -> None:
        """A fetch that reached this client after it ended is answered, not dropped."""
        refuse(envelope)
        reply = getattr(envelope.message, "reply", None)
        if reply is not None:
            reply.set_error(DIRECTORY.gone_error(self.origin_rr))

    def on_receive(self, message: Any) -> None:
        if isinstance(message, FetchVia):
            try:
                DIRECTORY.lookup(self.target_rr).tell(
                    Fetch(message.server, self.origin_rr, message.reply)
                )
            except RrError as exc:
                message.reply.set_error(exc)


class Clients:
    """A registrar's client actors by `(target registrar, server)`: its one client cache.

    Its actor starts them (`start`, on the actor's thread) and stops them; its handle
    looks them up from any thread (`get`, one dict read).
    """

    __slots__ = ("_refs",)

    def __init__(self) -> None:
        self._refs: dict[tuple[str, str], pykka.ActorRef[ClientActor]] = {}

    def get(self, target_rr: str, server: str) -> pykka.ActorRef[ClientActor] | None:
        """The client actor for `target_rr/server`, if one was started (any thread)."""
        return self._refs.get((target_rr, server))

    def start(
        self, registrar_ref: pykka.ActorRef[Any], origin_rr: str, target_rr: str, server: str
    ) -> pykka.ActorRef[ClientActor]:
        """The client actor for `target_rr/server`, started on first use (actor thread)."""
        key = (target_rr, server)
        client = self._refs.get(key)
        if client is None:
            client = ClientActor.start(registrar_ref, origin_rr, target_rr, server)
            self._refs[key] = client
        return client

    def stop_all(self) -> None:
        """Stop every client actor (the registrar stops or died; actor thread)."""
        for client in list(self._refs.values()):
            client.stop(block=True, timeout=5.0)
