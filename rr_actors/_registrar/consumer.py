"""The consumer side of a registrar actor: a call's life here, from its answer to its release.

```
 calls.py (caller's thread) ─► ClientLoaded | DurableLoaded, CallFailed
 Answers   decide(...) ─► Action: KEEP | COMMIT the record, or give the id back
   │       (`messages.give_back`; nothing was written before the Load left)
   ▼
 Flights   in_flight: unsettled_at (its provider died with the call on its way: it
   │       may hold the id, a retry may come) ─► kept_for_retry; parked notices that
   │       overtook their answer, handled again once it came
   ▼
 Holdings  status callbacks, the epoch of each answer, the client actors;
   │       forget(id): the one place a held id goes
   ▼
 Releases  Release ─Unload─► provider ─► statuses its answer carries delivered ─►
   │       forget; provider down ─► unreleased (left out of its next Reconcile);
   │       this registrar stops ─► ids given back (Abandon), answered before it ends
   ▼
 Reconciling  Reconcile(ids held there, epoch, life) ─► the provider releases the
          others and names those it no longer knows ─► FATAL, forgotten (rules 19, 20);
          an answer of a run that is not the one it reconciles with: the list sent again
```

Each part owns its state and changes another's through its methods only, all on the
actor's thread: docs/explanation/inside.md, "The consumer's parts" and "The consumer's
reconcile".
"""

from __future__ import annotations

import contextlib
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
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._core.replies import FutureReply, Join
from rr_actors._platform.base import no_thread
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
    KeptUnclaimed,
    ListClientQueries,
    LostEverything,
    OpenClient,
    Reconcile,
    ReconcileAsk,
    Reconciled,
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
from rr_actors._registrar.state import NO_REPLY, Phase, Shared, life_order
from rr_actors._types import Query, Status, StatusCallback
from rr_actors.errors import (
    CallTimeoutError,
    CatalogWriteError,
    ConfigError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    ResourceLoadError,
    RrError,
    UnknownQueryError,
)

logger = logging.getLogger("rr_actors")


# -- one call in flight ----------------------------------------------------------------


@dataclasses.dataclass(eq=False)
class InFlight:
    """What a consumer knows of one query id whose call is not settled yet."""

    unsettled_at: str | None = None
    parked: list[StatusNotice | Revoke | ResponseUpdated] = dataclasses.field(default_factory=list)

    def idle(self) -> bool:
        return self.unsettled_at is None and not self.parked


class Action(enum.Enum):
    """What the consumer does with one call's answer (`decide`)."""

    KEEP = "keep"
    """A plain call's answer: record it (its caller has it already)."""
    COMMIT = "commit"
    """A durable call's answer: commit its record, then answer its caller."""
    LEAVE = "leave"
    """A durable answer its caller withdrew: nothing to do (the caller gave the id back)."""
    GIVE_BACK = "give back"
    """A durable answer withdrawn or failed by a stop, while this registrar stops: give it back."""
    REFUSE = "refuse"
    """A durable top-level answer while stopping: give it back; its caller gets a stop error."""
    FORGET = "forget"
    """A plain top-level answer while stopping: give the id back (its caller has the answer)."""
    RELEASE_LATE = "release late"
    """A dependency whose resource failed or is unloading: give the id back at once (rule 4)."""


def decide(
    *, durable: bool, withdrawn: bool, dependency: bool, stopping: bool, owner_gone: bool
) -> Action:
    """What the consumer does with a call's answer (pure: `withdrawn`: a durable attempt
    this actor could not take; `owner_gone`: the dependency's resource failed or unloads)."""
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


class ConsumerRecord(Shared):
    """The registrar's record (`Shared`) as its consumer side sees it: its parts, each the
    owner of its fields (another changes them through its methods), and what they read.
    The actor fills it (`actor.py`); a part holds the record, never another part."""

    due: DueAnswers  # the ids whose answers are on their way (callers' threads too)
    redeliver: Callable[[Any], None]  # handles a message as the actor does (its dispatch)
    clients: Clients
    targets: dict[str, tuple[Query, StatusCallback]]  # what the status desk here reads
    texts: ClientTexts  # its client records' texts, made before a snapshot reads them
    flights: Flights
    holdings: Holdings
    answers: Answers
    releases: Releases
    reconciling: Reconciling


