"""Calls that wait out a provider's restart, and ids abandoned while it was down.

```
 call_with_retry ── the consumer's call ──► provider ── answer ────────────────► Query
        │ RegistrarUnavailableError (it died), or stopped for a restart
        ▼
   the restart wait (a future the tree settles) ── back ──► the same call again, same id
        │ timed out, or interrupted (a cancelled task)
        ▼
   abandon_after_restart ── running? ── Abandon(id) to the provider now
                            down?    ── kept in the tree; sent by its next start
```

The retry is written once, as steps (`replies.Steps`): the consumer's call
(`call_steps`) and the restart wait (`tree.RestartWait`) are steps of their own, so
`Supervisor.call_with_retry` runs it blocking and `acall_with_retry` awaits it, with no
thread held while it waits. Built on the one handle class, `Registrar`, so the consumer
may be any registrar handle (in this process, or in a manager process).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from rr_actors._core import runtime
from rr_actors._core.ids import new_id
from rr_actors._core.replies import Steps
from rr_actors._registrar import Registrar, give_back
from rr_actors._registrar.handle import call_steps
from rr_actors._supervision.children import ChildInfo
from rr_actors._supervision.tree import Level, Tree, find_child
from rr_actors._types import Query, StatusCallback
from rr_actors.config import check_seconds
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    UnknownServerError,
)

__all__ = ["MISSING", "Restarts", "abandon_after_restart", "call_with_retry", "give_back_abandoned"]

_WAITING_STATES = ("stopping", "restarting", "starting")
"""States of a provider that its supervisor stopped to restart it."""


class Restarts(Protocol):
    """What `call_with_retry` asks of a supervision tree (a `Supervisor`)."""

    def child(self, name: str) -> ChildInfo:
        """The snapshot of child `name` anywhere in the tree (`UnknownServerError`)."""
        ...

    def _restart_wait(self, name: str, timeout: float, restarts: int | None) -> Steps[ChildInfo]:
        """The steps of a wait for child `name`'s restart (see `Supervisor.wait_restarted`)."""
        ...


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
    request: Any = MISSING,
    *,
    on_status: StatusCallback | None = None,
    timeout: float | None = None,
    query_id: str | None = None,
) -> Steps[Query]:
    """The steps of `Supervisor.call_with_retry` (which documents it) and its twin.

    Args:
        tree: the supervisor whose tree holds `target_rr`.
        abandon: `abandon(provider, query_id, origin)`: give the id back at the provider,
            now or when it is back (see `abandon_after_restart`).
        consumer, target_rr, server, request, on_status, timeout, query_id: as for
            `Supervisor.call_with_retry`.
    """
    _check(consumer, target_rr, server, request, timeout, query_id)
    limit = timeout if timeout is not None else consumer.config.call_timeout
    qid = query_id or new_id()
    deadline = runtime.monotonic() + limit
    while True:
        found = _lookup(tree, target_rr)
        before = found.restarts if found is not None else 0
        left = deadline - runtime.monotonic()
        if left <= 0:
            abandon(target_rr, qid, consumer.name)
            raise CallTimeoutError(f"call to '{target_rr}/{server}' timed out after {limit:g} s")
        try:
            return (
                yield from call_steps(
                    consumer,
                    target_rr,
                    server,
                    request,
                    on_status=on_status,
                    timeout=left,
                    query_id=qid,
                )
            )
        except RegistrarUnavailableError:
            if found is None or found.restart == "temporary":
                raise
        except RegistrarStoppedError:
            now = _lookup(tree, target_rr)  # stopped by its supervisor for a restart?
            if now is None or now.state not in _WAITING_STATES:
                raise
        wait = max(deadline - runtime.monotonic(), 1e-3)
        try:
            yield from tree._restart_wait(target_rr, wait, before + 1)
        except CallTimeoutError:
            abandon(target_rr, qid, consumer.name)
            raise CallTimeoutError(
                f"call to '{target_rr}/{server}' timed out after {limit:g} s while "
                f"{target_rr!r} was restarting"
            ) from None
        except BaseException as exc:
            if not isinstance(exc, Exception):  # interrupted (a cancelled task, Ctrl-C):
                abandon(target_rr, qid, consumer.name)  # withdrawn as a timeout withdraws it
            raise


def _check(
    consumer: object,
    target_rr: object,
    server: object,
    request: object,
    timeout: float | None,
    query_id: object,
) -> None:
    """`ConfigError` for an argument `call_with_retry` cannot use, before anything is sent."""
    if not isinstance(consumer, Registrar):
        raise ConfigError(
            "call_with_retry(consumer, target_rr, server, request): the consumer comes "
            f"first, a registrar (sup.registrar(name), a ResourceRegistrar), got {consumer!r}"
        )
    if request is MISSING:
        raise ConfigError(
            "call_with_retry(consumer, target_rr, server, request): request is missing"
        )
    for field, value in (("target_rr", target_rr), ("server", server)):
        if not isinstance(value, str):
            raise ConfigError(f"{field} must be a name (a str), got {value!r}")
    check_seconds("timeout", timeout, allow_none=True)
    if query_id is not None and not (isinstance(query_id, str) and query_id):
        raise ConfigError(
            f"query_id must be a non-empty str (or None: a fresh id), got {query_id!r}"
        )


def abandon_after_restart(tree: Tree, root: Level, name: str, query_id: str, origin: str) -> None:
    """Abandon `query_id` at provider `name`: now if it runs, else when it is back.

    Under the tree's abandon lock, which `give_back_abandoned` takes after a child was
    marked running: an id is either sent here or handed to the next start, never left
    behind.
    """
    with tree.abandon_lock:
        child = find_child(root, name)
        if child is None or child.state != "running" or child.running is None:
            tree.abandon_later.setdefault(name, []).append((query_id, origin))
            return
    give_back(name, query_id, origin)


def give_back_abandoned(tree: Tree, name: str) -> None:
    """Send provider `name`, just started, the ids abandoned while it was down."""
    with tree.abandon_lock:  # see abandon_after_restart
        abandoned = tree.abandon_later.pop(name, [])
    for query_id, origin in abandoned:
        give_back(name, query_id, origin)
