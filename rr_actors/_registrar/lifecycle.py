"""A registrar actor's life: start (settle what a crash cut short), serve, stop or die.

```
 SETTING_UP ──ready──► SERVING ──stop()──► STOPPING ──► ENDED
      └──────────────────┴── crash (a bug, testing.crash) ─────► ENDED (death)
```

Starting settles what the last run left in doubt (rule 16); while the manager's `setup`
runs, that settling is kept out of the backup, so a crash during `setup` offers the same
entries to the next one (`settle_held`, once `setup` returned). That settling, and the
sweep of the restored catalog after it serves, are `restoring.py`'s:

```
 on_start ──► restoring: settle_in_doubt, unload_unheld (the sweep starts)
          ──► presence: the peers lost meanwhile ──► reconcile (now, or on Ready)
 reconcile ──► restoring.ask_consumers (ReconcileAsk) + reconciling.reconcile_all
 YieldName (a carrier: another registrar of its name is kept, rule 22)
      ──► servers.give_up_all: every served resource released and unloaded ──► Stop
 Stop ──► releases: withdraw_pending, give_back_unsettled, release_client (newest first)
      ──► the unloads under way (teardown.py), at most until `unloads_until`
      ──► the backup flushed and closed ──► children stopped ──► ENDED
 death ──► every waiter failed (provider.py, flights.py, open requests, the mailbox)
```

A clean stop releases what
this registrar holds as a consumer, newest first (rule 12), keeps what its servers serve
(a restart needs it), flushes and closes the backup. A death fails every waiting caller
at once (`RegistrarUnavailableError`), writes nothing more, and tells the providers this
consumer is gone unless a supervisor will restart it (death watch).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import pykka

from rr_actors import events
from rr_actors._catalog import ClientRecord, Resource
from rr_actors._core.actor import Actor, OneShotFuture, refuse
from rr_actors._core.directory import DIRECTORY, LocalPeer, Reply
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._core.replies import FutureReply
from rr_actors._core.timers import Cancellable, thread_timer
from rr_actors._registrar import chronicle
from rr_actors._registrar.deathwatch import gone_for_good
from rr_actors._registrar.messages import (
    ClientLoaded,
    Crash,
    Flush,
    PeerLost,
    PeerReachable,
    Reachable,
    Ready,
    Save,
    Snapshot,
    Stop,
    YieldName,
    give_back,
)
from rr_actors._registrar.state import NO_REPLY, OpenReply, Phase, Shared
from rr_actors.errors import (
    CatalogWriteError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
)

if TYPE_CHECKING:
    from rr_actors._registrar.flights import Flights
    from rr_actors._registrar.holdings import Holdings
    from rr_actors._registrar.presence import Presence
    from rr_actors._registrar.provider import Provider
    from rr_actors._registrar.reconciling import Reconciling
    from rr_actors._registrar.releases import Releases
    from rr_actors._registrar.restoring import Restoring
    from rr_actors._registrar.servers import Servers
    from rr_actors._registrar.teardown import Teardown

__all__ = ["CatalogView", "Lifecycle"]

logger = logging.getLogger("rr_actors")


@dataclasses.dataclass(frozen=True)
class CatalogView:
    """An immutable copy of a registrar's catalog rows (for inspection and tests).

    Attributes:
        resources: the served resources, each with a copy of its consumers.
        clients: the client records (queries this registrar holds).
        servers: the names of its registered resource servers.
        in_doubt: the id and request display text of each resource found in doubt at
            its restore (`ResourceRegistrar.in_doubt`).
    """

    resources: tuple[Resource, ...]
    clients: tuple[ClientRecord, ...]
    servers: tuple[str, ...] = ()
    in_doubt: tuple[tuple[str, str | None], ...] = ()


class Hearing:
    """How this process's membership (`rr_actors._core.membership`) tells a registrar
    actor who is lost or reachable again: a `PeerLost` / `PeerReachable` to its mailbox
    (any thread; one for an actor that ended is dropped: it holds nothing any more)."""

    __slots__ = ("peer",)

    def __init__(self, peer: LocalPeer) -> None:
        self.peer = peer

    @property
    def name(self) -> str:
        """The registrar's name."""
        return self.peer.name

    def peer_lost(self, name: str) -> None:
        """Registrar `name` is gone for good (rule 19): `presence.py`."""
        with contextlib.suppress(RrError):
            self.peer.tell(PeerLost(name))

    def peer_stopped(self, name: str) -> None:
        """Registrar `name` was stopped for good (its supervisor says): `presence.py`."""
        with contextlib.suppress(RrError):
            self.peer.tell(PeerLost(name, stopped=True))

    def peer_reachable(self, name: str) -> None:
        """Registrar `name` answers again (a healed link, rule 20): `presence.py`."""
        with contextlib.suppress(RrError):
            self.peer.tell(PeerReachable(name))


