"""What every part of one registrar actor shares: its record, and the probes on its steps.

```
 Shared: the registrar's record, held by each part as `self.registrar` (the actor's
 thread only, but `probes`)
   config, name       its configuration
   catalog            what it serves and holds (`_catalog`): the actor its one writer
   saver              the save policy over its backup (or over nothing)
     commit(*told)    the catalog's changes to the saver with the events that tell of
                      them (written now: one transaction), then published; a failed
                      write (a full disk) is returned, the changes kept pending
     unwritable()     why a durable registrar refuses new loads now
   phase              SETTING_UP ─ready─► SERVING ─stop─► STOPPING ─► ENDED (death: ENDED)
   servers            server name ─► Server(ref, on_status, closing, label);
                      servers_settled: setup returned, a server it did not bring back
                      is gone for good
   workers            the threads that run user callbacks
   tokens, ref        come_back(then), send(target, make, then): the answer to what it
                      asks comes back through its mailbox (the actor never waits)
   events             its publisher: an event is built only while it is `active`
   held_in_doubt      restored in-doubt ids whose settling waits for `setup` (rule 16)
   probes             Probes: hooks on named steps (`rr_actors.testing.intercept`);
                      a message's step, or a POINT inside one (`probe(step, subject)`)
```

A name that no step has raises `ConfigError` in `intercept`, so renaming a step cannot
turn a race test into one that passes without racing anything.
"""

from __future__ import annotations

import dataclasses
import enum
import itertools
import logging
from collections.abc import Callable
from typing import Any

import pykka

from rr_actors import events
from rr_actors._catalog import Catalog, Resource
from rr_actors._core import runtime
from rr_actors._core.bus import Publisher
from rr_actors._core.directory import DIRECTORY, LocalPeer, Reply
from rr_actors._core.replies import Continuation, TokenReply, Tokens
from rr_actors._core.workers import Workers
from rr_actors._store import Saver
from rr_actors._types import StatusCallback
from rr_actors.config import RegistrarConfig
from rr_actors.errors import CatalogWriteError, RrError

__all__ = [
    "NO_REPLY",
    "POINTS",
    "Hook",
    "OpenReply",
    "Pace",
    "Phase",
    "Probes",
    "Server",
    "Shared",
    "Staged",
    "TurnEvents",
    "Waiter",
    "consumers_by_origin",
    "life_order",
    "new_life",
]

logger = logging.getLogger("rr_actors")


def consumers_by_origin(resource: Resource) -> dict[str, tuple[str, ...]]:
    """A resource's consumer ids, grouped by the registrar that holds them."""
    by_origin: dict[str, list[str]] = {}
    for query_id, origin in resource.consumers.items():
        by_origin.setdefault(origin, []).append(query_id)
    return {origin: tuple(ids) for origin, ids in by_origin.items()}


class Phase(enum.Enum):
    """Where a registrar actor is in its life (one phase, no lifecycle booleans)."""

    SETTING_UP = "setting up"
    """`start(setup=)` runs: loads for servers it has not registered yet are held."""
    SERVING = "serving"
    """Serving every request."""
    STOPPING = "stopping"
    """`stop()` releases what it holds as a consumer; new loads are refused."""
    ENDED = "ended"
    """Stopped or dead: what still arrives is refused (`on_late`)."""


class Pace:
    """What a server's loads take lately: `load_s`, an average of the recent ones (from 0:
    nothing is shed before a load has run), and `learned`, when it last moved or a probe
    left (`time.monotonic()`). Its actor's workers write it (`provider.ServerActor.ran`);
    the provider reads it too, to tell a refused caller when to ask again (a float
    each, read or written whole: no lock)."""

    __slots__ = ("learned", "load_s")

    def __init__(self) -> None:
        self.load_s = 0.0
        self.learned = 0.0


