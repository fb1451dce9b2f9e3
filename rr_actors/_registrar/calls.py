"""The call protocol, on the caller's thread: send, then the answer, a death, or the timeout.

```
 caller thread (Calls.steps)           consumer registrar actor          provider
 (a first call to a server: its client opened, monitor(provider)); due.expect(id, attempt)
 attempt.sent(); Load(its run: life) ──────────────────────────────────► on_load
 attempt.wait(answer | error | timeout) ◄──── ClientReply (the answering thread) ◄─┘
   answered: ClientLoaded ──► due.outcomes ──► recorded before the actor's next message
   durable:  DurableLoaded ─────────► the record committed, then the caller answered
   timeout:  attempt.withdraw(), Abandon ───────────────────────────────► release the id
             CallFailed ────► due.outcomes + TakeOutcomes ──► forget the attempt's record
```

Like OTP's `gen:do_call`: a provider that dies fails the reply at once. A reply that
races the timeout, a stop or a death is decided by one state under one lock, the call's
`CallAttempt` (SENDING ─► SENT ─► ANSWERED | RECORDING ─► ANSWERED | FAILED, or FAILED,
or WITHDRAWN; docs/explanation/architecture.md, "One call attempt's states"); the party
whose transition took it acts on the state it left. Who does what, and presumed abort:
docs/explanation/inside.md, "A call's outcome".
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
from collections.abc import Callable, Iterator
from typing import Any

import pykka

from rr_actors._catalog import ClientRecord
from rr_actors._core import hlc, runtime
from rr_actors._core.actor import LateQueue, OneShotFuture, awaiting, deliver
from rr_actors._core.bus import Publisher
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.replies import Steps
from rr_actors._registrar.messages import Load, check_picklable, give_back
from rr_actors._registrar.state import Probes
from rr_actors._types import Query, StatusCallback
from rr_actors.errors import (
    CallTimeoutError,
    OverloadedError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
)

_FIRST_PAUSE = 0.005
"""Seconds a call refused for overload waits before it asks again when its provider does
not say (its `retry_after`); each further refusal doubles it, up to `_LAST_PAUSE`."""
_LAST_PAUSE = 0.1


# -- one call attempt ------------------------------------------------------------------


class AttemptState(enum.Enum):
    """Where one call attempt is (see `CallAttempt`)."""

    SENDING = "sending"
    """Its `Load` has not left yet."""
    SENT = "sent"
    """Its `Load` left; its caller waits."""
    RECORDING = "recording"
    """A durable call's answer: the registrar actor commits its record, then settles it."""
    ANSWERED = "answered"
    """Its caller has the answer (and, for a plain call, records it)."""
    FAILED = "failed"
    """It failed (an error answer, the provider died, the registrar stopped or died)."""
    WITHDRAWN = "withdrawn"
    """Its caller stopped waiting first: an answer that comes later is not kept."""


# (by these names: on CPython 3.11 a member read through its class costs ~1k instructions)
SENDING, SENT, RECORDING = AttemptState.SENDING, AttemptState.SENT, AttemptState.RECORDING
ANSWERED, FAILED, WITHDRAWN = AttemptState.ANSWERED, AttemptState.FAILED, AttemptState.WITHDRAWN
_OPEN = (SENDING, SENT)


