"""A registrar actor's life: start (restore, settle what a crash cut short), serve, hear of
its peers (lost for good, reachable again), stop or die, and say so.

```
 SETTING_UP ──ready──► SERVING ──stop()──► STOPPING ──► ENDED
      └──────────────────┴── crash (a bug, testing.crash) ─────► ENDED (death)

 start: CatalogRestored; join the membership; settle_in_doubt (rule 16) ─► InDoubt;
   the sweep of the restored catalog, one slice per turn, after it serves
 serve (Ready, Reachable): ReconcileAsk to its consumers, Reconcile with its providers
 peers (Presence): PeerLost(X) ─► lose(X): what X held here released, what is held
   at X FATAL (rule 19); PeerReachable(X), ReconcileAsk ─► Reconcile with X, retried
   until answered (rule 20)
 stop (Stop; YieldName, rule 22): calls withdrawn, what it holds released newest
   first, the unloads under way until `unloads_until` ─► the backup closed ─► ENDED
 death (on_failure): every waiter failed at once, nothing more written
 the death watch (the supervisor and process layers): gone_for_good, back, tell_gone,
   lost_everything
 the outside's views: Served (a carrier), Hearing (this process's membership)
```

Why a restarted provider is not lost, and who knows who is gone: docs/explanation/inside.md,
"A registrar's peers". The phase is the record's (`state.py`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import logging
from collections.abc import Callable, Container, Iterable
from typing import Any, Protocol

import pykka

from rr_actors import events
from rr_actors._catalog import Catalog, ClientRecord, Resource, ResourceState
from rr_actors._core import runtime
from rr_actors._core.actor import Actor, OneShotFuture, refuse
from rr_actors._core.directory import DIRECTORY, LocalPeer, Reply
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._core.replies import FutureReply, Join
from rr_actors._registrar.calls import ClientLoaded
from rr_actors._registrar.messages import (
    ConsumerDown,
    Crash,
    Flush,
    KeepName,
    LostEverything,
    PeerLost,
    PeerReachable,
    PeersStopped,
    Reachable,
    Ready,
    ReconcileAsk,
    ReconcileRetry,
    Save,
    SettleInDoubt,
    Snapshot,
    Stop,
    YieldName,
    give_back,
)
from rr_actors._registrar.provider import ProviderRecord
from rr_actors._registrar.state import NO_REPLY, OpenReply, Phase, Server, Shared
from rr_actors.config import RegistrarConfig, Steps
from rr_actors.errors import (
    CatalogWriteError,
    ConfigError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
    UnknownQueryError,
)
from rr_actors.events.kinds import LISTED_ROWS, Rows

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


class RegistrarRecord(ProviderRecord):
    """The registrar's whole record (`Shared`, then each side's parts: `ConsumerRecord`,
    `StatusRecord`, `ProviderRecord`), as its lifecycle and the actor see it."""

    # the handle's requests not answered yet (`OpenReply`: any thread); a dict: a death
    # fails them oldest first (a set's address order no replay repeats)
    open_requests: dict[OpenReply, None]
    lifecycle: Lifecycle
    restoring: Restoring
    presence: Presence
    actor: Actor  # (the actor machinery only: its mailbox, `end_now`, its dispatch)
    died: runtime.Event  # set once a crash was fully handled (death watch included)
    ended: OneShotFuture[None]  # set once the actor's thread handed on its last message


class Lifecycle:
    def __init__(self, registrar: RegistrarRecord) -> None:
        self.registrar = registrar
        self.stop_waiters: list[Reply] | None = None  # while a stop is under way
        self.flush_timer: runtime.Cancellable | None = None
        # while it yields its name (rule 22): where `KeepName`'s answer goes, else `None`
        self.keepers: list[Reply] | None = None
        self.hearer = Hearing(registrar.peer)  # what this process's membership tells it

    # -- start ------------------------------------------------------------------------

    def on_start(self) -> None:
        publish_restored(self.registrar)  # before anything is served
        MEMBERSHIP.monitor_all(self.registrar.name, on=True)  # (restarts: all till `sweep`)
        rows = self.registrar.catalog.providers() | self.registrar.catalog.consumer_origins()
        gone = MEMBERSHIP.join(self.hearer, rows)  # (a mark is never missed)
        # every provider the restored catalog knows, also those settle_in_doubt forgets
        # what it released while a provider was down is in no row: reconcile with all (rule 20;
        # announced by its supervisor: each holding ids of it asks it, `on_reconcile_ask`)
        registrar = self.registrar
        everyone = not registrar.announced and registrar.saver.store is not None
        registrar.reconciling.expect_reconcile(registrar.catalog.providers(), everyone=everyone)
        self.registrar.restoring.settle_in_doubt()
        self.registrar.restoring.unload_unheld()
        for name, stopped in sorted(gone.items()):  # as if it had heard each mark
            if stopped:  # (`Presence`)
                self.registrar.presence.stopped(name)
            else:
                self.registrar.presence.lose(name)
        self.arm_flush_timer()
        if self.registrar.phase is Phase.SERVING:  # (else once setup is done: `on_ready`)
            self.reconcile()

    def reconcile(self) -> None:
        """It serves: as a provider ask its consumers for their ids (`ReconcileAsk`, after the
        sweep, which names them), as a consumer tell its providers which it holds (`Reconcile`)."""
        self.registrar.restoring.ask_consumers()
        for serving_rr, ask in sorted(self.registrar.reconciling.reconcile_all().items()):
            self.registrar.presence.begin(serving_rr, ask=ask)  # (setup's)

    def on_reachable(self, _message: Reachable, reply: Reply) -> None:
        if self.registrar.phase is Phase.SERVING:  # (during setup, `on_ready` reconciles)
            self.reconcile()
        reply.set_result(None)

    def on_ready(self, _message: Ready, reply: Reply) -> None:
        """Setup is done: serve what waited for it (unknown servers now fail)."""
        self.registrar.phase = Phase.SERVING
        self.registrar.servers_settled = True
        self.registrar.provider.serve_held()
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
        """Copy the catalog's rows; with `check`, after checking its invariants (a failure is
        the caller's `AssertionError`, not this registrar's death)."""
        try:
            if message.check:
                self.registrar.catalog.check_invariants()
            self.registrar.texts.fill()
            view = CatalogView(
                resources=tuple(
                    dataclasses.replace(r, consumers=dict(r.consumers))
                    for r in self.registrar.catalog.read_all().values()
                ),
                clients=tuple(map(dataclasses.replace, self.registrar.catalog.client_records())),
                servers=tuple(self.registrar.servers),
            )
        except Exception as exc:  # noqa: BLE001 - an exception here would kill the registrar
            reply.set_error(exc)
            return
        reply.set_result(view)

    # -- stop -------------------------------------------------------------------------

    def on_yield_name(self, message: YieldName, _reply: Reply) -> None:
        """Another registrar of this name is kept (rule 22): unload every resource it serves
        (for `call_timeout` at most), then stop as `stop()` does, unless `on_keep_name` comes."""
        phase = self.registrar.phase
        if phase not in (Phase.SETTING_UP, Phase.SERVING):
            return  # stopping or ended already
        logger.info("registrar %s yields its name: %s", self.registrar.name, message.reason)
        self.registrar.phase = Phase.STOPPING  # (new loads are refused from now on)
        until = runtime.monotonic() + self.registrar.config.call_timeout
        stopped = False
        self.keepers = []
        self.registrar.yielding = True
        reopen = [server for server in self.registrar.servers.values() if not server.closing]

        def stop(*_: object) -> None:
            nonlocal stopped
            if not stopped:
                stopped = True
                timer.cancel()
                keep, self.keepers = self.keepers, None
                self.registrar.yielding = False
                if keep and self.stop_waiters is None:  # (no stop() came meanwhile)
                    self.serve_again(phase, reopen, keep)
                    return
                for one in keep or ():
                    one.set_result(False)
                self.on_stop(Stop(FutureReply(), until), NO_REPLY)

        late = self.registrar.come_back(stop)
        timer = runtime.thread_timer(
            max(0.0, until - runtime.monotonic()), lambda: late.set_result(None)
        )
        self.registrar.registry.give_up_all(stop)

    def on_keep_name(self, message: KeepName, _reply: Reply) -> None:
        """The one kept in this one's place went for good while this one yields (rule 22): serve
        again once what it unloads is gone (`reply`: `True`); `False` if it began to stop."""
        if self.keepers is None or self.stop_waiters is not None:
            message.reply.set_result(False)
            return
        logger.warning(
            "registrar %s: the registrar kept in its place went for good while it yielded "
            "its name: it serves it again once what it unloads is gone (rule 22)",
            self.registrar.name,
        )
        self.keepers.append(message.reply)

    def serve_again(self, phase: Phase, reopen: list[Server], keep: list[Reply]) -> None:
        """A yield given up: the servers open before it take loads again, back in `phase`
        (its consumers reconcile with it, rule 20)."""
        for server in reopen:
            server.closing = False
        self.registrar.phase = phase
        for one in keep:
            one.set_result(True)

    def on_stop(self, message: Stop, reply: Reply) -> None:
        """Unload what this registrar holds as a consumer (newest first), wait for the unloads
        under way here until `message.unloads_until` (monotonic; `None`: no wait), then stop."""
        if self.stop_waiters is not None:  # one is under way (a yield's, another caller's)
            self.stop_waiters.append(reply)
            return
        self.stop_waiters = []
        unloads_until = message.unloads_until
        self.registrar.phase = Phase.STOPPING
        self.registrar.presence.close()  # no more reconcile retries
        stopped = RegistrarStoppedError(
            f"registrar {self.registrar.name!r} stopped during the call"
        )
        releases = self.registrar.releases
        # the ids given back are released at their providers before the stop goes on
        given_back = Join(lambda: self.wait_for_unloads(unloads_until, finish))
        releases.withdraw_pending(stopped, given_back)
        releases.give_back_unsettled(given_back)
        tops = [
            r
            for r in reversed(list(self.registrar.catalog.client_records()))
            if r.parent is None and r.loaded
        ]

        def next_one() -> None:
            if tops:
                releases.release_client(tops.pop(0), next_one)
                return
            given_back.seal()

        def finish() -> None:
            self.registrar.commit()
            publish_stopped(self.registrar)
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
            name = self.registrar.name
            self.fail_waiting(RegistrarStoppedError(f"registrar {name!r} was stopped", name))
            self.registrar.probe("stop_drained", None)
            self.registrar.phase = Phase.ENDED
            self.registrar.actor.end_now()  # at once: what arrives from now on goes to `on_late`

        next_one()

    def wait_for_unloads(self, until: float | None, then: Callable[[], None]) -> None:
        """Run `then()` once no unload is under way here, or at `until` (monotonic) at the latest:
        each still under way is cut short (`UnloadCutShort`, in doubt at the next start)."""
        done = False
        timer: runtime.Cancellable | None = None

        def go(*, cut_short: bool) -> None:
            nonlocal done
            if done:
                return
            done = True
            if timer is not None:
                timer.cancel()
            for resource in self.registrar.teardown.busy() if cut_short else ():
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

        if until is not None and self.registrar.teardown.busy():
            late = self.registrar.come_back(lambda _value, _error: go(cut_short=True))
            timer = runtime.thread_timer(
                max(0.0, until - runtime.monotonic()), lambda: late.set_result(None)
            )
        self.registrar.teardown.when_idle(lambda: go(cut_short=False))
        if not done and until is None:
            go(cut_short=True)

    def stop_children(self) -> None:
        for server in self.registrar.servers.values():
            server.ref.stop(block=True, timeout=5.0)
        self.registrar.clients.stop_all()

    # -- death --------------------------------------------------------------------------

    def on_crash(self, _message: Crash, _reply: Reply) -> None:
        raise RuntimeError(
            f"registrar {self.registrar.name!r} was made to crash (rr_actors.testing)"
        )

    def die(self) -> None:
        self.registrar.phase = Phase.ENDED
        self.registrar.presence.close()
        MEMBERSHIP.leave(self.hearer)
        DIRECTORY.unregister(self.registrar.peer, "died")
        died = RegistrarUnavailableError(f"registrar {self.registrar.name!r} died")
        self.registrar.abort_turn(died)  # (staged, never written: never answered as done)
        self.fail_waiting(died)
        self.stop_children()
        if self.flush_timer is not None:
            self.flush_timer.cancel()
        self.registrar.saver.close(erase=False, flush=False)  # a crash writes nothing more
        if not DIRECTORY.restart_expected(self.registrar.name):  # gone for good (rule 19):
            gone_for_good(self.registrar.name, also=DIRECTORY.names())  # other processes too
        self.registrar.died.set()

    # -- whoever still waits ----------------------------------------------------------

    def fail_waiting(self, error: RrError) -> None:
        """Answer everyone still waiting on this actor with `error` (handle requests first)."""
        self.registrar.provider.fail_waiting(error)
        self.registrar.flights.fail_waiting(error)
        for request in list(self.registrar.open_requests):
            request.set_error(error)
        inbox = self.registrar.actor.actor_inbox
        while not inbox.empty():
            self.refuse(inbox.get(), error)
        outcomes = self.registrar.due.outcomes
        while not outcomes.empty():
            self.refuse_message(outcomes.get(), error)

    def refuse(self, envelope: Any, error: Exception) -> None:
        """Answer a message this actor will not handle (it stops or died); any thread."""
        refuse(envelope)  # a pykka ask, e.g. the handle's `ref.stop()`: it must hear
        self.refuse_message(envelope.message, error)

    def refuse_message(self, message: Any, error: Exception) -> None:
        pending = getattr(message, "reply", None)
        if pending is not None:
            pending.set_error(error)
        if isinstance(message, ClientLoaded):  # its id would leak at the provider
            query = message.record.query
            give_back(query.serving_rr, query.id, self.registrar.name)
            message.attempt.fail(error)


# -- restoring -------------------------------------------------------------------------


def cut_short(catalog: Catalog, steps: Steps) -> list[Resource]:
    """The restored resources a crash cut short: neither loaded nor unloaded (rule 16)."""
    step = steps.in_doubt  # (a copy of this step passed in: `RegistrarConfig.steps`)
    if step is not None:
        return [r for r in catalog.resources.values() if step(r.state.value)]
    return [r for r in catalog.resources.values() if r.state is not ResourceState.LOADED]


class Restoring:
    def __init__(self, registrar: ProviderRecord, *, hold_in_doubt: bool = False) -> None:
        self.registrar = registrar
        self.hold_in_doubt = hold_in_doubt  # their settling waits for the manager (`setup`)
        self.in_doubt_ids: frozenset[str] = frozenset()  # found in doubt at the restore
        self.sweeping = False  # slices of the restored catalog are still to be swept
        self.swept_origins: set[str] = set()  # registrars holding ids in what was swept
        self.reconcile_owed = False  # `ask_consumers` came during the sweep

    def settle_in_doubt(self) -> None:
        """Drop restored resources whose load or unload a crash cut short (rule 16), releasing
        their dependencies and giving up calls in flight; with `hold_in_doubt` their rows stay in
        the backup until the manager settles them."""
        catalog = self.registrar.catalog
        doubtful = cut_short(catalog, self.registrar.config.steps)
        self.in_doubt_ids = frozenset(r.id for r in doubtful)
        if self.hold_in_doubt:
            self.registrar.held_in_doubt.update(self.in_doubt_ids)
        for resource in doubtful:
            if self.registrar.events.active:
                self.registrar.events.publish(
                    events.InDoubt(
                        self.registrar.name,
                        resource.id,
                        resource.server,
                        "load" if resource.state is ResourceState.LOADING else "unload",
                    )
                )
            catalog.begin_unload(resource.id)
            self.registrar.releases.release_dependencies(
                resource.id, functools.partial(self.registrar.teardown.remove_resource, resource)
            )
        for record in list(catalog.client_records()):
            orphan = record.parent is not None and record.parent not in catalog.resources
            if orphan or (record.parent is None and not record.loaded):
                query = record.query
                give_back(query.serving_rr, query.id, self.registrar.name)
                self.registrar.holdings.forget(query.id, commit=False, reason="in doubt")
        self.registrar.commit()

    def unload_unheld(self) -> None:
        """Unload restored resources that no consumer holds (rule 7): a crash came between their
        last release and their unload; they run once setup registered their server."""
        for resource in self.registrar.catalog.unheld():
            self.registrar.teardown.unload_resource(resource, None)
        self.sweep(0)

    def sweep(self, after: int) -> None:
        """Sweep the restored resources still in the backup, one slice per turn (calls are
        served between slices): unload those nobody holds, note who holds ids (`ask_consumers`)."""
        if self.registrar.phase in (Phase.STOPPING, Phase.ENDED):
            return
        try:
            unheld, origins, next_slice = self.registrar.catalog.sweep(after)
            self.swept_origins |= origins
            MEMBERSHIP.monitor(self.registrar.name, *origins)
            for resource in unheld:
                self.registrar.teardown.unload_resource(resource, None)
            if next_slice is not None:
                self.sweeping = True
                self.registrar.come_back(lambda _v, _e: self.sweep(next_slice)).set_result(None)
                return
            MEMBERSHIP.monitor_all(self.registrar.name, on=False)  # (each holder is monitored)
        except RrError as exc:  # a damaged row: a lookup that needs it fails then
            logger.error(  # noqa: TRY400 - the cause says it all
                "registrar %s: the sweep of its restored catalog stopped: %s",
                self.registrar.name,
                exc,
            )
        self.sweeping = False
        if self.reconcile_owed:
            self.reconcile_owed = False
            self.registrar.unloading.ask_to_reconcile(self.swept_origins)

    def ask_consumers(self) -> None:
        """It serves: ask every consumer holding ids here to reconcile (once the sweep is done)."""
        if self.sweeping:
            self.reconcile_owed = True
        else:
            self.registrar.unloading.ask_to_reconcile(self.swept_origins)

    def on_settle_in_doubt(self, message: SettleInDoubt, reply: Reply) -> None:
        """The manager handled in-doubt entry `query_id` (`None`: every one): its row leaves the
        backup. A failed write is the caller's `CatalogWriteError` (settled in memory still)."""
        query_id = message.query_id
        if query_id is None:
            rids = set(self.in_doubt_ids)
        elif query_id in self.in_doubt_ids:
            rids = {query_id}
        else:
            reply.set_error(
                UnknownQueryError(
                    f"{query_id!r} is not in doubt at registrar {self.registrar.name!r}"
                )
            )
            return
        failed = self.registrar.settle_held(rids)  # (a failed write stays pending: the
        if failed is not None:  # next commit writes it; until then a restart offers it again)
            reply.set_error(failed)
            return
        reply.set_result(None)