class Flights:
    def __init__(self, registrar: ConsumerRecord) -> None:
        self.registrar = registrar
        self.in_flight: dict[str, InFlight] = {}
        self.kept_for_retry: dict[str, str] = {}  # query id -> the provider that kept it
        # query id -> the provider's life that kept it ("": not known)
        self.kept_in: dict[str, str] = {}
        # query id -> the resource whose load made it: a retry can only come from that load
        self.dependency_of: dict[str, str] = {}
        self.doubted: dict[str, set[str]] = {}  # due id -> providers whose reconcile knew not it
        self.forgetting: Notice | None = None  # FATAL of ids forgotten next: never parked

    # -- one call's record --------------------------------------------------------------

    def flight(self, query_id: str) -> InFlight:
        flight = self.in_flight.get(query_id)
        if flight is None:
            flight = self.in_flight[query_id] = InFlight()
        return flight

    def landed(self, query_id: str) -> None:
        flight = self.in_flight.get(query_id)
        if flight is not None and flight.idle():
            del self.in_flight[query_id]

    # -- calls that failed as their provider died (unsettled, then kept for a retry) ----

    def unsettled(self) -> dict[str, str]:
        """Query id -> provider, of calls that failed as their provider died (may hold the id)."""
        return {q: f.unsettled_at for q, f in self.in_flight.items() if f.unsettled_at}

    def settle(self, query_id: str, provider: str | None) -> None:
        if provider is not None:
            self.flight(query_id).unsettled_at = provider
        elif query_id in self.in_flight:
            self.in_flight[query_id].unsettled_at = None
            self.landed(query_id)

    def reset(self, query_id: str, provider: str | None, parent: str | None = None) -> None:
        """A new outcome of `query_id`'s call; `parent`: the load that made it."""
        self.settle(query_id, provider)
        self.unkeep(query_id)
        if provider is not None and parent is not None:
            self.dependency_of[query_id] = parent

    def unkeep(self, query_id: str) -> str | None:
        self.kept_in.pop(query_id, None)
        return self.kept_for_retry.pop(query_id, None)

    def kept_at(self, serving_rr: str, life: str) -> set[str]:
        """The ids `serving_rr` kept for a retry in its life `life` ("": not known), listed again
        to that life; an earlier life's are left out, so its restart releases them (rule 17)."""
        return {
            query_id
            for query_id, provider in self.kept_for_retry.items()
            if provider == serving_rr and (not life or self.kept_in[query_id] in ("", life))
        }

    def was_unsettled(self, query_id: str) -> bool:
        flight = self.in_flight.get(query_id)
        return flight is not None and flight.unsettled_at is not None

    def held_at(self, serving_rr: str) -> bool:
        return serving_rr in self.unsettled().values() or serving_rr in self.kept_for_retry.values()

    def settle_listed(
        self, serving_rr: str, listing: Listing | None, unknown: Iterable[str] = (), life: str = ""
    ) -> list[str]:
        """`serving_rr`'s run `life` answered `listing`'s `Reconcile`: keep for a retry (in that
        run) the failed calls it holds, forget those it released; no listing (it is gone for
        good): all of them. The ids kept for a retry from now on."""
        lost = set(unknown)
        kept: list[str] = []
        for query_id, provider in list(self.kept_for_retry.items()):
            if provider != serving_rr:
                continue
            if listing is None or query_id not in listing.held or query_id in lost:
                self.unkeep(query_id)
            elif life and not self.kept_in.get(query_id):
                self.kept_in[query_id] = life  # (the life that keeps it, now known)
        for query_id, provider in self.unsettled().items():
            if provider == serving_rr and (
                listing is None or query_id in listing.held or query_id in listing.left_out
            ):
                self.settle(query_id, None)
                if listing is not None and query_id in listing.held and query_id not in lost:
                    self.kept_for_retry[query_id] = serving_rr
                    self.kept_in[query_id] = life
                    kept.append(query_id)
        return kept

    def take_unclaimed(self, query_id: str, serving_rr: str) -> bool:
        """Take `query_id` if `serving_rr` keeps it for a retry no call claimed (none due)."""
        if query_id in self.registrar.due or self.kept_for_retry.get(query_id) != serving_rr:
            return False
        self.unkeep(query_id)
        self.dependency_of.pop(query_id, None)
        return True

    def take_dependencies(self, rid: str) -> list[tuple[str, str]]:
        """Resource `rid`'s load ended: take (to give back) the ids its calls left unsettled or
        kept for a retry, with their providers; no retry can come from it now."""
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
        """This registrar stops: take the unsettled and kept ids, with providers, to give back."""
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
        outcomes = self.registrar.due.outcomes
        while not outcomes.empty():
            self.registrar.redeliver(outcomes.get())

    def parked(self, notice: Notice) -> bool:
        """Hold `notice` while the answer to one of its queries is on its way (`answered`)."""
        for query_id in () if notice is self.forgetting else notice.query_ids:
            if self.registrar.due.awaited(query_id):
                self.take_outcomes()  # (handed over before the mark was read?)
            if query_id in self.registrar.due:
                self.flight(query_id).parked.append(notice)
                return True
        return False

    def doubt(self, query_ids: Iterable[str], provider: str) -> None:
        """`provider`'s reconcile knew not these due ids: reconcile again as each call ends."""
        for query_id in query_ids:
            self.doubted.setdefault(query_id, set()).add(provider)

    def answered(self, query_id: str, attempt: CallAttempt, provider: str = "") -> None:
        # settled first: a reconcile lists it not due (its parked notices are still on their
        # way for the status desk: `StatusTargets.on_way`, no direct delivery till they went)
        settled = self.registrar.due.settle(query_id, attempt)
        if provider in self.doubted.pop(query_id, ()):  # (of the run a restart replaced?)
            self.registrar.redeliver(ReconcileAsk(provider, holds_yours=False))
        flight = self.in_flight.get(query_id)
        if not settled or flight is None or not flight.parked:
            return
        waiting, flight.parked = flight.parked, []
        self.landed(query_id)
        while waiting:
            notice = waiting.pop(0)
            try:
                self.registrar.redeliver(notice)
            except BaseException:  # the actor dies: `fail_waiting` answers the rest
                self.flight(query_id).parked[:0] = waiting
                raise

    def parked_ids(self) -> frozenset[str]:
        return frozenset(q for q, f in self.in_flight.items() if f.parked)

    def fail_waiting(self, error: RrError) -> None:
        for call in self.registrar.due.durable_calls():
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
    """`CallAnswered` of `record` (none while nobody listens), to commit with its record."""
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
    shared.publish(*answer_event(shared, record, attempt, retry=retry))