class CallAttempt(OneShotFuture[Any]):
    """One attempt of a call: the future its caller waits on, settled through one `state`.
    Its caller, the answering thread and the actor race over it; each transition returns the
    state it leaves, or changes nothing (docs/explanation/inside.md, "A call's outcome").
    Entering `ANSWERED` or `FAILED` wakes the caller."""

    # What its events tell (set by its caller when known): when the call began (wall
    # clock seconds, 0.0: not known) and its trace context (`_core/traces.py`).
    started = 0.0
    trace = ""
    caller_span = ""

    def __init__(self) -> None:
        super().__init__()
        self._state_lock = runtime.Lock()
        self.state = SENDING
        self._awaited = False

    def __repr__(self) -> str:
        return f"<rr_actors.CallAttempt {self.state.value}>"

    @property
    def awaited(self) -> bool:
        """Whether a notice waits for this call's answer: its caller then wakes the actor."""
        with self._state_lock:
            return self._awaited

    def mark_awaited(self) -> None:
        """The registrar actor: a notice waits for this call's answer. Under the state lock, so
        the caller reading it and the actor taking the outcomes see each other's write."""
        with self._state_lock:
            self._awaited = True

    def sent(self) -> AttemptState:
        """The caller: its `Load` leaves now (`SENT`), unless it failed meanwhile."""
        with self._state_lock:
            if self.state is SENDING:
                self.state = SENT
            return self.state

    def answer(self, value: Any) -> AttemptState:
        """The answering thread: a plain call's answer came; its caller records it."""
        with self._state_lock:
            if self.state in _OPEN:
                self._settle_as(ANSWERED, value, None)
            return self.state

    def take(self) -> AttemptState:
        """The registrar actor: a durable call's answer came; commit it (`RECORDING`)."""
        with self._state_lock:
            if self.state in _OPEN:
                self.state = RECORDING
            return self.state

    def settle(self, value: Any = None, error: BaseException | None = None) -> AttemptState:
        """The actor that took it: the answer is committed (`value`), or not kept (`error`)."""
        with self._state_lock:
            if self.state is RECORDING:
                state = ANSWERED if error is None else FAILED
                self._settle_as(state, value, error)
            return self.state

    def fail(self, error: BaseException) -> AttemptState:
        """Any party: the call failed with `error` (unless it was settled or taken)."""
        with self._state_lock:
            if self.state in _OPEN:
                self._settle_as(FAILED, None, error)
            return self.state

    def fail_open(self, error: BaseException) -> bool:
        """The registrar actor, as it stops: fail the call with `error` if it is still open;
        whether this did (else its outcome comes anyway)."""
        with self._state_lock:
            if self.state not in _OPEN:
                return False
            self._settle_as(FAILED, None, error)
            return True

    def withdraw(self) -> AttemptState:
        """The caller: it stops waiting (`WITHDRAWN`), unless the answer won the race."""
        with self._state_lock:
            if self.state in _OPEN:
                self._settle_as(WITHDRAWN, None, None)
            return self.state

    def _settle_as(self, state: AttemptState, value: Any, error: BaseException | None) -> None:
        self.state = state  # (under the state lock)
        if error is None:
            self.set(value)
        else:
            self.set_exception((type(error), error, error.__traceback__))


# -- what a caller hands its registrar -------------------------------------------------


@dataclasses.dataclass(frozen=True, slots=True)  # (one per call: slots build faster)
class ClientLoaded:
    """A plain call's answer to record, handed over by its caller, who has it already."""

    record: ClientRecord
    on_status: StatusCallback | None
    attempt: CallAttempt  # the caller's


@dataclasses.dataclass(frozen=True, slots=True)
class DurableLoaded(ClientLoaded):
    """A durable call's answer, told by the answering thread: the registrar takes the attempt,
    commits its record, then answers the caller (handled as a `ClientLoaded`)."""


@dataclasses.dataclass(frozen=True, slots=True)  # (one per call: slots build faster)
class CallFailed:
    """A call ended without an answer to record: it failed, or its caller withdrew it."""

    query_id: str
    attempt: CallAttempt
    withdrawn: bool = False  # given up by its caller, who told the provider an Abandon first
    serving_rr: str | None = None  # set if it failed as its provider died or stopped: it
    # may have executed, and a retry with the same id may come (held until reconciled)
    parent: str | None = None  # the resource of this registrar whose load made the call
    provider: str = ""  # the call's provider and server, and what it failed with (events)
    server: str = ""
    error: BaseException | None = None
    why: str = "timeout"  # of a withdrawal: "timeout", "interrupted", "registrar stopped"


@dataclasses.dataclass(frozen=True)
class TakeOutcomes:
    """Wake the actor for the outcomes waiting in `DueAnswers.outcomes` that something awaits."""


BACKLOG = 64
"""Plain outcomes that may wait for the registrar actor before a caller wakes it."""

Outcome = ClientLoaded | CallFailed