@dataclasses.dataclass
class Server:
    """A registered resource server (its `label(request)`: `display.py`; its own bound of
    new loads under way, `max_pending`, or `None`: the registrar's; its `pace`, shared
    with its actor)."""

    name: str
    ref: pykka.ActorRef[Any]  # (a `provider.ServerActor`)
    on_status: StatusCallback | None
    closing: bool = False
    label: Callable[[Any], Any] | None = None
    max_pending: int | None = None
    # new loads refused since its last `ServerOverloaded`, and when that was published
    # (`Provider.refused`; kept here, it goes with the server when it is unregistered)
    refusals: tuple[int, float] | None = None
    pace: Pace = dataclasses.field(default_factory=Pace)


@dataclasses.dataclass
class Waiter:
    """A caller waiting for a load: its consumer id, its registrar, where to answer."""

    query_id: str
    origin_rr: str
    reply: Reply
    trace: str = ""  # the traceparent its Load carried (`_core/traces.py`)


class OpenReply:
    """A handle request's reply, known to its actor until answered (a crash fails it).

    Answered on the actor thread (after the commit of its turn, if the turn staged a
    change: `Shared.after_commit`), or, for `send_status`, on the thread of the last
    acknowledgement (at once): so `open_requests` (a dict used as an ordered set: in the
    order the requests came) is only ever changed by single dict operations (set an
    item, pop one) and read as a copy (`list(...)`), each atomic.
    """

    __slots__ = ("open", "reply", "shared")

    def __init__(
        self, reply: Reply, open_requests: dict[OpenReply, None], shared: Shared | None = None
    ) -> None:
        self.reply = reply
        self.open = open_requests
        self.shared = shared  # (its answer waits for the commit of its actor's turn)
        open_requests[self] = None

    def set_result(self, value: Any) -> None:
        shared = self.shared
        if shared is not None and shared.dirty and shared.holds_here():
            shared.after_commit(lambda: self.set_result(value))  # (after the turn's commit)
            return
        self.open.pop(self, None)
        self.reply.set_result(value)

    def set_error(self, error: BaseException) -> None:
        shared = self.shared
        if shared is not None and shared.dirty and shared.holds_here():
            shared.after_commit(lambda: self.set_error(error))  # (after the turn's commit)
            return
        self.open.pop(self, None)
        self.reply.set_error(error)


class _NoReply:
    """The reply of a message that wants no answer (a tell): what it is given goes nowhere."""

    __slots__ = ()

    def set_result(self, value: Any) -> None:
        pass

    def set_error(self, error: BaseException) -> None:
        pass


NO_REPLY: Reply = _NoReply()
"""What a role's handler gets as `reply` for a message without one (`actor.DISPATCH`)."""


@dataclasses.dataclass(slots=True)
class Staged:
    """A step whose change waits for its turn's commit (`Shared.commit_then`): what it
    does then. `undo` `None`: `ok` runs after a failed write too; `refuse` `None`: a
    death leaves its caller to `Lifecycle.fail_waiting`."""

    ok: Callable[[], None]
    undo: Callable[[CatalogWriteError], None] | None
    refuse: Callable[[RrError], None] | None


class TurnEvents:
    """A registrar's publisher as its parts see it (`Shared.events`): while its turn has
    changes staged, an event published is held and published after the turn's commit
    (`Shared.end_turn`), in order with the events of those changes; else at once."""

    __slots__ = ("_published", "_shared")

    def __init__(self, shared: Shared) -> None:
        self._shared = shared
        self._published = shared.published

    @property
    def active(self) -> bool:
        """Whether anyone listens (`Publisher.active`)."""
        return self._published.active

    def publish(self, event: events.Event) -> None:
        """Publish `event` (actor's thread), after the turn's commit if one is pending."""
        shared = self._shared
        if shared.dirty:
            shared.held.append((event, False))
        else:
            self._published.publish(event)


_STARTS = itertools.count()  # registrars started in this process (`Shared.life`)