def publish_failed(shared: Shared, message: CallFailed, *, retry: bool) -> None:
    """Publish `CallWithdrawn` or `CallFailed` for a call's failure `message` (nothing
    for the answer to an `Abandon` after a withdrawn call)."""
    stray = not message.withdrawn and message.attempt.state is AttemptState.WITHDRAWN
    if stray or not shared.events.active:  # (stray: the answer to an `Abandon`)
        return
    attempt = message.attempt
    stamps = (attempt.started, attempt.trace, attempt.caller_span)
    if message.withdrawn:
        shared.events.publish(
            events.CallWithdrawn(
                shared.name,
                message.query_id,
                message.provider,
                message.server,
                message.why,
                *stamps,
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
            *stamps,
            message.parent,
        )
    )


def publish_refused(
    shared: Shared, query: Query, error: BaseException, attempt: CallAttempt
) -> None:
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
"""How a release began (`Releases.send_unload`), for its `QueryForgotten`."""

NOT_BEGUN: Began = (0, 0, "", "")


def publish_forgotten(shared: Shared, query: Query, reason: str, began: Began = NOT_BEGUN) -> None:
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
    def __init__(self, registrar: ConsumerRecord) -> None:
        self.registrar = registrar

    def on_client_loaded(self, message: ClientLoaded, _reply: Reply) -> None:
        try:
            self.record_answer(message)
        finally:  # (also when recording failed: what waits for it must not wait for good)
            query = message.record.query
            self.registrar.flights.answered(query.id, message.attempt, query.serving_rr)

    def record_answer(self, message: ClientLoaded) -> None:
        """Decide what `message`'s answer does, and do it. A durable answer is kept only while
        its caller still waits: the actor takes the attempt before it commits."""
        query = message.record.query
        held = self.registrar.catalog.client(query.id)
        retry = self.registrar.flights.was_unsettled(query.id) or (held is not None and held.loaded)
        # (a retry of a call that failed as it died, or that its provider kept)
        self.registrar.flights.reset(query.id, None)
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
        """Run `action` on `message`'s answer; `retry`: the id was held or unsettled before."""
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
        """Record an answer (`KEEP`), or commit a durable one and answer its caller (`COMMIT`)."""
        catalog = self.registrar.catalog
        query = message.record.query
        durable = isinstance(message, DurableLoaded)
        if durable and self.unstorable(message):
            return
        if catalog.client(query.id) is not None:  # a retry of one held (or a record restored
            catalog.client_loaded(query.id, query.response)  # pending, an older backup)
        else:
            catalog.add_client(message.record)
            self.registrar.texts.added(message.record)
        told = answer_event(self.registrar, message.record, message.attempt, retry=retry)
        if durable:
            self.keep_durable(message, told)
            return
        if self.registrar.commit(*told) is not None:  # (written with its record)
            self.registrar.publish(*told)  # kept in memory: written with the next write
        self.registrar.holdings.held(query.id, message.on_status)

    def keep_durable(self, message: ClientLoaded, told: tuple[events.Event, ...]) -> None:
        """Commit a durable answer, then answer its caller; not written: give the id back."""
        query = message.record.query
        self.registrar.holdings.held(query.id, message.on_status)  # (a notice may come next)

        def undo(failed: CatalogWriteError) -> None:  # not kept
            give_back(query.serving_rr, query.id, self.registrar.name)
            self.registrar.holdings.forget(query.id, commit=False, reason=None)
            publish_refused(self.registrar, query, failed, message.attempt)
            message.attempt.settle(error=failed)

        def refuse(error: RrError) -> None:  # died before its commit: not kept either
            give_back(query.serving_rr, query.id, self.registrar.name)
            message.attempt.settle(error=error)

        def ok() -> None:
            message.attempt.settle(query.response)

        self.registrar.commit_then(*told, ok=ok, undo=undo, refuse=refuse)

    def unstorable(self, message: ClientLoaded) -> bool:
        """A durable call's response this catalog cannot store: give it back, fail the call."""
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
        """Give `query`'s id back to its provider (nothing was written for it: presumed abort)."""
        give_back(query.serving_rr, query.id, self.registrar.name)

    def owner_gone(self, record: ClientRecord) -> bool:
        """Whether `record` is a dependency of a resource that failed or is unloading (its
        dependencies were released already, so this one would never be)."""
        if record.parent is None:
            return False
        owner = self.registrar.catalog.resources.get(record.parent)
        return owner is None or owner.state is ResourceState.UNLOADING

    def give_back_late_dependency(self, message: ClientLoaded) -> None:
        """Release a dependency that arrived after its resource's own release (rule 4): the
        call succeeded, but nothing could release the id later."""
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
        if message.serving_rr is not None:  # (it died or stopped: answers of lists sent
            self.registrar.reconciling.died(message.serving_rr)  # before may be its run's)
        qid, flights = message.query_id, self.registrar.flights
        known = self.registrar.catalog.client(qid)
        unsettled = flights.was_unsettled(qid)  # (kept there for a retry, or may be)
        kept = unsettled or qid in flights.kept_for_retry
        publish_failed(self.registrar, message, retry=unsettled or bool(known and known.loaded))
        current = self.registrar.due.durable_attempt(qid)
        if current is None or current is message.attempt:  # (unsettled again if its provider may
            gone = message.withdrawn or message.attempt.state is AttemptState.WITHDRAWN
            flights.reset(qid, None if gone else message.serving_rr, message.parent)  # hold it)
        record = self.registrar.catalog.client(qid)
        stale = current is not None and current is not message.attempt
        stopped = message.withdrawn and self.registrar.stopping  # (a stop gives all back)
        withdrawn = message.withdrawn and not stopped
        retried = not stale and record is not None and record.loaded and not stopped
        try:
            if stale:
                pass  # a stale failure of an earlier attempt: a retry's is due
            elif retried and withdrawn:  # still held, unless its provider knew it not and the
                flights.doubt((qid,), message.provider)  # retry's load was undone: reconciled
            elif retried:
                pass  # a failed retry of an id this registrar holds: it still holds it
            elif record is not None:
                self.registrar.holdings.forget(qid, reason="withdrawn")
        finally:
            flights.answered(qid, message.attempt, message.provider)
        record = self.registrar.catalog.client(qid)  # (not due now: its FATAL is not parked)
        if retried and record is not None and record.loaded:
            self.retry_failed(message, record)
        elif withdrawn and kept and not retried:  # (kept there for a retry: its Abandon gave
            with self.registrar.due.frozen() as (due, _):  # back what the retry added) given
                if qid not in due:  # back, unless called again (none starts meanwhile)
                    give_back(message.provider, qid, self.registrar.name)

    def retry_failed(self, message: CallFailed, record: ClientRecord) -> None:
        """A held id's retry failed: it is still held, unless its provider ran a new load for it
        (`ResourceLoadError`: it no longer knew it, rule 20): then `FATAL` now, before its caller
        can release it and so skip the `FATAL` a reconcile would tell (issue 68)."""
        query = record.query
        error, provider = message.error, message.provider
        if isinstance(error, ResourceLoadError) and provider == query.serving_rr:
            why = "the provider no longer knows this query (a retry of it ran a new load there)"
            source = f"{query.serving_rr}/{query.server}"
            self.registrar.holdings.report_lost(
                source, (query.id,), why, forgotten="unknown at reconcile"
            )


