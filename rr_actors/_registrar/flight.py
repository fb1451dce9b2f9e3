"""A consumer's calls in flight: one record per query id, and what an answer does.

```
 query id ──► InFlight (Flights.in_flight; the registrar actor's thread only)
               ├─ attempt       a durable call whose pending record was committed:
               │                this actor answers its caller after the commit
               ├─ unsettled_at  the provider of a call that failed as it died or
               │                stopped: it may hold the id (a retry may come)
               └─ parked        notices that overtook the answer they are about
 the record goes when all three are empty (`InFlight.idle`)

 an answer ─► decide(durable, withdrawn, dependency, stopping, owner_gone) ─► Action
              (pure: every row in tests/registrar/test_answer_decision.py)
```

Like a `gen_statem` state function: the answers role reads what it knows (the message's
type says whether the call is durable; the attempt's `take()` whether its caller still
waits), `decide` names one `Action`, and it runs that action's step
(`Answers.record_answer`, `answers.py`). The records are kept by `flights.py`.
"""

from __future__ import annotations

import dataclasses
import enum
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rr_actors._registrar.attempt import CallAttempt
    from rr_actors._registrar.messages import ResponseUpdated, Revoke, StatusNotice

__all__ = ["Action", "InFlight", "decide"]


@dataclasses.dataclass(eq=False)
class InFlight:
    """What a consumer knows of one query id whose call is not settled yet.

    Attributes:
        attempt: a durable call's attempt whose pending record was committed (its
            `Pending`): this actor answers it after it commits the answer (`None`: no
            durable call with this id in flight). A same-id retry replaces it.
        unsettled_at: the provider of a call with this id that failed as that provider
            died or stopped: it may hold the id, and a retry may come; kept until a
            `Reconcile` with it was answered (`None`: none).
        parked: the notices (status, revoke, response update) that reached this
            registrar before the answer they are about, in arrival order.
    """

    attempt: CallAttempt | None = None
    unsettled_at: str | None = None
    parked: list[StatusNotice | Revoke | ResponseUpdated] = dataclasses.field(default_factory=list)

    def idle(self) -> bool:
        """Whether nothing is left of it (the consumer then forgets the record)."""
        return self.attempt is None and self.unsettled_at is None and not self.parked


class Action(enum.Enum):
    """What the consumer does with one call's answer (`decide`)."""

    KEEP = "keep"
    """A plain call's answer: record it (its caller has it already)."""
    COMMIT = "commit"
    """A durable call's answer: commit its record, then answer its caller (or, if it
    cannot be stored or written, give the id back and fail the call)."""
    LEAVE = "leave"
    """A durable answer its caller withdrew: nothing here (the caller gave the id back;
    its `CallFailed` forgets the pending record)."""
    GIVE_BACK = "give back"
    """A durable answer withdrawn or failed by a stop, while this registrar stops: give
    the id back (the stop's `Abandon` may have gone first) and forget the pending record."""
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