def new_life() -> str:
    """A token for one run of a registrar (`Shared.life`): its process, the wall clock
    (`runtime.wall_ns`) and a count of this process's starts, so no two starts share it
    and a later start orders after an earlier one (`life_order`); a simulation draws
    nothing from its seed for it."""
    return f"{runtime.getpid()}.{runtime.wall_ns()}.{next(_STARTS)}"


def life_order(life: str) -> tuple[int, int]:
    """Where `life` (`new_life`'s) comes among the runs of one registrar: its start's
    wall clock, then its process's count of starts; `(0, 0)` for "" or a token not
    made by `new_life` (no order known).

    The runs of one name follow each other (a restart comes after its run ended), so
    the later start orders after, as long as the host's wall clock does not step back
    across a restart by more than the restart took (`docs/explanation/failure-semantics.md`).
    """
    _pid, _, rest = life.partition(".")
    wall, _, count = rest.partition(".")
    if not (wall.isdigit() and count.isdigit()):
        return (0, 0)
    return (int(wall), int(count))


class Shared:
    """The registrar's record: what every part of its actor reads and writes."""

    def __init__(
        self,
        config: RegistrarConfig,
        catalog: Catalog,
        saver: Saver,
        peer: LocalPeer,
        published: Publisher[events.Event],
        *,
        setting_up: bool,
        life: str = "",
    ) -> None:
        self.config = config
        self.name = config.name
        self.catalog = catalog
        self.saver = saver
        self.peer = peer
        self.phase = Phase.SETTING_UP if setting_up else Phase.SERVING
        self.servers_settled = False
        self.servers: dict[str, Server] = {}
        self.yielding = False  # rule 22: closing servers are kept until the yield ends
        self.workers = Workers(config.name, max_workers=config.max_workers)
        self.tokens = Tokens()
        self.probes: Probes | None = None
        self.ref: pykka.ActorRef[Any] | None = None
        self.published = published  # (the publisher itself: `events` holds in a turn)
        # (a durable registrar's turn holds events: `TurnEvents`; no other ever stages)
        self.events: Publisher[events.Event] | TurnEvents = (
            TurnEvents(self) if saver.durable else published
        )
        # the turn (`commit_then`, `end_turn`): whether steps run in turns whose end
        # commits (a durable registrar's actor once started, until it dies), the changes
        # staged since the last write, what waits for that write, its events
        self.in_turn = False
        self.dirty = False
        self.turn_thread = 0  # (the thread of the turn that staged them: `holds_here`)
        self.staged: list[Staged] = []
        self.held: list[tuple[events.Event, bool]] = []  # (event, told by a staged change)
        self.held_in_doubt: set[str] = set()
        # this run of the registrar (`new_life`), the same in every `ReconcileAsk`,
        # `Reconcile` and `Load` it sends (`consumer.py`'s `Flights.kept_at`; a
        # provider fences the loads of an earlier run: `provider.py`'s `Lives`)
        self.life = life or new_life()

    @property
    def stopping(self) -> bool:
        """Whether it stops (or ended): it takes no new loads and keeps no new answers."""
        return self.phase is Phase.STOPPING or self.phase is Phase.ENDED

    # -- the turn: one transaction for the messages a turn handled ----------------------

    def commit_then(
        self,
        *told: events.Event,
        ok: Callable[[], None],
        undo: Callable[[CatalogWriteError], None],
        refuse: Callable[[RrError], None],
    ) -> None:
        """Commit the catalog's changes and the events `told` of them; then run `ok()`
        (the step's answer), or `undo(error)` if the write failed.

        In a turn of a durable registrar (`in_turn`: `save_on_modify` with a backup) the
        changes are staged: written with every other change of the turn in one
        transaction at its end (`end_turn`), and `ok` runs after that commit, so the
        answer is released only once its change is durable (rules 14-16). Otherwise
        they are committed now (`commit`), as before.

        Args:
            told: the events of the changes: in the outbox with them, published after
                the commit, before `ok`; dropped if the write fails.
            ok: the change is durable: answer (the actor's thread).
            undo: the write failed (`CatalogWriteError`: a full disk): undo the change
                in memory (no commit: the turn commits the undoing once) and fail the
                caller with the error.
            refuse: the registrar died before the turn's commit (`abort_turn`): fail
                the caller with the error (nothing is written any more).
        """
        if not (self.in_turn and self.saver.durable):
            failed = self.commit(*told)
            if failed is None:
                ok()
            else:
                undo(failed)
                self.commit()
            return
        changes = self.catalog.drain_changes()
        for rid in self.held_in_doubt.intersection(changes.resources):
            del changes.resources[rid]  # written once settled (`settle_held`)
        if changes:
            self.saver.stage(changes)
            if not self.dirty:
                self.dirty, self.turn_thread = True, runtime.get_ident()
        if not self.dirty:  # nothing of it, nor of the turn before it, to wait for
            self.publish(*told)
            ok()
            return
        self.held.extend((event, True) for event in told)
        self.staged.append(Staged(ok, undo, refuse))

    def after_commit(self, then: Callable[[], None]) -> bool:
        """Run `then()` after the turn's commit if changes wait for it (`False`: none wait,
        run it now). For an answer that may tell of a staged change (a handle's request:
        `OpenReply`); it runs after a failed write too."""
        if not self.dirty:
            return False
        self.staged.append(Staged(then, None, None))
        return True

    def holds_here(self) -> bool:
        """Whether the calling thread has the turn that staged changes (an answer given
        there waits for its commit; one from another thread, a status acknowledgement's,
        tells of no staged change and goes at once)."""
        return self.turn_thread == runtime.get_ident()

    def end_turn(self) -> CatalogWriteError | None:
        """Commit what the turn staged, one transaction, then release what waits for it.

        Runs at the end of each turn (`RegistrarActor.on_turn_end`), and at any other
        commit of the turn (`commit`: that change joins the transaction), so changes
        reach the file in the order they were made. Committed: the held events are
        published (in order), then each staged step's `ok` runs, in the order they were
        staged. The write failed: the events published outside a change are published,
        the staged steps undone (newest first) and that undoing committed (or kept
        pending), and the error returned.
        """
        failed: CatalogWriteError | None = None
        while self.dirty or self.staged:  # (an answer released may stage more)
            failed = self._write_turn() or failed
        return failed

    def _write_turn(self) -> CatalogWriteError | None:
        """One transaction of `end_turn`: what is staged and held now; `None` if written."""
        staged, held = self.staged, self.held
        self.staged, self.held, self.dirty = [], [], False
        told = [event for event, _ in held]
        healthy = self.saver.failure is None
        try:
            self.probe("turn_commit", staged)  # (staged, not written: a kill loses it)
            self.saver.write(told)
        except CatalogWriteError as exc:
            if healthy:
                self.warn_unwritten(exc)
            self.unwritten(staged, held, exc)
            return exc
        except BaseException:  # a bug: the actor dies (`abort_turn` refuses them)
            self.staged, self.held = staged + self.staged, held + self.held
            raise
        if told:
            self.probe("events_written", told)  # (committed with them, not yet published)
        for event, _ in held:
            self.published.publish(event)
        for step in staged:
            step.ok()
        return None

    def unwritten(
        self, staged: list[Staged], held: list[tuple[events.Event, bool]], exc: CatalogWriteError
    ) -> None:
        """The turn's write failed (`exc`): publish the events told outside a change, undo
        each staged step (newest first), commit that undoing (or keep it pending), then
        release the answers that wait for the write whatever its outcome."""
        for event, of_change in held:
            if not of_change:
                self.published.publish(event)
        for step in reversed(staged):
            if step.undo is not None:
                step.undo(exc)
        self.commit()  # (the undoing: kept pending if the disk is still full)
        for step in staged:
            if step.undo is None:
                step.ok()

    def abort_turn(self, error: RrError) -> None:
        """The registrar died in a turn: what it staged is never written, nor answered as
        done; each staged step's caller is failed with `error` (its `refuse`)."""
        staged, held = self.staged, self.held
        self.staged, self.held, self.dirty = [], [], False
        for event, of_change in held:
            if not of_change:
                self.published.publish(event)
        for step in staged:
            if step.refuse is not None:
                step.refuse(error)

    def warn_unwritten(self, exc: CatalogWriteError) -> None:
        """Log the first write of a failing streak (the next success clears it)."""
        logger.warning(
            "registrar %s: %s; changes wait in memory, new loads are refused until "
            "a write succeeds",
            self.name,
            exc,
        )

    def commit(self, *told: events.Event, now: bool = False) -> CatalogWriteError | None:
        """Hand the catalog's changes to the save policy (durable now, or at the next flush),
        and publish the events `told` that tell of them.

        Written at once (`save_on_modify`, or `now`: "whatever the policy"), the changes
        and their events are one transaction (the backup's outbox, `_store/outbox.py`),
        and the events are published after it: a SIGKILL after the commit cannot lose
        them (the supervisor's side reads them from the backup after the exit). Left for
        the interval's flush, the events are published now (a crash loses the change
        within the save window, not its event).

        Args:
            told: the events of the changes (built only when `events.active`).
            now: write them now whatever the save policy (an unload: `Teardown`).

        Returns:
            `None`, or the error of a write that failed (a full disk): the changes stay
            pending in memory and go with the next write that succeeds, and `told` is
            not published: a step whose caller waits for durability undoes its change
            and fails the caller with it; one whose change stands publishes them itself
            (`publish`).
        """
        if self.dirty:  # with what the turn staged, one transaction
            return self._join_turn(told)
        if self.saver.store is None:  # nothing persists this catalog
            self.publish(*told)
            return None
        changes = self.catalog.drain_changes()
        for rid in self.held_in_doubt.intersection(changes.resources):
            del changes.resources[rid]  # written once settled (`settle_held`)
        if not changes and not (now and self.saver.pending):
            self.publish(*told)
            return None
        healthy = self.saver.failure is None
        try:
            written = self.saver.changed(changes, told, now=now)
        except CatalogWriteError as exc:
            if healthy:  # once per failing streak: the next success clears it
                self.warn_unwritten(exc)
            return exc
        if written and told:
            self.probe("events_written", told)  # (committed with them, not yet published)
        self.publish(*told)
        return None

    def _join_turn(self, told: tuple[events.Event, ...]) -> CatalogWriteError | None:
        """`commit` in a turn that staged changes: this change, and its events `told`,
        are written in the turn's transaction (then the turn's end releases its steps).

        Not a transaction of their own after the staged one: a staged row is written as
        the catalog holds it at the write (the live row), so it already carries this
        change, while the staged events tell only of the staged ones. A hit staged, then
        its id released by its caller's `Abandon` in the same turn, would commit its
        `ConsumerAdded` without the id, and a kill before the release's own commit would
        lose the `ConsumerReleased`: an id acknowledged, then lost (issue 51).

        Returns:
            The error of the write that carried this change (`CatalogWriteError`: the
            staged steps were undone, `told` dropped; the caller undoes its change), or
            `None`.
        """
        changes = self.catalog.drain_changes()
        for rid in self.held_in_doubt.intersection(changes.resources):
            del changes.resources[rid]  # written once settled (`settle_held`)
        if changes:
            self.saver.stage(changes)
        self.held.extend((event, True) for event in told)
        failed = self._write_turn()
        self.end_turn()  # (what its steps' answers staged meanwhile, if any)
        return failed

    def publish(self, *told: events.Event) -> None:
        """Publish events built while `events.active` (this actor's thread)."""
        for event in told:
            self.events.publish(event)

    def settle_held(self, rids: set[str]) -> CatalogWriteError | None:
        """Write what became of held in-doubt resources `rids` (settled now), as `commit`."""
        for rid in rids & self.held_in_doubt:
            self.held_in_doubt.discard(rid)
            self.catalog.mark_changed(rid)
        return self.commit()

    def unwritable(self) -> CatalogWriteError | None:
        """Why a durable registrar must refuse new loads now: its backup cannot be written.

        While an earlier write failed, each new load first tries it again (`Saver.retry`);
        `None` once it succeeds (or for a registrar without `save_on_modify`).
        """
        saver = self.saver
        if not saver.durable or saver.failure is None:
            return None
        if self.dirty:  # (the retry would write what the turn staged, without its events)
            self.end_turn()
        if saver.failure is None or saver.retry():
            return None
        return saver.failure

    def come_back(self, then: Continuation) -> TokenReply:
        """A reply that runs `then(value, error)` back on this actor's thread."""
        assert self.ref is not None
        return self.tokens.reply(self.ref, then)

    def send(self, target: str, make: Callable[[Reply], Any], then: Continuation) -> None:
        """Send `make(reply)` to registrar `target`; `then(value, error)` runs on the answer.

        The actor never waits: the answer comes back through its mailbox. A target that
        cannot be reached answers at once with its error.
        """
        reply = self.come_back(then)
        try:
            DIRECTORY.lookup(target).tell(make(reply))
        except RrError as exc:
            reply.set_error(exc)

    def probe(self, step: str, subject: Any) -> None:
        """Fire the test probes of a named point `step` (no-op without probes)."""
        probes = self.probes
        if probes is not None:
            probes.fire(step, subject)