# -- presence --------------------------------------------------------------------------


RETRY_FIRST = 0.05
"""Seconds before the first retry of a `Reconcile` that failed after a healed link."""

RETRY_MAX = 2.0
"""The longest wait between two retries (the backoff doubles up to it)."""


def retry_delay(attempt: int) -> float:
    """Seconds to wait before retry `attempt` (1, 2, ...): doubling, at most `RETRY_MAX`."""
    return float(min(RETRY_MAX, RETRY_FIRST * 2 ** max(0, min(attempt - 1, 16))))


class Presence:
    def __init__(
        self, registrar: ProviderRecord, timer: runtime.StartTimer = runtime.thread_timer
    ) -> None:
        self.registrar = registrar
        self.timer = timer  # `timer(delay, fn)` for the retries (injectable for tests)
        # provider -> (its reconcile round, the attempt waited for), until answered
        self.rounds: dict[str, tuple[int, int]] = {}
        self.lives: dict[str, str] = {}  # provider -> the life that asked for its round
        self.asks: dict[str, tuple[int, str]] = {}  # provider -> the ask it answers (`attempt`)
        self.timers: dict[str, runtime.Cancellable] = {}
        self.round_count = 0
        # names lost while a namesake served (rule 22): lost if the reconcile with it fails
        self.served_on: set[str] = set()
        # consumers lost while a namesake served: when their `Reconcile` is due
        self.asked_timers: dict[str, runtime.Cancellable] = {}

    # -- lost for good (rule 19) --------------------------------------------------------

    def on_peer_lost(self, message: PeerLost, _reply: Reply) -> None:
        self.lose(message.name)

    def on_peers_stopped(self, message: PeersStopped, _reply: Reply) -> None:
        for name in message.names:
            self.stopped(name)

    def on_consumer_down(self, message: ConsumerDown, _reply: Reply) -> None:
        """Another process's death watch mark: into this process's membership, which tells every
        registrar here (`PeerLost`)."""
        by = f"a death-watch mark to {self.registrar.name}"
        if message.stopped:
            MEMBERSHIP.stopped(message.origin_rr, by=by)
        else:
            MEMBERSHIP.lost(message.origin_rr, by=by)

    def stopped(self, name: str) -> None:
        """Registrar `name` was stopped for good: it holds nothing (rule 12), so every id of it
        still here is released; what this one holds there is left as a stop leaves it."""
        if name == self.registrar.name:
            return
        self.registrar.unloading.release_stopped(name)

    def lose(self, name: str, *, defer: bool = True) -> None:
        """Registrar `name` is gone and nobody will restart it: release what it held here, report
        what this one held there `FATAL` and forget it (rule 19).

        Unless another registrar of the name serves now (rule 22 kept it): then reconcile with
        it first (`lost_after_all` if that fails), and as a provider ask it for a `Reconcile`,
        releasing its ids only if none comes within `call_timeout`.
        """
        if name == self.registrar.name:
            return
        registrar = self.registrar
        serving = (
            registrar.phase is Phase.SERVING
            # (business first: the directory's names are every registrar of the system,
            # read at each loss by each registrar here, N x N in a tree's stop)
            and (registrar.unloading.holds_of(name) or registrar.reconciling.holds_at(name))
            and name in DIRECTORY.names()
        )
        if not (defer and serving and self.ask_consumer(name)):
            self.stop_asking(name)
            self.registrar.unloading.release_all_of(name)
        if defer and serving and self.registrar.reconciling.holds_at(name):
            logger.info(
                "registrar %s: %s is lost for good, and a registrar named so serves: "
                "it reconciles with that one first (rule 22)",
                self.registrar.name,
                name,
            )
            self.served_on.add(name)
            self.begin(name)
            return
        self.served_on.discard(name)
        self.stop_retrying(name)
        self.registrar.reconciling.lose_provider(name)

    # -- reachable again (rule 20) ------------------------------------------------------

    def on_peer_reachable(self, message: PeerReachable, _reply: Reply) -> None:
        name = message.name
        if name == self.registrar.name or self.registrar.phase is not Phase.SERVING:
            return  # (during setup `on_ready` reconciles with everyone; stopping: nothing)
        self.served_on.discard(name)  # (a healed link: the reconcile decides)
        if self.registrar.reconciling.holds_at(name):
            self.begin(name)
        if self.registrar.catalog.consumers_from(name):  # (with the round of an ask standing,
            self.registrar.unloading.ask_holder(name)  # `ask_consumer`: its answer clears it)

    def on_reconcile_ask(self, message: ReconcileAsk, reply: Reply) -> None:
        """Provider `serving_rr` asks for a `Reconcile` (rule 20): sent, and retried until it is
        answered (one sent once could be lost as its connection fails while it comes back)."""
        reply.set_result(None)  # (heard: one that stopped first answers that, `ask_to_reconcile`)
        name = message.serving_rr  # (re)started: it may have forgotten ids it holds here
        if not message.holds_yours and name != self.registrar.name and self.holds_of(name):
            self.registrar.unloading.ask_holder(name)  # (its `Reconcile` releases them, rule 20)
        if self.registrar.reconciling.asked(message):
            self.begin(message.serving_rr, message.life, (message.round, message.life))

    def holds_of(self, name: str) -> bool:
        """Whether this registrar holds ids of consumer `name`, or has its loads under way."""
        return self.registrar.unloading.holds_of(name) or bool(
            self.registrar.provider.under_way_of(name)
        )

    def ask_consumer(self, name: str) -> bool:
        """Ask consumer `name` for a `Reconcile`, with its `call_timeout` armed; whether it was
        asked (nothing of it held here, or it cannot be told: not)."""
        if not self.registrar.unloading.holds_of(name):
            return False
        # (a call given up fails: nothing held anywhere)
        self.registrar.unloading.give_up_loads_of(name)
        self.round_count += 1
        round_, ref = self.round_count, self.registrar.ref
        try:
            DIRECTORY.lookup(name).tell(
                ReconcileAsk(self.registrar.name, life=self.registrar.life, round=round_)
            )
        except RrError as exc:
            logger.debug("registrar %s: %s cannot be asked: %s", self.registrar.name, name, exc)
            return False
        self.stop_asking(name)
        held = frozenset(self.registrar.catalog.consumers_from(name))
        self.registrar.unloading.expect(name, round_, held)

        def due() -> None:
            with contextlib.suppress(pykka.ActorDeadError):
                assert ref is not None
                ref.tell(ReconcileRetry(name, round_, 0, asked=True))

        self.asked_timers[name] = self.timer(self.registrar.config.call_timeout, due)
        # then a reconcile of this one's ids there: one that cannot answer fails it at once
        self.registrar.reconciling.reconcile(
            name, then=functools.partial(self.probed, name, round_)
        )
        return True

    def probed(self, name: str, round_: int, error: BaseException | None) -> None:
        if error is not None:
            self.unanswered(name, round_)

    def unanswered(self, name: str, round_: int) -> None:
        """The `Reconcile` asked of consumer `name` by round `round_` did not come in time: it is
        lost as a consumer (every id it held here when asked released)."""
        asked = self.registrar.unloading.expected(name)
        if asked is None or asked[0] != round_:
            return  # it came (or a newer ask waits)
        self.stop_asking(name)
        logger.info(
            "registrar %s: %s, heard lost, did not reconcile: releasing the ids it held when asked",
            self.registrar.name,
            name,
        )
        self.registrar.unloading.release_all_of(name, only=asked[1])  # (not those loaded since)

    def stop_asking(self, name: str) -> None:
        self.registrar.unloading.not_expected(name)
        timer = self.asked_timers.pop(name, None)
        if timer is not None:
            timer.cancel()

    def on_reconcile_retry(self, message: ReconcileRetry, _reply: Reply) -> None:
        if message.asked:
            self.unanswered(message.name, message.round)
            return
        if self.rounds.get(message.name) != (message.round, message.attempt - 1):
            return  # answered meanwhile, lost, or a newer round started
        if self.registrar.phase is not Phase.SERVING:
            self.stop_retrying(message.name)
            return
        if self.lost_after_all(message.name):
            return
        self.attempt(message.name, message.round, message.attempt, self.lives.get(message.name, ""))

    def begin(self, name: str, life: str = "", ask: tuple[int, str] = (0, "")) -> None:
        """Start a new round of `Reconcile` with provider `name` (`attempt` 0)."""
        self.round_count += 1
        self.attempt(name, self.round_count, 0, life, ask)

    def attempt(
        self, name: str, round_: int, attempt: int, life: str = "", ask: tuple[int, str] = (0, "")
    ) -> None:
        """Send `Reconcile` attempt `attempt` of round `round_` to provider `name` (`life`: the
        life that asked, "": not known; `ask`: its `ReconcileAsk.round` and `life`), retried
        unless answered within `call_timeout`."""
        ask = ask if ask[0] else self.asks.get(name, ask)  # (one standing: a newer round answers)
        self.stop_retrying(name)
        self.rounds[name] = (round_, attempt)
        self.lives[name], self.asks[name] = life, ask
        self.arm(name, round_, attempt + 1, self.registrar.config.call_timeout)
        self.registrar.reconciling.reconcile(
            name, then=lambda error: self.answered(name, round_, attempt, error), life=life, ask=ask
        )

    def answered(self, name: str, round_: int, attempt: int, error: BaseException | None) -> None:
        if self.rounds.get(name) != (round_, attempt):
            return  # a late answer of an attempt given up (the newer one decides)
        if error is not None and self.lost_after_all(name):
            return
        if error is None or isinstance(error, RegistrarStoppedError):
            self.stop_retrying(name)  # reconciled; or stopped: its restart reconciles
            self.served_on.discard(name)
            return
        logger.debug(
            "registrar %s: reconcile %d with %s failed (%s); retrying",
            self.registrar.name,
            attempt,
            name,
            error,
        )
        self.arm(name, round_, attempt + 1, retry_delay(attempt + 1))

    def lost_after_all(self, name: str) -> bool:
        """Whether `name` was lost while a namesake served and the reconcile with it failed."""
        if name not in self.served_on:
            return False
        self.lose(name, defer=False)
        return True

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
        self.lives.pop(name, None)
        self.asks.pop(name, None)
        timer = self.timers.pop(name, None)
        if timer is not None:
            timer.cancel()

    def close(self) -> None:
        for name in list(self.rounds):
            self.stop_retrying(name)
        for name in list(self.asked_timers):
            self.stop_asking(name)
        self.registrar.reconciling.close()


