"""The consumer's side of a call as events: answered, failed, withdrawn, forgotten.

```
 answers.py  record_answer ──► answer ────► CallAnswered (the id is held), committed
                                            with its record, then published
             on_call_failed ─► failed ────► CallFailed | CallWithdrawn (nothing held;
                                            or held until reconciled: may_have_executed)
 holdings.py forget ─────────► forgotten ─► QueryForgotten (why)
```

Each builds its event only when someone listens (`Shared.events.active`) and runs on
the registrar actor's thread, so a consumer's events are in the order it recorded
them (an id is answered before it is forgotten).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from rr_actors import events
from rr_actors._registrar.attempt import AttemptState

if TYPE_CHECKING:
    from rr_actors._catalog import ClientRecord
    from rr_actors._registrar.messages import CallFailed
    from rr_actors._registrar.state import Shared
    from rr_actors._types import Query

__all__ = ["answer", "answered", "failed", "forgotten", "refused"]


def answer(shared: Shared, record: ClientRecord, *, retry: bool) -> tuple[events.Event, ...]:
    """`CallAnswered` of `record` (none while nobody listens), to commit with its record."""
    if not shared.events.active:
        return ()
    query = record.query
    return (
        events.CallAnswered(
            shared.name, query.id, query.serving_rr, query.server, record.parent, retry
        ),
    )


def answered(shared: Shared, record: ClientRecord, *, retry: bool) -> None:
    """Publish `CallAnswered`: `record`'s answer is recorded (`retry`: its id was known)."""
    shared.publish(*answer(shared, record, retry=retry))


def failed(shared: Shared, message: CallFailed, *, retry: bool) -> None:
    """Publish `CallWithdrawn` or `CallFailed` for a call's failure `message`.

    An error answer to an attempt its caller withdrew first (the provider's answer to
    the `Abandon` that followed its `Load`) publishes nothing: the withdrawal was the
    call's outcome.
    """
    if not shared.events.active:
        return
    if not message.withdrawn and message.attempt.state is AttemptState.WITHDRAWN:
        return
    if message.withdrawn:
        shared.events.publish(
            events.CallWithdrawn(
                shared.name, message.query_id, message.provider, message.server, message.why
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
        )
    )


def refused(shared: Shared, query: Query, error: BaseException) -> None:
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
            )
        )


def forgotten(shared: Shared, query: Query, reason: str) -> None:
    """Publish `QueryForgotten`: the consumer no longer holds `query` (`reason`)."""
    if shared.events.active:
        shared.events.publish(
            events.QueryForgotten(shared.name, query.id, query.serving_rr, reason)
        )
