"""Calls that wait out a provider's restart.

```
 call_with_retry ── the consumer's call ──► provider ── answer ────────────────► Query
        │ RegistrarUnavailableError (it died), or stopped for a restart
        ▼
   the restart wait (a future the tree settles) ── back ──► the same call again, same id
     for the next restart; for the one that ran (at once) if the tree says it was not
     killed since the try began, once per restart count (restart_after_failure)
        │ timed out, or interrupted (a cancelled task, an error)
        ▼
   abandon (`Tree.abandon`) ── running? ── Abandon(id) to the provider now
        │                      down?    ── kept in the tree; sent by its next start
   withdrawn at the consumer, wherever it lives (`Here.withdrawn`): its `CallWithdrawn`
```

Written once, as steps (`replies.Steps`): `call_with_retry` runs them blocking,
`acall_with_retry` awaits them; the consumer may be any `Registrar` handle.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable
from typing import Any, Protocol

from rr_actors._core import runtime
from rr_actors._core.replies import Steps
from rr_actors._registrar import Registrar
from rr_actors._registrar.handle import Here, call_steps
from rr_actors._supervision.children import ChildInfo
from rr_actors._types import Query, StatusCallback
from rr_actors.config import check_seconds, check_strs
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
    UnknownServerError,
)

_WAITING_STATES = ("stopping", "restarting", "starting")  # stopped by its supervisor to restart


class Restarts(Protocol):
    """What `call_with_retry` asks of a supervision tree (a `Supervisor`)."""

    def child(self, name: str) -> ChildInfo: ...

    def _restart_wait(
        self, name: str, timeout: float, restarts: int | None
    ) -> Steps[ChildInfo]: ...


def _lookup(tree: Restarts, name: str) -> ChildInfo | None:
    try:
        return tree.child(name)
    except UnknownServerError:
        return None


MISSING: Any = object()
"""`call_with_retry`'s `request` when none was given (told as a `ConfigError`)."""


def call_with_retry(
    tree: Restarts,
    abandon: Callable[[str, str, str], None],
    consumer: Registrar,
    target_rr: str,
    server: str,
    request: Any,
    on_status: StatusCallback | None,
    timeout: float | None,
    query_id: str | None,
) -> Steps[Query]:
    """The steps of `Supervisor.call_with_retry` (which documents it); `abandon(provider,
    query_id, origin)` gives the id back, now or when it is back."""
    _check(consumer, target_rr, server, request, timeout, query_id)
    limit = timeout if timeout is not None else consumer.config.call_timeout
    qid = query_id or runtime.new_id()
    deadline, started = runtime.monotonic() + limit, runtime.wall()
    tried_again_at = -1  # the restart count at which it last tried again at once
    call = functools.partial(
        call_steps, consumer, target_rr, server, request, on_status=on_status, query_id=qid
    )

    def give_up(why: str = "timeout", while_: str = "") -> CallTimeoutError:  # (the id given
        abandon(target_rr, qid, consumer.name)  # back, the call withdrawn where it lives)
        told = consumer._actor.steps(Here.withdrawn, None, qid, target_rr, server, why, started)
        with contextlib.suppress(StopIteration, RrError):
            next(told)  # (a notice: sent at its first step, not waited for)
        told.close()
        return CallTimeoutError(
            f"call to '{target_rr}/{server}' timed out after {limit:g} s{while_}"
        )

    while True:
        found = _lookup(tree, target_rr)
        before = found.restarts if found is not None else 0
        left = deadline - runtime.monotonic()
        if left <= 0:
            raise give_up()
        try:
            return (yield from call(timeout=left))
        except RegistrarUnavailableError:
            if found is None or found.restart == "temporary":
                raise
            target = restart_after_failure(found, _lookup(tree, target_rr), tried_again_at)
        except RegistrarStoppedError:
            now = _lookup(tree, target_rr)  # stopped by its supervisor for a restart?
            if now is None or now.state not in _WAITING_STATES:
                raise
            target = before + 1
        if target == before:
            tried_again_at = before
        wait = max(deadline - runtime.monotonic(), 1e-3)
        try:
            yield from tree._restart_wait(target_rr, wait, target)
        except CallTimeoutError:
            raise give_up(while_=f" while {target_rr!r} was restarting") from None
        except BaseException:  # interrupted (a cancelled task, Ctrl-C, an error): withdrawn
            give_up("interrupted")  # as a timeout withdraws it
            raise


def restart_after_failure(before: ChildInfo, now: ChildInfo | None, tried_again_at: int) -> int:
    """The restart count to wait for after a call failed as unavailable (the tree said
    `before` when the call began, says `now`): `before.restarts` if it was down then (the
    start under way brings it back); `+ 1` if it was killed since, or was tried again at
    once at this count already; else `before.restarts` (try again at once).

    Trying again at once, once per count: a provider restarted before `before` was read
    may not be seen served here yet (across hosts), and no further restart would come.
    """
    if before.state not in ("running", "exited", "stopped"):
        return before.restarts
    if (
        now is None
        or now.state != "running"
        or now.restarts > before.restarts
        or tried_again_at == before.restarts
    ):
        return before.restarts + 1
    return before.restarts


def _check(
    consumer: object,
    target_rr: object,
    server: object,
    request: object,
    timeout: float | None,
    query_id: object,
) -> None:
    if not isinstance(consumer, Registrar):
        raise ConfigError(
            "call_with_retry(consumer, target_rr, server, request): the consumer comes "
            f"first, a registrar (sup.registrar(name), a ResourceRegistrar), got {consumer!r}"
        )
    if request is MISSING:
        raise ConfigError(
            "call_with_retry(consumer, target_rr, server, request): request is missing"
        )
    check_strs(target_rr=target_rr, server=server)
    check_seconds("timeout", timeout, allow_none=True)
    if query_id is not None and not (isinstance(query_id, str) and query_id):
        raise ConfigError(
            f"query_id must be a non-empty str (or None: a fresh id), got {query_id!r}"
        )