class Lifecycle:
    """Starts, stops and buries one registrar actor; answers the handle's requests.

    Attributes:
        open_requests: handle requests not answered yet (a death fails them).
        died: set once a crash was fully handled (death watch included).
        ended: set once the actor's thread handed on its last message.
    """

    def __init__(
        self,
        shared: Shared,
        provider: Provider,
        teardown: Teardown,
        restoring: Restoring,
        flights: Flights,
        holdings: Holdings,
        releases: Releases,
        reconciling: Reconciling,
        presence: Presence,
        servers: Servers,
        actor: Actor,
        died: threading.Event,
        ended: OneShotFuture[None],
    ) -> None:
        self.registrar = shared
        self.servers = servers
        self.provider = provider
        self.teardown = teardown
        self.restoring = restoring
        self.flights = flights
        self.holdings = holdings
        self.releases = releases
        self.reconciling = reconciling
        self.presence = presence
        self.actor = actor  # (the actor machinery only: its mailbox, `end_now`)
        self.died = died
        self.ended = ended
        self.open_requests: set[OpenReply] = set()
        self.stop_waiters: list[Reply] | None = None  # while a stop is under way
        self.flush_timer: Cancellable | None = None
        self.hearer = Hearing(shared.peer)  # what this process's membership tells it

    # -- start ------------------------------------------------------------------------

    def on_start(self) -> None:
        chronicle.publish_restored(self.registrar)  # before anything is served
        # from now on it hears who is lost (`PeerLost`); who was lost before it started
        # (while it was down, or before its restore) it hears now: a mark is never missed
        gone = MEMBERSHIP.join(self.hearer)
        # every provider the restored catalog knows, also those settle_in_doubt forgets
        providers = {record.query.serving_rr for record in self.registrar.catalog.clients.values()}
        self.reconciling.expect_reconcile(providers)
        # what it released or gave up while a provider was down is in no row: with a
        # backup, it reconciles with every registrar of the system (rule 20)
        self.reconciling.everyone = self.registrar.saver.store is not None
        self.restoring.settle_in_doubt()
        self.restoring.unload_unheld()
        for name, stopped in sorted(gone.items()):  # as if it had heard each mark
            if stopped:  # (`presence.py`)
                self.presence.stopped(name)
            else:
                self.presence.lose(name)
        self.arm_flush_timer()
        if self.registrar.phase is Phase.SERVING:  # (else once setup is done: `on_ready`)
            self.reconcile()

    def reconcile(self) -> None:
        """It serves: reconcile what its restored catalog says with its peers' catalogs.

        As a provider it asks every consumer holding ids here for the ids it holds
        (`ReconcileAsk`), as a consumer it tells every provider it holds ids at which
        ids it holds (`Reconcile`): ids released while one side was down are released,
        and ids one side lost in its restart are reported to the consumer as `FATAL`.
        While the sweep of a restored catalog is under way, the provider's side waits
        for it (it names the consumers to ask: `restoring.py`).
        """
        self.restoring.ask_consumers()
        self.reconciling.reconcile_all()

    def on_reachable(self, _message: Reachable, reply: Reply) -> None:
        """A carrier serves it: the other processes can reach it (and answer it) now."""
        if self.registrar.phase is Phase.SERVING:  # (during setup, `on_ready` reconciles)
            self.reconcile()
        reply.set_result(None)

    def on_ready(self, _message: Ready, reply: Reply) -> None:
        """Setup is done: serve what waited for it (unknown servers now fail)."""
        self.registrar.phase = Phase.SERVING
        self.registrar.servers_settled = True
        self.provider.serve_held()
        self.reconcile()
        reply.set_result(None)

    # -- the save interval ------------------------------------------------------------

    def arm_flush_timer(self) -> None:
        ref = self.registrar.ref

        def tick() -> None:
            with contextlib.suppress(pykka.ActorDeadError):
                assert ref is not None
                ref.tell(Flush())

        self.flush_timer = self.registrar.saver.schedule(tick)

    def on_flush(self, _message: Flush, _reply: Reply) -> None:
        if self.registrar.stopping:
            return
        try:
            self.registrar.saver.flush()
        except CatalogWriteError as exc:  # the changes stay pending: the next flush tries
            logger.warning("registrar %s: the interval save failed: %s", self.registrar.name, exc)
        finally:
            self.arm_flush_timer()

    def on_save(self, _message: Save, reply: Reply) -> None:
        self.registrar.commit()
        self.registrar.saver.flush()
        reply.set_result(None)

    # -- requests from the handle -----------------------------------------------------

    def on_snapshot(self, message: Snapshot, reply: Reply) -> None:
        """Copy the catalog's rows (a restored row decodes its values here, once); with
        `check`, after checking the catalog's invariants (a failure is the caller's
        `AssertionError`, not this registrar's death)."""
        try:
            if message.check:
                self.registrar.catalog.check_invariants()
            view = CatalogView(
                resources=tuple(
                    dataclasses.replace(r, consumers=dict(r.consumers))
                    for r in self.registrar.catalog.read_all().values()
                ),
                clients=tuple(
                    dataclasses.replace(c) for c in self.registrar.catalog.clients.values()
                ),
                servers=tuple(self.registrar.servers),
            )
        except Exception as exc:  # noqa: BLE001 - an exception here would kill the registrar
            reply.set_error(exc)
            return
        reply.set_result(view)

    # -- stop -------------------------------------------------------------------------

    def on_yield_name(self, message: YieldName, _reply: Reply) -> None:
        """Another registrar of this name is kept (rule 22; the carrier no longer serves
        this one): unload every resource it serves, then stop as `stop()` does.

        It waits `call_timeout` seconds at most for what it serves to be gone (a load
        under way finishes, then is unloaded; an `unload` runs): then it stops anyway,
        and what is still under way is in doubt at its next start (rule 16)."""
        if self.registrar.phase not in (Phase.SETTING_UP, Phase.SERVING):
            return  # stopping or ended already
        logger.info("registrar %s yields its name: %s", self.registrar.name, message.reason)
        self.registrar.phase = Phase.STOPPING  # (new loads are refused from now on)
        until = time.monotonic() + self.registrar.config.call_timeout
        stopped = False

        def stop(*_: object) -> None:
            nonlocal stopped
            if not stopped:
                stopped = True
                timer.cancel()
                self.on_stop(Stop(FutureReply(), until), NO_REPLY)

        late = self.registrar.come_back(stop)
        timer = thread_timer(max(0.0, until - time.monotonic()), lambda: late.set_result(None))
        self.servers.give_up_all(stop)

    def on_stop(self, message: Stop, reply: Reply) -> None:
        """Unload what this registrar holds as a consumer (newest first), wait for the
        unloads under way here until `message.unloads_until` (`time.monotonic()`
        seconds; `None`: no wait), then stop (rule 12)."""
        if self.stop_waiters is not None:  # one is under way (a yield's, another caller's)
            self.stop_waiters.append(reply)
            return
        self.stop_waiters = []
        unloads_until = message.unloads_until
        self.registrar.phase = Phase.STOPPING
        self.presence.close()  # no more reconcile retries
        stopped = RegistrarStoppedError(
            f"registrar {self.registrar.name!r} stopped during the call"
        )
        releases = self.releases
        releases.withdraw_pending(stopped)
        releases.give_back_unsettled()
        tops = [
            r
            for r in reversed(self.registrar.catalog.clients.values())
            if r.parent is None and r.loaded
        ]

        def next_one() -> None:
            if tops:
                releases.release_client(tops.pop(0), next_one)
                return
            self.wait_for_unloads(unloads_until, finish)

        def finish() -> None:
            self.registrar.commit()
            chronicle.publish_stopped(self.registrar)
            if self.flush_timer is not None:
                self.flush_timer.cancel()
            unsaved: CatalogWriteError | None = None
            try:
                self.registrar.saver.close(erase=self.registrar.config.erase_on_destruct)
            except CatalogWriteError as exc:  # stopped anyway; its caller hears what was lost
                name = self.registrar.name
                logger.error("registrar %s stopped without its last changes: %s", name, exc)  # noqa: TRY400
                unsaved = exc
            MEMBERSHIP.leave(self.hearer)
            DIRECTORY.unregister(self.registrar.peer, "stopped")
            self.stop_children()
            for waiting in [reply, *(self.stop_waiters or ())]:
                if unsaved is None:
                    waiting.set_result(None)
                else:
                    waiting.set_error(unsaved)
            self.fail_waiting(
                RegistrarStoppedError(f"registrar {self.registrar.name!r} was stopped")
            )
            self.registrar.probe("stop_drained", None)
            self.registrar.phase = Phase.ENDED
            self.actor.end_now()  # at once: what arrives from now on goes to `on_late`

        next_one()

    def wait_for_unloads(self, until: float | None, then: Callable[[], None]) -> None:
        """Run `then()` once no unload is under way here, or at `until` (monotonic
        seconds) at the latest: each unload still under way then is cut short
        (`UnloadCutShort`; the resource stays unloading in the backup, in doubt at the
        next start). Its callback runs on, on its worker thread; its answer goes nowhere."""
        done = False
        timer: Cancellable | None = None

        def go(*, cut_short: bool) -> None:
            nonlocal done
            if done:
                return
            done = True
            if timer is not None:
                timer.cancel()
            for resource in self.teardown.under_way.values() if cut_short else ():
                logger.warning(
                    "registrar %s: stopped while the unload of %s (%s) was under way; "
                    "it is in doubt at the next start",
                    self.registrar.name,
                    resource.id,
                    resource.server,
                )
                if self.registrar.events.active:
                    self.registrar.events.publish(
                        events.UnloadCutShort(self.registrar.name, resource.server, resource.id)
                    )
            then()

        if until is not None and self.teardown.under_way:
            late = self.registrar.come_back(lambda _value, _error: go(cut_short=True))
            timer = thread_timer(max(0.0, until - time.monotonic()), lambda: late.set_result(None))
        self.teardown.when_idle(lambda: go(cut_short=False))
        if not done and until is None:
            go(cut_short=True)

    def stop_children(self) -> None:
        for server in self.registrar.servers.values():
            server.ref.stop(block=True, timeout=5.0)
        self.holdings.stop_clients()

    # -- death --------------------------------------------------------------------------

    def on_crash(self, _message: Crash, _reply: Reply) -> None:
        raise RuntimeError(
            f"registrar {self.registrar.name!r} was made to crash (rr_actors.testing)"
        )

    def die(self) -> None:
        """A crash: fail every waiting caller, release this consumer's ids elsewhere."""
        self.registrar.phase = Phase.ENDED
        self.presence.close()
        MEMBERSHIP.leave(self.hearer)
        DIRECTORY.unregister(self.registrar.peer, "died")
        self.fail_waiting(RegistrarUnavailableError(f"registrar {self.registrar.name!r} died"))
        self.stop_children()
        if self.flush_timer is not None:
            self.flush_timer.cancel()
        self.registrar.saver.close(erase=False, flush=False)  # a crash writes nothing more
        if not DIRECTORY.restart_expected(self.registrar.name):  # gone for good (rule 19):
            gone_for_good(self.registrar.name, also=DIRECTORY.names())  # other processes too
        self.died.set()

    # -- whoever still waits ----------------------------------------------------------

    def fail_waiting(self, error: RrError) -> None:
        """Answer everyone still waiting on this actor with `error` (it stops or died)."""
        self.provider.fail_waiting(error)
        self.flights.fail_waiting(error)
        for request in list(self.open_requests):
            request.set_error(error)
        inbox = self.actor.actor_inbox
        while not inbox.empty():
            self.refuse(inbox.get(), error)
        outcomes = self.flights.due.outcomes
        while not outcomes.empty():
            self.refuse_message(outcomes.get(), error)

    def refuse(self, envelope: Any, error: Exception) -> None:
        """Answer a message this actor will not handle (it stops or died); any thread."""
        refuse(envelope)  # a pykka ask, e.g. the handle's `ref.stop()`: it must hear
        self.refuse_message(envelope.message, error)

    def refuse_message(self, message: Any, error: Exception) -> None:
        """Answer what `message` obliges this actor to, as it will not handle it; any thread."""
        pending = getattr(message, "reply", None)
        if pending is not None:
            pending.set_error(error)
        if isinstance(message, ClientLoaded):  # its id would leak at the provider
            query = message.record.query
            give_back(query.serving_rr, query.id, self.registrar.name)
            message.attempt.fail(error)
