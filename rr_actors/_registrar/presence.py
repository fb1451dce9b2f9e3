"""Presence: what a registrar does when a peer is lost for good, or reachable again.

Who is gone for good is known per process, by its membership
(`rr_actors._core.membership`): a carrier (the AF_UNIX one on one machine, Zenoh across
hosts) feeds it from its liveness (`_transport/messenger.py`), the death watch
(`deathwatch.py`) from what supervisors and owners know, and a mark of another process
(`ConsumerDown` on the wire, handled here) is fed into it too. It tells each registrar of
the process one event, `PeerLost` (through `Served.peer_lost`), and tells one that starts
later the names gone for good then (`starting.py`). This role is the one place that
decides what they mean for the catalog:

```
 another process's death watch ─► ConsumerDown(name) ─► MEMBERSHIP.lost(name)
 the membership ── Served.peer_lost(name) ──► PeerLost ──► lose(name)     (rule 19)
     as a provider: every id `name` held here is released (each `unload` runs once)
     as a consumer: the ids held at `name` get `FATAL` (and up their dependents), then
                    they are forgotten (a later `unload` of one: `UnknownQueryError`)
 carrier ── Endpoint.peer_reachable(name) ──► PeerReachable ──► on_peer_reachable
     as a consumer: `Reconcile` with `name`; retried (ReconcileRetry, after a bounded
                    backoff, or when unanswered within `call_timeout`) until it is
                    answered, `name` is lost or stopped, or this registrar stops
     as a provider: `ReconcileAsk` to `name` when it holds ids here (once: the peer's
                    own carrier tells it that this one is reachable, and it retries)
```

A provider that its supervisor restarts is not lost (rule 15): nobody sends a
`ConsumerDown` for it, its restored catalog keeps its consumers' ids, and it reconciles
by itself when it serves again (`lifecycle.py`).
"""

from __future__ import annotations

import contextlib
import logging

import pykka

from rr_actors._core.directory import DIRECTORY, Reply
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._core.timers import Cancellable, Timer, thread_timer
from rr_actors._registrar.messages import (
    ConsumerDown,
    PeerLost,
    PeerReachable,
    ReconcileAsk,
    ReconcileRetry,
)
from rr_actors._registrar.reconciling import Reconciling
from rr_actors._registrar.state import Phase, Shared
from rr_actors._registrar.unloading import Unloading
from rr_actors.errors import RegistrarStoppedError, RrError

__all__ = ["RETRY_FIRST", "RETRY_MAX", "Presence", "retry_delay"]

logger = logging.getLogger("rr_actors")

RETRY_FIRST = 0.05
"""Seconds before the first retry of a `Reconcile` that failed after a healed link."""

RETRY_MAX = 2.0
"""The longest wait between two retries (the backoff doubles up to it)."""


def retry_delay(attempt: int) -> float:
    """Seconds to wait before retry `attempt` (1, 2, ...): doubling, at most `RETRY_MAX`."""
    return float(min(RETRY_MAX, RETRY_FIRST * 2 ** max(0, min(attempt - 1, 16))))