# -- holdings --------------------------------------------------------------------------


class Holdings:
    def __init__(self, registrar: ConsumerRecord) -> None:
        self.registrar = registrar
        self.status_callbacks: dict[str, StatusCallback] = {}  # query id -> its callback
        self.epoch = 0  # how many `Reconcile` lists it built (`new_epoch`)
        self.answered_in: dict[str, int] = {}  # query id -> its answer's epoch (none: 0)
        # the ids its `CatalogRestored` listed
        self.restored = {r.query.id for r in registrar.catalog.client_records()}

    # -- holding and forgetting queries -------------------------------------------------

    def held(self, query_id: str, on_status: StatusCallback | None) -> None:
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
        `commit=False`: the caller commits. `reason`: its `QueryForgotten`'s, if its holding was
        told (`None`: the caller published it); `began`: its release's stamps."""
        record = self.registrar.catalog.client(query_id)
        if record is not None:
            told = query_id in self.answered_in or query_id in self.restored
            self.restored.discard(query_id)
            if told and reason is not None:
                publish_forgotten(self.registrar, record.query, reason, began)
            self.registrar.catalog.remove_client(query_id)
            self.status_callbacks.pop(query_id, None)
            self.registrar.targets.pop(query_id, None)
            self.answered_in.pop(query_id, None)
            if commit and self.registrar.in_turn:  # (with the rest of the turn: an answer
                self.registrar.commit_then(ok=_nothing, undo=_ignored, refuse=_ignored)
            elif commit:  # after it waits for it)
                self.registrar.commit()

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
        """`FATAL` to the status callbacks of `ids` (and up their dependents), then forget them."""
        event, wall = runtime.new_id(), runtime.wall()  # (nobody waits for the acknowledgements)
        notice = StatusNotice(ids, Status.FATAL, why, source, event, FutureReply(), sent_at=wall)
        self.registrar.flights.forgetting = notice  # (told now: a retry's answer would come
        self.registrar.redeliver(notice)  # after they are forgotten, and run no callback)
        for query_id in ids:
            self.forget(query_id, commit=False, reason=forgotten)
        self.registrar.commit()

    def callback_of(self, query_id: str) -> StatusCallback | None:
        return self.status_callbacks.get(query_id)

    def publish_target(self, query_id: str) -> None:
        """Let the status desk run a loaded, non-dependency `query_id`'s callback (`status.py`)."""
        record = self.registrar.catalog.client(query_id)
        callback = self.status_callbacks.get(query_id)
        if record is None or callback is None or record.parent is not None or not record.loaded:
            self.registrar.targets.pop(query_id, None)
        else:
            self.registrar.targets[query_id] = (record.query, callback)

    # -- the epochs of `Reconcile` lists (`Reconciling`) --------------------------------

    def new_epoch(self) -> int:
        """A `Reconcile` list leaves now: its number (answers recorded later came after it)."""
        self.epoch += 1
        return self.epoch

    def answered_before(self, query_id: str, epoch: int) -> bool:
        return self.answered_in.get(query_id, 0) < epoch

    # -- notices from its providers -----------------------------------------------------

    def on_revoke(self, message: Revoke, _reply: Reply) -> None:
        if self.registrar.flights.parked(message):
            return
        for query_id in message.query_ids:
            self.forget(query_id, commit=False, reason="revoked")
        self.registrar.commit()

    def on_response_updated(self, message: ResponseUpdated, reply: Reply) -> None:
        if self.registrar.flights.parked(message):
            return
        if self.registrar.saver.store is not None:  # refused, as an answer it cannot store is
            check_picklable(message.response, "the new response")  # (a ConfigError answer)
        for query_id in message.query_ids:
            self.registrar.catalog.client_loaded(query_id, message.response)
            if query_id in self.registrar.targets:  # (its query says the new response)
                self.publish_target(query_id)
        self.registrar.commit()
        reply.set_result(None)

    # -- operations the handle asks for -------------------------------------------------

    def on_set_status_callback(self, message: SetStatusCallback, reply: Reply) -> None:
        if self.registrar.catalog.client(message.query_id) is None:
            raise UnknownQueryError(f"unknown or released query id {message.query_id!r}")
        self.status_callbacks[message.query_id] = message.callback
        self.publish_target(message.query_id)
        reply.set_result(None)

    def on_list_client_queries(self, _message: ListClientQueries, reply: Reply) -> None:
        reply.set_result([r.query for r in self.registrar.catalog.client_records() if r.loaded])

    def on_open_client(self, message: OpenClient, reply: Reply) -> None:
        """The client actor for `target_rr/server`, started on first use (thesis 4.3.3)."""
        MEMBERSHIP.monitor(self.registrar.name, message.target_rr)  # (before a first call's load
        MEMBERSHIP.monitor(message.target_rr, self.registrar.name)  # leaves: rule 20, once a life)
        ref = self.registrar.ref
        assert ref is not None
        try:
            client = self.registrar.clients.start(
                ref, self.registrar.name, message.target_rr, message.server
            )
        except RuntimeError as exc:  # no thread for its actor: that call fails, naming the bound
            reply.set_error(no_thread(message.target_rr, exc, "its client"))
            return
        reply.set_result(client)


