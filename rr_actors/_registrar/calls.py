"""The call protocol, on the caller's thread: send, then the answer, a death, or the timeout.

```
 caller thread (Calls.steps)           consumer registrar actor          provider
 ───────────────────────────           ────────────────────────          ────────
 due.expect(id, attempt)
 attempt.sent(); Load(its run: life) ──────────────────────────────────► on_load
 attempt.wait(answer | error | timeout) ◄──── ClientReply (the answering thread) ◄─┘
   answered: ClientLoaded ──► due.outcomes ──► recorded before the actor's next message
   durable:  DurableLoaded ─────────► the record committed, then the caller answered
   timeout:  attempt.withdraw(), Abandon ───────────────────────────────► release the id
             CallFailed ────► due.outcomes + TakeOutcomes ──► forget the attempt's record
```

Like OTP's `gen:do_call` (monitor, send, receive the reply, the 'DOWN' or the timeout):
a provider that dies fails the reply at once (`RegistrarUnavailableError`), not after
the timeout. What a reply that races the timeout, a stop or a death does is decided by
one state under one lock, the call's `CallAttempt`; each transition returns the state
it leaves, and the party that took it acts on that state:

```
          sent()            answer(value): a plain call (its caller records it)
 SENDING ───────► SENT ─────────────────────────────────────────► ANSWERED
    │              │ └─take(): a durable call's answer ──► RECORDING  ▲
    │              │     settle(value): committed ───────────┴───────┘
    │              │     settle(error): not kept ──────────────────┐
    │              │  fail(error): an error answer, the provider    ▼
    ├──────────────┴─ died, the registrar stopped or died ──────► FAILED
    │              │  withdraw(): the caller's time ran out, or it
    └──────────────┴─ was interrupted ──────────────────────────► WITHDRAWN
```

A plain call's outcome waits for the actor (`DueAnswers.outcomes`); a durable one is
committed by the actor before its caller gets it (`consumer.py`). Why, and presumed
abort: docs/explanation/inside.md, "A call's outcome".
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
from rr_actors._core.actor import OneShotFuture, awaiting, deliver
from rr_actors._core.bus import Publisher
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.queues import LateQueue
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

__all__ = [
    "BACKLOG",
    "AttemptState",
    "CallAttempt",
    "CallFailed",
    "Calls",
    "ClientLoaded",
    "ClientReply",
    "DueAnswers",
    "DurableLoaded",
    "Outcome",
    "TakeOutcomes",
]


_FIRST_PAUSE = 0.005
"""Seconds a call refused for overload (`OverloadedError`) waits before it asks again,
when its provider does not say (its `retry_after`, else); each further refusal doubles
it, up to `_LAST_PAUSE`."""
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


_OPEN = (AttemptState.SENDING, AttemptState.SENT)


class CallAttempt(OneShotFuture[Any]):
    """One attempt of a call: the future its caller waits on, settled through one `state`.

    Three threads race over it (the module's second diagram): its caller (whose time may
    run out), the thread that brings the answer (a connection's reader, or the
    provider's actor), and its registrar's actor (which commits a durable call's answer,
    and fails the calls in flight when it stops or dies).

    ```
     transition (who)                returns    what its caller does then
     sent() (the caller)             SENT       sends the Load
                                     FAILED     sends nothing: the registrar stopped
     answer(v) (answering thread)    ANSWERED   nothing: the caller wakes, records it
                                     WITHDRAWN  nothing: the caller gave the id back
     take() (actor: durable answer)  RECORDING  commits the record, then settle() on
                                                every path
                                     WITHDRAWN  drops the answer (the caller gave the
                                     or FAILED  id back; a stopping registrar does too)
     settle(v | e) (the actor)       ANSWERED   nothing more: the caller wakes
                                     or FAILED
     fail(e) (any)                   FAILED     nothing more: the caller wakes
     fail_open(e) (the actor stops)  True       gives a durable call's id back (Abandon)
                                     False      nothing: its outcome comes
     withdraw() (the caller)         WITHDRAWN  gives the id back (Abandon), tells its
                                                registrar (CallFailed): nothing is left
                                     RECORDING  waits for the commit, reads the outcome
                                     ANSWERED   reads the outcome (the answer won)
                                     or FAILED
    ```

    A transition that does not apply leaves the state as it is (the first settle wins;
    only the actor that took a `RECORDING` attempt settles it). Entering `ANSWERED` or
    `FAILED` wakes the caller (`get` returns the value or raises the error).
    """

    # What its events tell (set by its caller when known): when the call began (wall
    # clock seconds, 0.0: not known) and its trace context (`_core/traces.py`).
    started = 0.0
    trace = ""
    caller_span = ""

    def __init__(self) -> None:
        super().__init__()
        self._state_lock = runtime.Lock()
        self.state = AttemptState.SENDING
        self._awaited = False

    def __repr__(self) -> str:
        return f"<rr_actors.CallAttempt {self.state.value}>"

    @property
    def awaited(self) -> bool:
        """Whether a notice waits for this call's answer (`mark_awaited`): its caller then
        wakes the registrar actor for the outcome it hands over (`DueAnswers`)."""
        with self._state_lock:
            return self._awaited

    def mark_awaited(self) -> None:
        """The registrar actor: a notice waits for this call's answer (`awaited`).

        Under the state lock, like every transition: the caller that reads the mark after
        it handed its outcome over, and the actor that takes the outcomes after it marked,
        are ordered by it, so one of the two sees the other's write.
        """
        with self._state_lock:
            self._awaited = True

    def sent(self) -> AttemptState:
        """The caller: its `Load` leaves now (`SENT`), unless it failed meanwhile."""
        with self._state_lock:
            if self.state is AttemptState.SENDING:
                self.state = AttemptState.SENT
            return self.state

    def answer(self, value: Any) -> AttemptState:
        """The answering thread: a plain call's answer came; its caller records it."""
        with self._state_lock:
            if self.state in _OPEN:
                self._settle_as(AttemptState.ANSWERED, value, None)
            return self.state

    def take(self) -> AttemptState:
        """The registrar actor: a durable call's answer came; commit it (`RECORDING`)."""
        with self._state_lock:
            if self.state in _OPEN:
                self.state = AttemptState.RECORDING
            return self.state

    def settle(self, value: Any = None, error: BaseException | None = None) -> AttemptState:
        """The actor that took it: the answer is committed (`value`), or not kept (`error`)."""
        with self._state_lock:
            if self.state is AttemptState.RECORDING:
                state = AttemptState.ANSWERED if error is None else AttemptState.FAILED
                self._settle_as(state, value, error)
            return self.state

    def fail(self, error: BaseException) -> AttemptState:
        """Any party: the call failed with `error` (unless it was settled or taken)."""
        with self._state_lock:
            if self.state in _OPEN:
                self._settle_as(AttemptState.FAILED, None, error)
            return self.state

    def fail_open(self, error: BaseException) -> bool:
        """The registrar actor, as it stops: fail the call with `error` if it is still
        open (`SENDING` or `SENT`); whether this did (else its outcome comes anyway)."""
        with self._state_lock:
            if self.state not in _OPEN:
                return False
            self._settle_as(AttemptState.FAILED, None, error)
            return True

    def withdraw(self) -> AttemptState:
        """The caller: it stops waiting (`WITHDRAWN`), unless the answer won the race."""
        with self._state_lock:
            if self.state in _OPEN:
                self._settle_as(AttemptState.WITHDRAWN, None, None)
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
    """A durable call's answer: the registrar commits its record, then answers the caller.

    Its caller still waits (`CallAttempt.take`); told by the answering thread. Handled
    as a `ClientLoaded` (the same step, `client_loaded`); its type is what says the
    registrar answers the caller.
    """


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
    """Wake the actor for the outcomes waiting in `DueAnswers.outcomes` (taken before
    every message it handles: this one only wakes it for those something waits for)."""


BACKLOG = 64
"""Plain outcomes that may wait for the registrar actor before a caller wakes it."""

Outcome = ClientLoaded | CallFailed


class DueAnswers:
    """The query ids whose answer a consumer has not recorded yet, with their attempt.

    Shared by the registrar's callers and its actor: a caller adds its query id before
    its `Load` leaves; the actor removes it once it handled that attempt's answer
    (`ClientLoaded`) or failure (`CallFailed`). Across processes the provider's notices
    about a query (status, response update, revoke) travel on the provider's connection
    to this registrar's listener, while the answer comes back on this process's
    connection to the provider, read by another thread: a notice can overtake the answer
    it is about. The actor holds such a notice until the query id is no longer due. The
    lock makes "remove it if it is still this attempt's" atomic against a retry that
    reuses the query id.

    `outcomes` holds the outcomes of plain calls in the order their threads handed them
    over (the module's first diagram). Once the actor ended, an outcome handed over goes to its
    `late` handler at once (a `LateQueue`), which gives the id back.
    """

    __slots__ = ("_attempts", "_durable", "_lock", "outcomes")

    def __init__(self) -> None:
        self._attempts: dict[str, CallAttempt] = {}
        self._durable: dict[str, ClientReply] = {}  # of the durable calls among them
        self._lock = runtime.Lock()
        self.outcomes = LateQueue()

    def __contains__(self, query_id: str) -> bool:
        return query_id in self._attempts

    def ids(self) -> frozenset[str]:
        """A snapshot of the query ids whose answer is due."""
        with self._lock:
            return frozenset(self._attempts)

    @contextlib.contextmanager
    def frozen(self) -> Iterator[tuple[frozenset[str], frozenset[str]]]:
        """The ids due, and those of them whose caller withdrew the call, with no call
        starting until the block ends.

        A caller's `expect` waits for the block, so whatever it sends follows what the
        block sent on the same channel (a `Reconcile` lists every call sent before it).
        A withdrawn call is due until the actor handled its `CallFailed`; its id was
        given back already (its `Abandon` may have died with the provider), so a
        `Reconcile` must not list it (issue 51).
        """
        with self._lock:
            withdrawn = frozenset(
                q for q, a in self._attempts.items() if a.state is AttemptState.WITHDRAWN
            )
            yield frozenset(self._attempts) - withdrawn, withdrawn

    def expect(
        self, query_id: str, attempt: CallAttempt, durable: ClientReply | None = None
    ) -> None:
        """A call `attempt` with `query_id` is about to be sent (any thread); `durable`:
        a durable call's reply (its registrar answers it: `durable_calls`)."""
        with self._lock:
            self._attempts[query_id] = attempt
            if durable is not None:
                self._durable[query_id] = durable
            else:
                self._durable.pop(query_id, None)

    def durable_attempt(self, query_id: str) -> CallAttempt | None:
        """The attempt of `query_id`'s call due, if it is a durable one."""
        with self._lock:
            return self._attempts.get(query_id) if query_id in self._durable else None

    def durable_calls(self) -> list[ClientReply]:
        """The durable calls due (the actor: its stop withdraws them, its death fails them)."""
        with self._lock:
            return list(self._durable.values())

    def awaited(self, query_id: str) -> bool:
        """The actor: a notice waits for `query_id`'s answer; whether it is still due.

        Marks its attempt (`CallAttempt.awaited`): its caller, reading the mark after it
        handed the outcome over, wakes the actor for it. The actor takes the outcomes
        once more after marking, so one of the two sees the other's write.
        """
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
    """The answer to a consumer's load: hand it to the caller, who records it.

    The caller's thread wakes with the value and hands the consumer's registrar the
    client record itself: the answering thread (a connection's reader, or the provider's
    actor) wakes one thread, not two, and the caller's later `unload` finds the record
    (`DueAnswers.outcomes`). A notice about the query that reaches the registrar before
    the record waits for it (`DueAnswers`).

    With `commit_first` (a durable consumer) the answer goes to the registrar as a
    `DurableLoaded`: it takes the attempt, commits the record and then settles it (or,
    finding it withdrawn, gives the id back). Nothing was written before the load was
    sent (presumed abort, the module docstring).

    It also describes the call (its id, provider, server, request and parent), so that
    the caller's thread builds one `Query`, the answered one.
    """

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
        """The call's query, with `response`."""
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

    Args:
        ref: the consumer registrar actor.
        name: its name.
        due: the answers due, shared with the actor.
        commit_first: its calls are durable (a backup with `save_on_modify`): an answer
            is committed before its caller gets it.
        stored: its client records are stored (a backup), so requests and responses
            must pickle.
        life: the registrar's run (`Shared.life`), carried by each `Load`.
        probes: the registrar's test probes, read when a call is withdrawn.
        events: the registrar's events: when anyone listens (`active`), a plain call's
            answer wakes the actor, which publishes its `CallAnswered` at once.
    """

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

        Each wait is a `yield` (`replies.Steps`): `run_steps` blocks the caller's thread
        on it, `loops.run_steps_async` awaits it. An exception thrown in at a wait (a
        `KeyboardInterrupt`, a cancelled task) withdraws the call as a timeout does.

        Args:
            query_id: the call's query id.
            serving_rr: the provider registrar's name.
            server: the server's name there.
            request: what the call asks for.
            parent: the resource of this registrar the call is a dependency of, if any.
            chain: the resources being loaded further up (cycle detection).
            on_status: the client status callback to record with the answer.
            limit: the call's timeout in seconds (for the error message).
            deadline: when to give up (`time.monotonic()` seconds).
            begun: the caller's trace context (`_core/traces.py`'s `begin`): the
                `Load` carries its traceparent, the call's events both.
            wait_overloaded: whether a refusal for overload is asked again after a pause
                (while the time lasts), or raised at once (`if_overloaded="raise"`).

        Returns:
            The call's `Query`, with its response.

        Raises:
            CallTimeoutError: no answer in time; the call was withdrawn.
            RrError: what the call failed with.
        """
        pause = _FIRST_PAUSE
        while True:  # (again only after an `OverloadedError`: the provider holds nothing)
            attempt = self.new_attempt(begun)
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
                    withdrawn = attempt.withdraw() is AttemptState.WITHDRAWN  # unless the
                    if not withdrawn:  # answer won (being recorded: its outcome comes
                        yield attempt, None  # with the commit)
                if attempt.state is AttemptState.ANSWERED:
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
            assert attempt.state is AttemptState.FAILED  # (neither answered nor withdrawn)
            try:
                attempt.get()  # raises what the call failed with
            except OverloadedError as refused:  # holding nothing: wait, then ask again
                pause = pause if refused.retry_after is None else refused.retry_after
                # a caller that cannot wait, or no time for a pause and the answer after it
                left = deadline - runtime.monotonic()
                if not wait_overloaded or left <= pause + min(pause, _LAST_PAUSE):
                    raise
            yield OneShotFuture(), runtime.monotonic() + pause  # (never settled: a pause)
            pause = min(2 * pause, _LAST_PAUSE)

    def new_attempt(self, begun: tuple[str, str] | None) -> CallAttempt:
        """A call's attempt, stamped with when it began (while events are made) and with
        its caller's trace context `begun` (`(traceparent, caller's span)`, or `None`)."""
        attempt = self.attempt_type()
        if self.events.active:  # (its events say when it began)
            attempt.started = hlc.CLOCK.wall()
        if begun is not None:
            attempt.trace, attempt.caller_span = begun
        return attempt

    def send(self, load: Load, reply: ClientReply) -> None:
        """Send a call's `load` from the caller's thread (nothing is written first, also
        for a durable call: presumed abort, the module docstring).

        Along the client's route rather than through the client's mailbox: one thread
        hand-off less; mailbox order still holds, a later withdrawal reaches its actors
        after this. From an event loop's thread (an awaited call), an idle provider of
        this process handles the load in its turn on that thread, as a carrier's
        receiving thread may (`_core/actor.py`): a dedup hit is answered before the
        call awaits anything, and the loop is not woken from another thread. A durable
        provider's load (`save_on_modify`) goes to its own thread: its commit would
        hold the loop (`LocalPeer.deliver`).
        """
        if reply.attempt.sent() is not AttemptState.SENT:  # this registrar stopped
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
        """Take back a call whose caller stopped waiting: leave nothing behind (rule 17).

        The caller withdrew `attempt`, so an answer that comes later is dropped (or, for a
        durable call, not kept). Told from the caller's thread, like the `Load`: the
        provider sees the `Abandon` after the `Load` and before any retry this caller makes
        with the same id. Not for a call that failed: its provider may hold a committed id
        that a retry with the same id must find (`Supervisor.call_with_retry`).
        """
        probes = self.probes()
        if probes is not None:
            probes.fire("withdraw", reply.query())
        give_back(reply.serving_rr, reply.query_id, self.name)
        with contextlib.suppress(pykka.ActorDeadError):  # after: a crash in between keeps
            withdrawn = CallFailed(
                reply.query_id,
                attempt,
                withdrawn=True,
                provider=reply.serving_rr,
                server=reply.server,
                why=why,
            )
            self.hand_over(withdrawn, wake=True)  # the record

    def hand_over(self, outcome: Outcome, *, wake: bool) -> None:
        """Give the registrar actor a call's `outcome` to record (any thread).

        A plain call's waits in `due.outcomes` (module docstring); the actor is woken for
        it with `wake`, when a notice waits for its answer, or when `BACKLOG` wait. A
        durable registrar's go through its mailbox, in order with its answers.

        Raises:
            pykka.ActorDeadError: the registrar actor is not running.
        """
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