# -- the outside's views of it: a carrier's, the membership's -------------------------


class Hearing:
    """How this process's membership tells a registrar actor who is lost or reachable again
    (any thread; to an actor that ended, dropped)."""

    __slots__ = ("peer",)

    def __init__(self, peer: LocalPeer) -> None:
        self.peer = peer

    @property
    def name(self) -> str:
        return self.peer.name

    def peer_lost(self, name: str) -> None:
        with contextlib.suppress(RrError):
            self.peer.tell(PeerLost(name))

    def peers_stopped(self, names: tuple[str, ...]) -> None:
        with contextlib.suppress(RrError):
            self.peer.tell(PeersStopped(names))

    def peer_reachable(self, name: str) -> None:
        with contextlib.suppress(RrError):
            self.peer.tell(PeerReachable(name))

    def peer_started(self, name: str) -> None:
        with contextlib.suppress(RrError):
            self.peer.tell(ReconcileAsk(name, holds_yours=False))


class Network(Protocol):
    """What `ResourceRegistrar.start(network=)` needs of a carrier (every `Transport` is one):
    `serve` returns once the other processes can reach the registrar, which is served until
    it stops or dies."""

    def serve(self, endpoint: Served) -> None:
        """Make the registrar reachable from the other processes (and hosts) of the system.

        Raises:
            DuplicateNameError: another process of the system serves that name.
            ConfigError: the carrier cannot serve it.
            RegistrarStoppedError: this process left the system.
        """
        ...