class DueAnswers:
    """The query ids whose answer a consumer has not recorded yet, with their attempt.
    Callers add an id before its `Load` leaves, the actor removes it once it handled the
    outcome; a notice that overtook its answer waits until its id is no longer due.
    `outcomes`: plain calls' outcomes in hand-over order; after the actor ended, to `late`."""

    __slots__ = ("_attempts", "_durable", "_lock", "outcomes")

    def __init__(self) -> None:
        self._attempts: dict[str, CallAttempt] = {}
        self._durable: dict[str, ClientReply] = {}  # of the durable calls among them
        self._lock = runtime.Lock()
        self.outcomes = LateQueue()

    def __contains__(self, query_id: str) -> bool:
        return query_id in self._attempts

    def ids(self) -> frozenset[str]:
        with self._lock:
            return frozenset(self._attempts)

    @contextlib.contextmanager
    def frozen(self) -> Iterator[tuple[frozenset[str], frozenset[str]]]:
        """The ids due, and those whose caller withdrew the call, with no call starting until the
        block ends (a `Reconcile` lists every call sent before it, none of the withdrawn)."""
        with self._lock:
            withdrawn = frozenset(q for q, a in self._attempts.items() if a.state is WITHDRAWN)
            yield frozenset(self._attempts) - withdrawn, withdrawn

    def expect(
        self, query_id: str, attempt: CallAttempt, durable: ClientReply | None = None
    ) -> None:
        """Call `attempt` for `query_id` is about to leave; `durable`: the registrar answers it."""
        with self._lock:
            self._attempts[query_id] = attempt
            if durable is not None:
                self._durable[query_id] = durable
            else:
                self._durable.pop(query_id, None)

    def durable_attempt(self, query_id: str) -> CallAttempt | None:
        with self._lock:
            return self._attempts.get(query_id) if query_id in self._durable else None

    def durable_calls(self) -> list[ClientReply]:
        """The durable calls due (the actor: its stop withdraws them, its death fails them)."""
        with self._lock:
            return list(self._durable.values())

    def awaited(self, query_id: str) -> bool:
        """The actor: a notice waits for `query_id`'s answer; whether it is still due."""
        attempt = self._attempts.get(query_id)
        if attempt is None:
            return False
        attempt.mark_awaited()
        return True

    def settle(self, query_id: str, attempt: CallAttempt) -> bool:
        """`attempt`'s answer or failure was handled; whether it was the one due."""
        with self._lock:
            if self._attempts.get(query_id) is attempt:
                del self._attempts[query_id]
                self._durable.pop(query_id, None)
                return True
        return False


class ClientReply:
    """The answer to a consumer's load: wakes the caller's thread, which hands the record over
    (one wake-up); with `commit_first`, a `DurableLoaded` to the registrar. Describes the call."""

    __slots__ = (
        "attempt",
        "calls",
        "commit_first",
        "on_status",
        "parent",
        "query_id",
        "request",
        "server",
        "serving_rr",
    )

    def __init__(
        self,
        calls: Calls,
        query_id: str,
        serving_rr: str,
        server: str,
        request: Any,
        parent: str | None,
        on_status: StatusCallback | None,
        attempt: CallAttempt,
    ) -> None:
        self.calls = calls
        self.query_id = query_id
        self.serving_rr = serving_rr
        self.server = server
        self.request = request
        self.parent = parent
        self.on_status = on_status
        self.attempt = attempt
        self.commit_first = calls.commit_first

    def query(self, response: Any = None) -> Query:
        return Query(
            self.query_id, self.server, self.serving_rr, self.calls.name, self.request, response
        )

    def set_result(self, value: Any) -> None:
        if not self.commit_first:
            self.attempt.answer(value)  # (withdrawn: dropped, its caller gave the id back)
            return  # the caller records it
        query = self.query(value)
        record = ClientRecord(query, self.parent, loaded=True)
        loaded = DurableLoaded(record, self.on_status, self.attempt)
        try:
            if awaiting():  # (a loop's thread: the commit would hold the loop)
                self.calls.ref.tell(loaded)
            else:  # an idle consumer commits it on this thread, in its turn: no hand-off
                deliver(self.calls.ref, loaded)
        except pykka.ActorDeadError:  # the consumer stopped meanwhile: give the id back
            give_back(query.serving_rr, query.id, query.origin_rr)
            self.attempt.fail(
                RegistrarStoppedError(f"registrar {query.origin_rr!r} stopped during the call")
            )

    def set_error(self, error: BaseException, *, sent: bool = True) -> None:
        # A provider that died (or was stopped) may have executed the call: its id is
        # held until reconciled with the provider's next start, for a retry (rule 17).
        # Not one whose Load never left (`sent=False`): nothing there can hold its id.
        gone = sent and isinstance(error, RegistrarUnavailableError | RegistrarStoppedError)
        failed = CallFailed(
            self.query_id,
            self.attempt,
            serving_rr=self.serving_rr if gone else None,
            parent=self.parent,
            provider=self.serving_rr,
            server=self.server,
            error=error,
        )
        with contextlib.suppress(pykka.ActorDeadError):
            self.calls.hand_over(failed, wake=True)
        self.attempt.fail(error)