class Presence:
    """The registrar's answers to a carrier's presence callbacks (runs on the actor thread).

    Args:
        registrar: the state every role shares.
        unloading: releases the ids a lost consumer held here.
        reconciling: whether it holds ids at a peer; reports and forgets the ids held at
            a lost provider; reconciles.
        timer: `timer(delay, fn)` for the retries (injectable for tests).

    Attributes:
        rounds: provider -> (its reconcile round, the attempt waited for) while a
            reconcile after a healed link is not answered yet.
    """

    def __init__(
        self,
        registrar: Shared,
        unloading: Unloading,
        reconciling: Reconciling,
        timer: Timer = thread_timer,
    ) -> None:
        self.registrar = registrar
        self.unloading = unloading
        self.reconciling = reconciling
        self.timer = timer
        self.rounds: dict[str, tuple[int, int]] = {}
        self.timers: dict[str, Cancellable] = {}
        self.round_count = 0

    # -- lost for good (rule 19) --------------------------------------------------------

    def on_peer_lost(self, message: PeerLost, _reply: Reply) -> None:
        if message.stopped:
            self.stopped(message.name)
        else:
            self.lose(message.name)

    def on_consumer_down(self, message: ConsumerDown, _reply: Reply) -> None:
        """The wire mark of another process's death watch: into this process's
        membership, which tells every registrar here (this one too: `PeerLost`)."""
        by = f"a death-watch mark to {self.registrar.name}"
        if message.stopped:
            MEMBERSHIP.stopped(message.origin_rr, by=by)
        else:
            MEMBERSHIP.lost(message.origin_rr, by=by)

    def stopped(self, name: str) -> None:
        """Registrar `name` was stopped and nobody will start it again: it holds nothing
        (rule 12), so every id of it still here is released (ids it forgot while this
        one was down, which no reconcile will name now); what this one holds there is
        left as a stop leaves it."""
        if name == self.registrar.name:
            return
        self.unloading.release_stopped(name)

    def lose(self, name: str) -> None:
        """Registrar `name` is gone and nobody will restart it: release what it held here,
        report what this one held there `FATAL` and forget it (a second time: nothing)."""
        if name == self.registrar.name:
            return
        self.stop_retrying(name)
        self.unloading.release_all_of(name)
        self.reconciling.lose_provider(name)

    # -- reachable again (rule 20) ------------------------------------------------------

    def on_peer_reachable(self, message: PeerReachable, _reply: Reply) -> None:
        name = message.name
        if name == self.registrar.name or self.registrar.phase is not Phase.SERVING:
            return  # (during setup `on_ready` reconciles with everyone; stopping: nothing)
        if self.reconciling.holds_at(name):
            self.round_count += 1
            self.attempt(name, self.round_count, 0)
        if self.registrar.catalog.consumers_from(name):
            try:
                DIRECTORY.lookup(name).tell(ReconcileAsk(self.registrar.name))
            except RrError as exc:
                logger.debug(
                    "registrar %s: %s not reachable yet: %s", self.registrar.name, name, exc
                )

    def on_reconcile_retry(self, message: ReconcileRetry, _reply: Reply) -> None:
        if self.rounds.get(message.name) != (message.round, message.attempt - 1):
            return  # answered meanwhile, lost, or a newer round started
        if self.registrar.phase is not Phase.SERVING:
            self.stop_retrying(message.name)
            return
        self.attempt(message.name, message.round, message.attempt)

    def attempt(self, name: str, round_: int, attempt: int) -> None:
        """Send `Reconcile` attempt `attempt` of round `round_` to provider `name`.

        An attempt not answered within `call_timeout` is retried (a token that is back
        is not yet a peer that answers: a carrier may lose what it is sent meanwhile).
        """
        self.stop_retrying(name)
        self.rounds[name] = (round_, attempt)
        self.arm(name, round_, attempt + 1, self.registrar.config.call_timeout)
        self.reconciling.reconcile(
            name, then=lambda error: self.answered(name, round_, attempt, error)
        )

    def answered(self, name: str, round_: int, attempt: int, error: BaseException | None) -> None:
        if self.rounds.get(name) != (round_, attempt):
            return  # a late answer of an attempt given up (the newer one decides)
        if error is None or isinstance(error, RegistrarStoppedError):
            self.stop_retrying(name)  # reconciled; or stopped: its restart reconciles
            return
        logger.debug(
            "registrar %s: reconcile %d with %s failed (%s); retrying",
            self.registrar.name,
            attempt,
            name,
            error,
        )
        self.arm(name, round_, attempt + 1, retry_delay(attempt + 1))

    def arm(self, name: str, round_: int, attempt: int, delay: float) -> None:
        """Tell this actor `ReconcileRetry(name, round_, attempt)` after `delay` seconds."""
        old = self.timers.pop(name, None)
        if old is not None:
            old.cancel()
        ref = self.registrar.ref

        def fire() -> None:
            with contextlib.suppress(pykka.ActorDeadError):
                assert ref is not None
                ref.tell(ReconcileRetry(name, round_, attempt))

        self.timers[name] = self.timer(delay, fire)

    def stop_retrying(self, name: str) -> None:
        self.rounds.pop(name, None)
        timer = self.timers.pop(name, None)
        if timer is not None:
            timer.cancel()

    def close(self) -> None:
        """This registrar stops or died: no more retries."""
        for name in list(self.rounds):
            self.stop_retrying(name)