# -- releases --------------------------------------------------------------------------


GONE = (RegistrarUnavailableError, RegistrarStoppedError)
"""Errors of a provider that died or was stopped: what was sent may or may not have run."""


class Releases:
    def __init__(self, registrar: ConsumerRecord) -> None:
        self.registrar = registrar
        # ids whose `Unload` is on its way -> (the stamp it left at, `reconciled` then)
        self.releasing: dict[str, Began] = {}
        # provider -> the stamp of the last `Reconcile` with it answered (its list left)
        self.last_reconciled: dict[str, int] = {}
        self.unreleased: dict[str, str] = {}  # id -> provider, of failed releases (`unanswered`)

    # -- releasing one query ------------------------------------------------------------

    def release_dependencies(
        self,
        rid: str,
        then: Callable[[], None],
        only: Collection[str] | None = None,
        trace: str = "",
    ) -> None:
        """Release every query resource `rid` holds as a dependency (`only`: these ids); then
        `then()`. `trace`: the traceparent of the `Unload` of `rid` (`""`: untraced)."""
        join = Join(then)
        for record in self.registrar.catalog.dependencies(rid):
            if only is None or record.query.id in only:
                self.release_client(record, join.add(), traces.under(trace) if trace else None)
        for query_id, serving_rr in self.registrar.flights.take_dependencies(rid):
            give_back(serving_rr, query_id, self.registrar.name)
        join.seal()

    def release_client(
        self,
        record: ClientRecord,
        then: Callable[[], None],
        begun: tuple[str, str] | None = None,
    ) -> None:
        """Unload one query this registrar holds; the record goes whatever the answer. A
        provider that cannot be reached releases it when it reconciles (`unreleased`)."""
        query = record.query

        def answered(on_its_way: Any, error: BaseException | None) -> None:
            began = self.releasing.pop(query.id, NOT_BEGUN)
            if error is not None and not isinstance(error, UnknownQueryError):
                logger.warning("releasing %s at %s failed: %s", query.id, query.serving_rr, error)
            if isinstance(error, GONE):
                self.unanswered(query, began)
            join = Join(then)
            self.deliver_on_its_way(query.id, on_its_way, join)
            self.registrar.holdings.forget(
                query.id, reason="stop" if record.parent is None else "dependency", began=began
            )
            join.seal()

        self.send_unload(query, answered, begun)

    def on_release(self, message: Release, reply: Reply) -> None:
        query_id = message.query_id
        record = self.registrar.catalog.client(query_id)
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
            # released unless unknown there, or its unload overran (`UnloadOverran`)
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
            self.registrar.holdings.forget(query_id, began=began)
            join.seal()

        self.send_unload(query, answered, message.begun)

    def send_unload(
        self,
        query: Query,
        answered: Callable[[Any, BaseException | None], None],
        begun: tuple[str, str] | None = None,
    ) -> None:
        """Ask `query`'s provider to release its id; `answered(on_its_way, error)` runs on the
        answer (an `UnloadOverran` as its statuses on their way and its `CallTimeoutError`)."""

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
        """Deliver the statuses the answer to `query_id`'s `Unload` carried, before the id is
        forgotten (they may come after the answer on another connection); each a part of `join`."""
        for status in on_its_way or ():
            self.registrar.redeliver(
                status.notice((query_id,), self.registrar.come_back(join.add()))
            )

    def release_later(
        self, query: Query, error: BaseException, began: Began = NOT_BEGUN
    ) -> RrError:
        """The `Unload` of `query` failed as its provider died or stopped: forget the id now and
        keep it `unreleased` until the provider's next `Reconcile`, which leaves it out."""
        self.unanswered(query, began)
        self.registrar.holdings.forget(query.id, reason="unload unanswered", began=began)
        text = (
            f"{error}; query {query.id} is released: '{query.serving_rr}' releases it when "
            "it reconciles with this registrar after its restart (its unload runs once)"
        )
        told: RrError = (
            RegistrarStoppedError(text, error.registrar)  # (who stopped, as `error` says)
            if isinstance(error, RegistrarStoppedError)
            else RegistrarUnavailableError(text)
        )
        told.__cause__ = error
        return told

    def unanswered(self, query: Query, began: Began) -> None:
        """Its `Unload` failed as the provider died or stopped: `unreleased`, until a list leaves
        it out; one that left before the failure named it: if answered already, `again`."""
        self.unreleased[query.id] = query.serving_rr
        if began[0] < self.last_reconciled.get(query.serving_rr, 0):
            self.again(query.serving_rr)

    def again(self, serving_rr: str) -> None:
        """Reconcile now: `serving_rr` holds a failed release (stopping: the stop gives it back)."""
        if not self.registrar.stopping:
            self.registrar.reconciling.reconcile(serving_rr)

    # -- what `Reconciling` asks of it --------------------------------------------------

    def unreleased_at(self, serving_rr: str) -> frozenset[str]:
        return frozenset(q for q, p in self.unreleased.items() if p == serving_rr)

    def settle_listed(self, serving_rr: str, listing: Listing | None, lost: frozenset[str]) -> None:
        """`serving_rr` answered `listing` (none: it is gone for good): releases from now on began
        after it; those it left out or `lost` names were released (none: all). One it named is
        held there (its unload failed after the list left): `again`."""
        for query_id in [q for q, p in self.unreleased.items() if p == serving_rr]:
            if listing is None or query_id in listing.left_out or query_id in lost:
                del self.unreleased[query_id]
        if listing is not None:
            last = self.last_reconciled.get(serving_rr, 0)
            self.last_reconciled[serving_rr] = max(last, listing.at)
            if not self.unreleased_at(serving_rr).isdisjoint(listing.held):
                self.again(serving_rr)

    # -- this registrar stops -----------------------------------------------------------

    def withdraw_pending(self, error: RrError, given_back: Join) -> None:
        """This registrar stops: give up its durable top-level calls not answered yet (their
        callers get `error`); each provider's answer is a part of `given_back`."""
        for call in self.registrar.due.durable_calls():
            if call.parent is not None or not call.attempt.fail_open(error):
                continue  # (a dependency: its load's end settles it; or its outcome comes)
            self.give_back_before_stop(call.serving_rr, call.query_id, given_back)
            self.registrar.answers.on_call_failed(
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
        """On stop: give back unsettled and kept calls' ids and failed releases (`given_back`)."""
        for query_id, serving_rr in self.registrar.flights.take_unsettled():
            self.give_back_before_stop(serving_rr, query_id, given_back)
        for query_id, serving_rr in self.unreleased.items():
            self.give_back_before_stop(serving_rr, query_id, given_back)
        self.unreleased.clear()

    def give_back_before_stop(self, serving_rr: str, query_id: str, given_back: Join) -> None:
        """Give `query_id` back to `serving_rr` and wait (a part of `given_back`): an `Abandon`
        not waited for could reach the provider after its own stop (rule 12)."""
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
    """What one `Reconcile` told a provider, as it was when the list left (`epoch`: only
    records answered before it are settled by its answer; `left_out`: failed releases)."""

    held: tuple[str, ...]
    due: frozenset[str]
    left_out: frozenset[str]
    epoch: int
    life: str = ""  # the provider's life it was sent to (its `ReconcileAsk.life`; "": not known)
    at: int = 0


class Reconciling:
    """Reconciles what this registrar holds at providers with what they hold for it
    (`everyone`: with every registrar of the system, after a restore or `LostEverything`)."""

    def __init__(self, registrar: ConsumerRecord) -> None:
        self.registrar = registrar
        # provider -> the ask's round and life ((0, ""): none)
        self.asked_to_reconcile: dict[str, tuple[int, str]] = {}
        self.everyone = False
        self.kept_timers: dict[KeptUnclaimed, runtime.Cancellable] = {}  # (`expire_kept`)
        self.lives: dict[str, str] = {}  # provider -> its latest run heard of ("": none)
        # provider -> the last list's epoch when a call failed as it died, and its latest
        # run heard of then: the answers to the lists up to it may be of that (dead) run
        self.deaths: dict[str, tuple[int, str]] = {}

    def expect_reconcile(self, providers: Iterable[str], *, everyone: bool) -> None:
        self.everyone = everyone
        for provider in providers:
            self.asked_to_reconcile.setdefault(provider, (0, ""))

    def reconcile_all(self) -> dict[str, tuple[int, str]]:
        """This registrar serves (again): reconcile with every provider it holds ids at, those
        that asked during setup, and (`everyone`) every registrar it can reach now; but those
        that asked with a round, returned (provider -> (round, life)) for `Presence.attempt`
        to answer: retried, and its newer rounds echo that round until one is answered."""
        providers = self.registrar.catalog.providers()
        providers |= self.asked_to_reconcile.keys()
        if self.everyone:
            providers |= DIRECTORY.names() - {self.registrar.name}
        asks, self.asked_to_reconcile = self.asked_to_reconcile, {}
        rounds = {serving_rr: ask for serving_rr, ask in asks.items() if ask[0]}
        for serving_rr in sorted(providers - rounds.keys()):
            self.reconcile(serving_rr)
        return rounds

    # -- what it holds at a provider --------------------------------------------------

    def holds_at(self, serving_rr: str) -> bool:
        return (
            self.registrar.flights.held_at(serving_rr)
            or bool(self.registrar.releases.unreleased_at(serving_rr))
            or serving_rr in self.registrar.catalog.providers()
        )

    def listing(
        self,
        serving_rr: str,
        due: frozenset[str],
        withdrawn: frozenset[str] = frozenset(),
        life: str = "",
    ) -> Listing:
        """The list of a `Reconcile` to `serving_rr` leaving now, a new epoch. `withdrawn` ids
        are never listed, so the provider releases them; `life`: the asking life (`kept_at`)."""
        held = {
            record.query.id
            for record in self.registrar.catalog.client_records()
            if record.query.serving_rr == serving_rr
        }
        held |= {q for q, p in self.registrar.flights.unsettled().items() if p == serving_rr}
        held |= self.registrar.flights.kept_at(serving_rr, life)
        held |= due
        held -= withdrawn
        left_out = self.registrar.releases.unreleased_at(serving_rr)
        epoch = self.registrar.holdings.new_epoch()
        return Listing(tuple(sorted(held - left_out)), due, left_out, epoch, life, _hlc.CLOCK.now())

    def settle_listed(
        self,
        serving_rr: str,
        listing: Listing | None = None,
        unknown: Iterable[str] = (),
        life: str = "",
    ) -> None:
        """Settle the failed calls and releases `listing` listed or left out (none: all); those
        its provider's run `life` keeps for a retry now, unclaimed, are given back later
        (`expire_kept`)."""
        kept = self.registrar.flights.settle_listed(serving_rr, listing, unknown, life)
        self.registrar.releases.settle_listed(serving_rr, listing, frozenset(unknown))
        if kept:
            self.expire_kept(serving_rr, tuple(kept))

    def expire_kept(self, serving_rr: str, query_ids: tuple[str, ...]) -> None:
        """Tell this actor `KeptUnclaimed(serving_rr, query_ids)` after `call_timeout`."""
        ref, told = self.registrar.ref, KeptUnclaimed(serving_rr, query_ids)
        assert ref is not None

        def tell() -> None:
            with contextlib.suppress(pykka.ActorDeadError):
                ref.tell(told)

        self.kept_timers[told] = runtime.thread_timer(self.registrar.config.call_timeout, tell)

    def on_kept_unclaimed(self, message: KeptUnclaimed, _reply: Reply) -> None:
        """Give back the ids kept for a retry that none claimed: a call that failed as its
        provider died is held there at most `call_timeout` after the reconcile with its
        restart (issue 68: before, until the provider's next restart or this one's stop)."""
        self.kept_timers.pop(message, None)
        for query_id in message.query_ids:
            if self.registrar.flights.take_unclaimed(query_id, message.serving_rr):
                give_back(message.serving_rr, query_id, self.registrar.name)

    def close(self) -> None:
        """This registrar stops or died: no more timers (a stop gives the kept ids back)."""
        for timer in self.kept_timers.values():
            timer.cancel()

    def asked(self, message: ReconcileAsk) -> bool:
        """Whether to send an asking provider a `Reconcile` now (setup: once done; none owed)."""
        self.heard(message.serving_rr, message.life)
        if not message.holds_yours and not self.holds_at(message.serving_rr):
            # (told as every registrar of the system is: nothing to reconcile, but a due
            # answer may be of the run its restart replaced)
            self.registrar.flights.doubt(self.registrar.due.ids(), message.serving_rr)
            return False
        if self.registrar.phase is Phase.SETTING_UP:  # its status callbacks are not attached yet
            asks = self.asked_to_reconcile
            ask = (message.round, message.life)
            asks[message.serving_rr] = ask if ask[0] else asks.get(message.serving_rr, ask)
            return False
        return True

    def on_lost_everything(self, _message: LostEverything, _reply: Reply) -> None:
        """Restarted without a backup (`LostEverything`): reconcile with every registrar of the
        system, now and after each restart, so each releases the ids the list does not name
        (announced by its supervisor: each that holds ids of it asks it, `on_reconcile_ask`)."""
        self.everyone = not self.registrar.announced
        if self.registrar.phase is Phase.SERVING:  # (during setup `on_ready` reconciles)
            self.reconcile_all()

    def reconcile(
        self,
        serving_rr: str,
        then: Callable[[BaseException | None], None] | None = None,
        life: str = "",
        ask: tuple[int, str] = (0, ""),
    ) -> None:
        """Tell `serving_rr` the ids held there (`Reconcile`); `then(error)` here once handled.
        Why frozen and epoch-bound: docs/explanation/inside.md, "The consumer's reconcile".
        `ask`: the `ReconcileAsk.round` it answers and that ask's `life`, echoed."""
        with self.registrar.due.frozen() as (due, withdrawn):
            listing = self.listing(serving_rr, due, withdrawn, life)
            self.registrar.send(
                serving_rr,
                lambda reply: Reconcile(
                    self.registrar.name, listing.held, reply, self.registrar.life, *ask
                ),
                lambda answer, error: self.reconciled(
                    serving_rr, answer, error, listing, then, ask
                ),
            )

    def reconciled(
        self,
        serving_rr: str,
        answer: Reconciled | None,
        error: BaseException | None,
        listing: Listing,
        then: Callable[[BaseException | None], None] | None = None,
        ask: tuple[int, str] = (0, ""),
    ) -> None:
        if error is not None:  # not reachable: it asks for a Reconcile when it is back
            logger.debug(
                "reconciling %s with %s failed: %s", self.registrar.name, serving_rr, error
            )
            if then is not None:
                then(error)
            return
        assert answer is not None
        again = self.not_applied(serving_rr, answer.life, listing)
        if again is not None:  # (its list again, to the run that serves: rule 17)
            self.reconcile(serving_rr, then, again, ask)
            return
        self.heard(serving_rr, answer.life)
        self.settle_reconciled(serving_rr, answer.unknown, listing, listing.life or answer.life)
        if then is not None:
            then(None)

    # -- which run of a provider it reconciles with (rule 17) ---------------------------

    def heard(self, serving_rr: str, life: str) -> None:
        """A `ReconcileAsk` or an answer of `serving_rr`'s run `life` came."""
        if life and life_order(life) >= life_order(self.lives.get(serving_rr, "")):
            self.lives[serving_rr] = life

    def died(self, serving_rr: str) -> None:
        """A call to `serving_rr` failed as it died or stopped (`not_applied`)."""
        self.deaths[serving_rr] = (self.registrar.holdings.epoch, self.lives.get(serving_rr, ""))

    def not_applied(self, serving_rr: str, life: str, listing: Listing) -> str | None:
        """The life to send `listing` to again, dropping run `life`'s answer (`None`: apply
        it): one to a list made for another run (a dead run's retried ask reached its
        restart), or handled after a call failed as `serving_rr` died, of no run known to be
        later (the dead one's, perhaps). Applied, it would stamp a failed call's id as kept
        by the wrong run, or forget it: the serving run would release it (rule 17)."""
        if listing.life and life != listing.life:
            return life
        death = self.deaths.get(serving_rr)
        if death is None or listing.epoch > death[0]:
            return None
        if death[1] and life_order(life) > life_order(death[1]):
            return None  # (a later run than the one that died answered)
        return ""

    def settle_reconciled(
        self, serving_rr: str, unknown: tuple[str, ...], listing: Listing, life: str = ""
    ) -> None:
        """Report and forget the ids `serving_rr` no longer knows, of the records as `listing`
        found them; one answered since is reconciled again (its answer may be of the run the
        restart replaced: rule 20), a due one once its outcome is recorded (`Flights.doubted`)."""
        lost: dict[str, list[str]] = {}
        again = False
        for query_id in unknown:
            record = self.registrar.catalog.client(query_id)
            since = query_id in listing.due or not self.registrar.holdings.answered_before(
                query_id, listing.epoch
            )
            if query_id in self.registrar.due:
                self.registrar.flights.doubt((query_id,), serving_rr)  # (again then)
            elif record is None or not record.loaded or record.query.serving_rr != serving_rr:
                continue
            elif since:
                again = True
            elif query_id not in self.registrar.releases.releasing:  # (its release: no FATAL)
                lost.setdefault(record.query.server, []).append(query_id)
        # listed and known: held there for a retry (by run `life`); left out: released
        self.settle_listed(serving_rr, listing, unknown, life)
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
            self.registrar.holdings.report_lost(
                f"{serving_rr}/{server}", tuple(ids), forgotten="unknown at reconcile"
            )
        if again:
            self.registrar.redeliver(ReconcileAsk(serving_rr, holds_yours=False))

    def lose_provider(self, serving_rr: str) -> None:
        """Provider `serving_rr` is gone for good (rule 19): `FATAL` to its ids, then forget."""
        lost: dict[str, list[str]] = {}
        for record in list(self.registrar.catalog.client_records()):
            if record.query.serving_rr == serving_rr and record.loaded:
                lost.setdefault(record.query.server, []).append(record.query.id)
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
            self.registrar.holdings.report_lost(
                f"{serving_rr}/{server}",
                tuple(ids),
                "the provider is gone and nobody will restart it",
                forgotten="provider lost",
            )


# -- client actors ---------------------------------------------------------------------


class ClientActor(Actor):
    """The consumer-side endpoint for one target server: it relays fetches (thesis 4.3.3)."""

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


class Clients(dict[tuple[str, str], "pykka.ActorRef[ClientActor]"]):
    """A registrar's client actors by `(target registrar, server)`, looked up from any thread.

    A dict, so that a call looks its client up with the dict's own `get` (no frame of this
    module on a call's path); `start` and `stop_all` are the only writers.
    """

    __slots__ = ()

    def start(
        self, registrar_ref: pykka.ActorRef[Any], origin_rr: str, target_rr: str, server: str
    ) -> pykka.ActorRef[ClientActor]:
        key = (target_rr, server)
        client = self.get(key)
        if client is None:
            client = ClientActor.start(registrar_ref, origin_rr, target_rr, server)
            self[key] = client
        return client

    def stop_all(self) -> None:
        for client in list(self.values()):
            client.stop(block=True, timeout=5.0)