class Servable(Protocol):
    """What a carrier's `Served` uses of a started registrar (`handle.ResourceRegistrar`)."""

    @property
    def name(self) -> str: ...

    @property
    def config(self) -> RegistrarConfig: ...

    def is_alive(self) -> bool: ...

    def stop(self, *, timeout: float | None = None) -> None: ...

    def tell(self, message: object) -> bool: ...

    def wait_ended(self, timeout: float | None = None) -> bool: ...


def check_network(network: object) -> None:
    """Raise `ConfigError` naming `network` unless it is `None` or has a `serve` method."""
    if network is not None and not callable(getattr(network, "serve", None)):
        raise ConfigError(
            f"network must be a carrier's Transport (an AF_UNIX System, a ZenohNetwork) "
            f"or None, got {network!r}"
        )


def serve_on(network: Network, registrar: Servable) -> None:
    """Serve `registrar` on `network`; if that fails, stop it and raise what failed."""
    try:
        network.serve(Served(registrar))
    except BaseException:
        registrar.stop()
        raise


class Served:
    """A registrar of this process as a carrier serves it (`_transport.messenger.Endpoint`)."""

    __slots__ = ("max_message_bytes", "name", "registrar")

    def __init__(self, registrar: Servable) -> None:
        self.registrar = registrar
        # Read once (a registrar's config is frozen): the carrier reads both for every
        # message it delivers (it bounds its connections by `max_message_bytes`), so no
        # frame of this module runs on a call's path.
        self.name: str = registrar.name
        self.max_message_bytes: int = registrar.config.max_message_bytes

    def run(self, fn: Callable[[Any], Any]) -> Any:
        return fn(self.registrar)

    def wait_ended(self, timeout: float | None = None) -> bool:
        return self.registrar.wait_ended(timeout)

    def stopped_cleanly(self) -> bool:
        """Whether it ended because its owner stopped it (not a crash, not still running)."""
        if self.registrar.is_alive():
            return False
        return isinstance(DIRECTORY.gone_error(self.registrar.name), RegistrarStoppedError)

    def listening(self) -> None:
        """The other processes can reach it now: it reconciles with its peers again."""
        self.registrar.tell(Reachable(FutureReply()))  # (nobody waits: `serve` must not)

    def peer_lost(self, name: str) -> None:
        self.registrar.tell(PeerLost(name))

    def peer_reachable(self, name: str) -> None:
        self.registrar.tell(PeerReachable(name))

    def yield_name(self, reason: str) -> None:
        """Another process's registrar of this name is kept (rule 22): this one yields."""
        self.registrar.tell(YieldName(reason))

    def keep_name(self, reply: Reply) -> None:
        """The one kept went for good while this one yields (rule 22): serve again if it can."""
        self.registrar.tell(KeepName(reply))