# -- test probes on named steps --------------------------------------------------------


Hook = Callable[[Any], None]
"""`hook(subject)`: the message a step handles, or what a point is about."""

POINTS: frozenset[str] = frozenset(
    {
        "close_resource",  # unregister_server: a resource gets FATAL, is revoked, unloads
        "unload_resource",  # the last consumer left: dependencies, then `unload`
        "stop_drained",  # stop(): waiting callers failed, mailbox drained; the actor ends next
        "send_load",  # a call's Load is about to leave the caller's thread (durable: committed)
        "withdraw",  # a caller that stopped waiting is about to send its Abandon
        "events_written",  # a change and its events committed together; published next
        "turn_commit",  # a turn's staged changes are about to be written (the Staged list)
    }
)
"""Points inside a step (`before` runs there; `after` is the same as `before`)."""


class Probes:
    """The hooks installed on one registrar, by step name (any thread may fire them)."""

    def __init__(self) -> None:
        self._lock = runtime.Lock()
        self._before: dict[str, tuple[Hook, ...]] = {}
        self._after: dict[str, tuple[Hook, ...]] = {}

    def add(self, step: str, *, before: Hook | None, after: Hook | None) -> None:
        """Install hooks on `step` (`intercept` checks that a step has that name)."""
        with self._lock:
            if before is not None:
                self._before[step] = (*self._before.get(step, ()), before)
            if after is not None:
                self._after[step] = (*self._after.get(step, ()), after)

    def remove(self, step: str, *, before: Hook | None, after: Hook | None) -> None:
        """Remove hooks `add` installed (no-op for hooks that are not there)."""
        with self._lock:
            for table, hook in ((self._before, before), (self._after, after)):
                if hook is not None and hook in table.get(step, ()):
                    table[step] = tuple(h for h in table[step] if h is not hook)

    def around(self, step: str, subject: Any, run: Callable[[Any], None]) -> None:
        """Run `run(subject)` between the `before` and `after` hooks of `step`."""
        for hook in self._before.get(step, ()):
            hook(subject)
        run(subject)
        for hook in self._after.get(step, ()):
            hook(subject)

    def fire(self, step: str, subject: Any) -> None:
        """Run the hooks of a point `step` (its `before` hooks, then its `after` hooks)."""
        for hook in (*self._before.get(step, ()), *self._after.get(step, ())):
            hook(subject)
