"""One call attempt as a state machine: what a reply racing a timeout, a stop or a death does.

The call protocol (`calls.py`) and the answers role (`answers.py`) act on the state a
transition returns; this module holds only the states and the transitions (under one
lock), so that messages can carry an attempt without importing the call protocol.
"""

from __future__ import annotations

import enum
import threading
from typing import Any

from rr_actors._core.actor import OneShotFuture

__all__ = ["AttemptState", "CallAttempt"]


class AttemptState(enum.Enum):
    """Where one call attempt is (see `CallAttempt`)."""

    SENDING = "sending"
    """Its `Load` has not left yet (a durable call: its record is written as pending)."""
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

    Three threads race over an attempt: its caller (whose time may run out), the thread
    that brings the answer (a connection's reader, or the provider's actor), and its
    registrar's actor (which commits a durable call's answer, and fails the calls in
    flight when it stops or dies). Each transition is taken under one lock and returns
    the state it leaves the attempt in; the party that called it acts on that state.

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

    def __init__(self) -> None:
        super().__init__()
        self._state_lock = threading.Lock()
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