# -- the death watch -------------------------------------------------------------------


def _mark(name: str, *, stopped: bool = False) -> ConsumerDown:
    return ConsumerDown(name, stopped)


def gone_for_good(
    name: str,
    *,
    also: Iterable[str] = (),
    stopped: bool = False,
    later: Container[str] = frozenset(),
) -> None:
    """Registrar `name` is gone and nobody will restart it: this process's membership
    records it, and each of `also` of another process gets the mark (skipped if unreachable).
    `stopped`: stopped cleanly, so it holds nothing (rule 12) and what it held is released;
    `later`: registrars here that hear that stop later (`PeersStopped`, the tree's stop)."""
    if stopped:
        MEMBERSHIP.stopped(name, by="its supervisor", later=later)
    else:
        MEMBERSHIP.lost(name, by="the death watch")
    here = {peer.name for peer in DIRECTORY.local_peers()}
    for target in sorted(set(also) - here - {name}):
        try:
            DIRECTORY.lookup(target).tell(_mark(name, stopped=stopped))
        except RrError:
            logger.debug("death watch: registrar %s unreachable", target)


def back(name: str) -> None:
    MEMBERSHIP.back(name)


def gone() -> dict[str, bool]:
    """The registrars this process knows are gone for good, each with whether it was stopped."""
    return MEMBERSHIP.gone()