class Calls:
    """The caller-thread side of one registrar's calls (its handle holds one).
    `commit_first`: an answer is committed before its caller gets it; `stored`: requests and
    responses must pickle; `life`: the run each `Load` carries; `events`: while anyone
    listens, a plain answer wakes the actor."""

    def __init__(
        self,
        ref: pykka.ActorRef[Any],
        name: str,
        due: DueAnswers,
        *,
        commit_first: bool,
        stored: bool,
        probes: Callable[[], Probes | None],
        events: Publisher[Any],
        life: str = "",
    ) -> None:
        self.ref = ref
        self.name = name
        self.due = due
        self.commit_first = commit_first
        self.stored = stored
        self.probes = probes
        self.events = events
        self.life = life
        self.attempt_type: type[CallAttempt] = CallAttempt

    def steps(
        self,
        query_id: str,
        serving_rr: str,
        server: str,
        request: Any,
        parent: str | None,
        chain: tuple[str, ...],
        on_status: StatusCallback | None,
        limit: float,
        deadline: float,
        begun: tuple[str, str] | None = None,
        wait_overloaded: bool = True,
    ) -> Steps[Query]:
        """A call's steps: send its load, wait for its answer until `deadline` (rule 17).
        Raises `CallTimeoutError` (withdrawn, as when an exception is thrown in at a wait) or
        what it failed with. `parent`: the resource it is a dependency of; `chain`:
        those loading further up; `limit`: the timeout in s; `begun`: the trace context;
        `wait_overloaded`: ask again after a refusal."""
        pause, slowest = _FIRST_PAUSE, 0.0  # (the slowest refusal: a last try's margin)
        while True:  # (again only after an `OverloadedError`: the provider holds nothing)
            attempt, sent = self.new_attempt(begun), runtime.monotonic()
            trace = attempt.trace
            reply = ClientReply(
                self, query_id, serving_rr, server, request, parent, on_status, attempt
            )
            answered: Query | None = None
            withdrawn = False
            try:
                # a notice that overtakes the answer waits; a durable call's is the actor's
                self.due.expect(query_id, attempt, reply if self.commit_first else None)
                load = Load(
                    query_id,
                    server,
                    request,
                    self.name,
                    chain,
                    reply,
                    self.life,
                    trace,
                    deadline,
                    wait_overloaded,
                )
                self.send(load, reply)
                if not (yield attempt, deadline):  # the time is up: withdraw,
                    withdrawn = attempt.withdraw() is WITHDRAWN  # unless the
                    if not withdrawn:  # answer won (being recorded: its outcome comes
                        yield attempt, None  # with the commit)
                if attempt.state is ANSWERED:
                    answered = reply.query(attempt.get())
                    if self.stored and not self.commit_first:
                        check_picklable(  # stored with its record at the next flush
                            answered.response, f"the response of '{serving_rr}/{server}'"
                        )
                    if not self.commit_first:  # a durable one the registrar recorded already
                        loaded = ClientRecord(answered, parent, loaded=True)
                        # (a dependency's owner may be gone: it is given back at once)
                        outcome = ClientLoaded(loaded, on_status, attempt)
                        self.hand_over(outcome, wake=parent is not None or self.events.active)
            except pykka.ActorDeadError:  # this registrar stopped meanwhile: give the id back
                give_back(serving_rr, query_id, self.name)
                raise DIRECTORY.gone_error(self.name) from None
            except BaseException:  # the caller stops waiting (KeyboardInterrupt, cancelled)
                attempt.withdraw()
                self.withdraw(reply, attempt, "interrupted")
                raise
            if withdrawn:
                self.withdraw(reply, attempt)
                raise CallTimeoutError(
                    f"call to '{serving_rr}/{server}' timed out after {limit:g} s"
                )
            if answered is not None:
                return answered
            assert attempt.state is FAILED  # (neither answered nor withdrawn)
            try:
                attempt.get()  # raises what the call failed with
            except OverloadedError as refused:  # holding nothing: wait, then ask again
                pause = pause if refused.retry_after is None else refused.retry_after
                # a caller that cannot wait, or no time for a pause and the answer after it
                now = runtime.monotonic()  # (an answer may take twice the slowest so far)
                slowest = max(slowest, now - sent)
                answer = max(min(pause, _LAST_PAUSE), 2 * slowest)
                if not wait_overloaded or deadline - now <= pause + answer:
                    raise
            yield OneShotFuture(), runtime.monotonic() + pause  # (never settled: a pause)
            pause = min(2 * pause, _LAST_PAUSE)

    def new_attempt(self, begun: tuple[str, str] | None) -> CallAttempt:
        """A call's attempt, stamped with when it began and its caller's trace context `begun`."""
        attempt = self.attempt_type()
        if self.events.active:  # (its events say when it began)
            attempt.started = hlc.CLOCK.wall()
        if begun is not None:
            attempt.trace, attempt.caller_span = begun
        return attempt

    def send(self, load: Load, reply: ClientReply) -> None:
        """Send a call's `load` from the caller's thread, along the client's route (mailbox
        order holds); on a loop's thread an idle non-durable local provider may handle it."""
        if reply.attempt.sent() is not SENT:  # this registrar stopped
            return  # meanwhile and failed it: nothing to send
        probes = self.probes()
        if probes is not None:
            probes.fire("send_load", load)
        try:
            provider = DIRECTORY.lookup(reply.serving_rr)
            if awaiting():  # (on a loop) an idle provider of this process handles it here
                provider.deliver(load)  # (its turn, `_core/actor.py`): no thread hand-off
            else:
                provider.tell(load)
        except RrError as exc:  # refused at once: nothing was sent
            reply.set_error(exc, sent=False)

    def withdraw(self, reply: ClientReply, attempt: CallAttempt, why: str = "timeout") -> None:
        """Take back a call whose caller stopped waiting (rule 17): an answer coming later is
        dropped; the `Abandon`, told from this thread, follows the `Load` and precedes any
        retry. Not for a failed call: a retry with its id must find it."""
        probes = self.probes()
        if probes is not None:
            probes.fire("withdraw", reply.query())
        give_back(reply.serving_rr, reply.query_id, self.name, withdrawn=True)  # (then the
        self.withdrawn(reply.query_id, attempt, reply.serving_rr, reply.server, why)  # record)

    def withdrawn(self, qid: str, attempt: CallAttempt, to: str, server: str, why: str) -> None:
        """Tell the actor its caller withdrew `attempt` of `qid` (its id given back): it forgets
        the call and publishes its `CallWithdrawn` (`consumer.publish_failed`)."""
        failed = CallFailed(qid, attempt, withdrawn=True, provider=to, server=server, why=why)
        with contextlib.suppress(pykka.ActorDeadError):  # (stopped: nothing to tell)
            self.hand_over(failed, wake=True)

    def hand_over(self, outcome: Outcome, *, wake: bool) -> None:
        """Give the actor a call's `outcome` (any thread): a durable one by mailbox, else into
        `due.outcomes` (`wake` if awaited or past `BACKLOG`); `pykka.ActorDeadError` if ended."""
        if self.commit_first:
            self.ref.tell(outcome)
            return
        if not self.ref.is_alive():
            raise pykka.ActorDeadError(f"registrar {self.name!r} is not running")
        outcomes = self.due.outcomes
        outcomes.put(outcome)  # (then read the mark: see `DueAnswers.awaited`)
        if wake or outcome.attempt.awaited or outcomes.qsize() >= BACKLOG:
            with contextlib.suppress(pykka.ActorDeadError):  # (it ended: the outcome
                self.ref.tell(TakeOutcomes())  # went to its late handler)