def tell_gone(target: str, name: str, *, stopped: bool = False) -> None:
    """Tell registrar `target` only that registrar `name` is gone for good (`stopped`: as
    `gone_for_good`); `RrError` if `target` cannot be reached."""
    DIRECTORY.lookup(target).tell(_mark(name, stopped=stopped))


def heard_started(target: str, name: str) -> None:
    """Tell registrar `target` that `name` (re)started: it reconciles with it if they have
    business (rule 20); nothing if it cannot be reached (it reconciles when it is back)."""
    if target != name:
        with contextlib.suppress(RrError):
            DIRECTORY.lookup(target).tell(ReconcileAsk(name, holds_yours=False))


def lost_everything(name: str, *, also: Iterable[str] = (), handle: Servable | None = None) -> None:
    """Registrar `name` restarted without a backup: those here (`Membership.started`) and in `also`
    are told it started (`heard_started`), and it `LostEverything` (rule 20). `handle`: its
    `ResourceRegistrar`, through which it is told (it may not be in the directory yet)."""
    MEMBERSHIP.started(name)
    also = set(also)
    if also:  # (this process's registrars are not listed for nobody: a tree of 1,000's)
        for target in sorted(also - {peer.name for peer in DIRECTORY.local_peers()}):
            heard_started(target, name)
    if handle is not None:
        handle.tell(LostEverything())
        return
    try:
        DIRECTORY.lookup(name).tell(LostEverything())
    except RrError:
        logger.debug("lost everything: registrar %s unreachable", name)


# -- the catalog as events (CatalogRestored, RegistrarStopped) ------------------------


def _catalog_rows(shared: Shared) -> dict[str, object]:
    """The rows, counts and digest of a catalog event (`CatalogRestored`): up to
    `LISTED_ROWS` rows of each kind, read as plain strings; above that only counts."""
    catalog = shared.catalog
    clients = tuple(
        (record.query.id, record.query.serving_rr, record.query.server, record.parent or "")
        for record in catalog.client_records()
    )
    rows = catalog.rows(LISTED_ROWS)
    if rows is None or len(clients) > LISTED_ROWS:
        return {
            "resources": (),
            "consumers": (),
            "clients": (),
            "counts": (*catalog.counts(), len(clients)),
            "complete": False,
            "digest": "",
        }
    kinds: tuple[Rows, Rows, Rows] = (tuple(rows[0]), tuple(rows[1]), clients)
    # hashed as one string (one `update`, not two per row)
    digest = hashlib.sha256("".join(map(_digested, kinds)).encode())
    return {
        "resources": kinds[0],
        "consumers": kinds[1],
        "clients": kinds[2],
        "counts": tuple(len(listed) for listed in kinds),
        "complete": True,
        "digest": digest.hexdigest()[:16],
    }


def _digested(listed: Rows) -> str:
    """One kind's rows as the digest reads them: sorted, fields joined by \x1f, rows ended
    by \x1e, the kind by \x1d."""
    if not listed:
        return "\x1d"
    return "\x1e".join(map("\x1f".join, sorted(listed))) + "\x1e\x1d"


def publish_restored(shared: Shared) -> None:
    if shared.events.active and shared.saver.store is not None:
        shared.events.publish(events.CatalogRestored(shared.name, **_catalog_rows(shared)))  # type: ignore[arg-type]


def publish_stopped(shared: Shared) -> None:
    if shared.events.active:
        shared.events.publish(events.RegistrarStopped(shared.name, **_catalog_rows(shared)))  # type: ignore[arg-type]
