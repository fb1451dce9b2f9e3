"""What every part of one registrar actor shares: its record, and the probes on its steps.

```
 Shared: the registrar's record, held by each part as `self.registrar` (the actor's
 thread only, but `probes`); each side's module widens it by its parts (`ConsumerRecord`,
 `StatusRecord`, `ProviderRecord`, `RegistrarRecord`), which the actor puts in it
   catalog            what it serves and holds (`_catalog`): the actor its one writer
   saver              the save policy over its backup (or over nothing)
     commit(*told)    changes and the events telling of them, one transaction, then
                      published; a failed write returned, the changes kept pending
   phase              SETTING_UP ─ready─► SERVING ─stop─► STOPPING ─► ENDED
   servers, workers   its resource servers; the threads that run user callbacks
   come_back, send    the answer to what it asks comes back through its mailbox
   events             its publisher: an event is built only while it is `active`
   probes             hooks on named steps (`rr_actors.testing.intercept`)
```

A name that no step has raises `ConfigError` in `intercept`, so renaming a step cannot
turn a race test into one that passes without racing anything. How a turn's changes
are written: docs/explanation/architecture.md, "One turn's transaction".
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
from rr_actors._catalog import Catalog, Changes, Resource
from rr_actors._core import runtime
from rr_actors._core.bus import Publisher
from rr_actors._core.directory import DIRECTORY, LocalPeer, Reply
from rr_actors._core.replies import Continuation, TokenReply, Tokens
from rr_actors._core.workers import Workers
from rr_actors._store import Saver
from rr_actors._types import StatusCallback
from rr_actors.config import RegistrarConfig
from rr_actors.errors import CatalogWriteError, RrError

logger = logging.getLogger("rr_actors")


def consumers_by_origin(resource: Resource) -> dict[str, tuple[str, ...]]:
    by_origin: dict[str, list[str]] = {}
    for query_id, origin in resource.consumers.items():
        by_origin.setdefault(origin, []).append(query_id)
    return {origin: tuple(ids) for origin, ids in by_origin.items()}


class Phase(enum.Enum):
    """Where a registrar actor is in its life (one phase, no lifecycle booleans)."""

    SETTING_UP = "setting up"
    """`start(setup=)` runs: loads for servers it has not registered yet are held."""
    SERVING = "serving"
    STOPPING = "stopping"
    """`stop()` releases what it holds as a consumer; new loads are refused."""
    ENDED = "ended"
    """Stopped or dead: what still arrives is refused (`on_late`)."""


_OVER = (Phase.STOPPING, Phase.ENDED)  # (a member read through its class: see `calls.SENT`)


class Pace:
    """What a server's loads take lately: `load_s`, the recent average (from 0); `learned`,
    when it last moved or a probe left (monotonic). Floats, read whole: no lock."""

    __slots__ = ("learned", "load_s")

    def __init__(self) -> None:
        self.load_s = 0.0
        self.learned = 0.0


@dataclasses.dataclass
class Server:
    """A registered resource server (`max_pending` `None`: the registrar's)."""

    name: str
    ref: pykka.ActorRef[Any]  # (a `provider.ServerActor`)
    on_status: StatusCallback | None
    closing: bool = False
    label: Callable[[Any], Any] | None = None
    max_pending: int | None = None
    # refusals since its last `ServerOverloaded`, and when that was (`Provider.refused`)
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
    """A handle request's reply, known to its actor until answered (a crash fails it). Answered
    on any thread: `open_requests` changes by single dict operations, read as a copy."""

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
    """A step whose change waits for its turn's commit: what it does then (`undo` `None`:
    `ok` runs after a failed write too; `refuse` `None`: a death leaves it to `fail_waiting`)."""

    ok: Callable[[], None]
    undo: Callable[[CatalogWriteError], None] | None
    refuse: Callable[[RrError], None] | None


class TurnEvents:
    """A registrar's publisher as its parts see it: while its turn has changes staged, an
    event is held and published after the turn's commit, in order; else at once."""

    __slots__ = ("_published", "_shared")

    def __init__(self, shared: Shared) -> None:
        self._shared = shared
        self._published = shared.published

    @property
    def active(self) -> bool:
        return self._published.active

    def publish(self, event: events.Event) -> None:
        shared = self._shared
        if shared.dirty:
            shared.held.append((event, False))
        else:
            self._published.publish(event)


_STARTS = itertools.count()  # registrars started in this process (`Shared.life`)


def new_life() -> str:
    """A token for one run of a registrar (`Shared.life`): process, wall clock and this
    process's count of starts, so a later start orders after (`life_order`)."""
    return f"{runtime.getpid()}.{runtime.wall_ns()}.{next(_STARTS)}"


def life_order(life: str) -> tuple[int, int]:
    """Where `life` comes among the runs of one registrar (`(0, 0)`: no order known); holds
    while the wall clock does not step back across a restart more than the restart took."""
    _pid, _, rest = life.partition(".")
    wall, _, count = rest.partition(".")
    if not (wall.isdigit() and count.isdigit()):
        return (0, 0)
    return (int(wall), int(count))


class Shared:
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
        # this run (`new_life`), in every `ReconcileAsk`, `Reconcile` and `Load` it sends
        self.life = life or new_life()
        # its supervisor tells the system it (re)started (`announce_started`): it never
        self.announced = False  # reconciles with every registrar, only its own catalog's

    @property
    def stopping(self) -> bool:
        return self.phase in _OVER

    # -- the turn: one transaction for the messages a turn handled ----------------------

    def commit_then(
        self,
        *told: events.Event,
        ok: Callable[[], None],
        undo: Callable[[CatalogWriteError], None],
        refuse: Callable[[RrError], None],
    ) -> None:
        """Commit the catalog's changes and the events `told` of them; then run `ok()` (the
        step's answer), or `undo(error)` if the write failed. In a durable registrar's turn
        they are staged and written at its end (`end_turn`), so an answer is released only
        once its change is durable (rules 14-16); `refuse(error)`: it died before that."""
        if not (self.in_turn and self.saver.durable):
            failed = self.commit(*told)
            if failed is None:
                ok()
            else:
                undo(failed)
                self.commit()
            return
        changes = self._drain()
        if changes is not None:
            self.saver.stage(changes)
            if not self.dirty:
                self.dirty, self.turn_thread = True, runtime.get_ident()
        if not self.dirty:  # nothing of it, nor of the turn before it, to wait for
            self.publish(*told)
            ok()
            return
        if told:
            self.held.extend((event, True) for event in told)
        self.staged.append(Staged(ok, undo, refuse))

    def after_commit(self, then: Callable[[], None]) -> bool:
        """Run `then()` after the turn's commit, failed or not (`False`: nothing staged; run it)."""
        if not self.dirty:
            return False
        self.staged.append(Staged(then, None, None))
        return True

    def holds_here(self) -> bool:
        """Whether the calling thread has the turn that staged changes."""
        return self.turn_thread == runtime.get_ident()

    def end_turn(self) -> CatalogWriteError | None:
        """Commit what the turn staged in one transaction, then publish its held events and run
        each staged `ok` in order; failed: undo each (newest first), commit that, return it."""
        failed: CatalogWriteError | None = None
        while self.dirty or self.staged:  # (an answer released may stage more)
            failed = self._write_turn() or failed
        return failed

    def _write_turn(self) -> CatalogWriteError | None:
        staged, held = self.staged, self.held
        self.staged, self.held, self.dirty = [], [], False
        told = [event for event, _ in held] if held else ()
        healthy = self.saver.failure is None
        try:
            if self.probes is not None:  # (staged, not written: a kill loses it)
                self.probes.fire("turn_commit", staged)
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
        """The turn's write failed (`exc`): publish the events told outside a change, undo each
        staged step (newest first), commit that, then release the answers that wait."""
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
        """The registrar died in a turn: each staged step is refused `error`, nothing written."""
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
        """Hand the catalog's changes to the save policy and publish the events `told` of them.
        Written at once (`save_on_modify`, `now`), changes and events are one transaction (the
        outbox), published after it; left for the interval's flush, the events go now. Returns
        the error of a failed write (changes pending, `told` unpublished), else `None`."""
        if self.dirty:  # with what the turn staged, one transaction
            return self._join_turn(told)
        if self.saver.store is None:  # nothing persists this catalog
            self.publish(*told)
            return None
        changes = self._drain()
        if changes is None and not (now and self.saver.pending):
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
        """`commit` in a turn that staged changes: in the turn's transaction (a staged row is
        written as it then is, with this change: its events go with it). The error, or `None`."""
        changes = self._drain()
        if changes is not None:
            self.saver.stage(changes)
        self.held.extend((event, True) for event in told)
        failed = self._write_turn()
        self.end_turn()  # (what its steps' answers staged meanwhile, if any)
        return failed

    def publish(self, *told: events.Event) -> None:
        for event in told:
            self.events.publish(event)

    def _drain(self) -> Changes | None:  # (`None`: nothing changed)
        if not self.catalog.changed():
            return None
        changes = self.catalog.drain_changes()
        if self.held_in_doubt:  # written once settled (`settle_held`)
            for rid in self.held_in_doubt.intersection(changes.resources):
                del changes.resources[rid]
            return changes if changes else None
        return changes

    def settle_held(self, rids: set[str]) -> CatalogWriteError | None:
        """Write what became of held in-doubt resources `rids` (settled now), as `commit`."""
        for rid in rids & self.held_in_doubt:
            self.held_in_doubt.discard(rid)
            self.catalog.mark_changed(rid)
        return self.commit()

    def unwritable(self) -> CatalogWriteError | None:
        """Why a durable registrar must refuse new loads now (its backup cannot be written; each
        new load retries the write), `None` once it can."""
        saver = self.saver
        if not saver.durable or saver.failure is None:
            return None
        if self.dirty:  # (the retry would write what the turn staged, without its events)
            self.end_turn()
        if saver.failure is None or saver.retry():
            return None
        return saver.failure

    def come_back(self, then: Continuation) -> TokenReply:
        assert self.ref is not None
        return self.tokens.reply(self.ref, then)

    def send(self, target: str, make: Callable[[Reply], Any], then: Continuation) -> None:
        """Send `make(reply)` to registrar `target`; `then(value, error)` runs on the answer."""
        reply = self.come_back(then)
        try:
            DIRECTORY.lookup(target).tell(make(reply))
        except RrError as exc:
            reply.set_error(exc)

    def probe(self, step: str, subject: Any) -> None:
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
        with self._lock:
            for table, hook in ((self._before, before), (self._after, after)):
                if hook is not None and hook in table.get(step, ()):
                    table[step] = tuple(h for h in table[step] if h is not hook)

    def around(self, step: str, subject: Any, run: Callable[[Any], None]) -> None:
        for hook in self._before.get(step, ()):
            hook(subject)
        run(subject)
        for hook in self._after.get(step, ()):
            hook(subject)

    def fire(self, step: str, subject: Any) -> None:
        """Run the hooks of a point `step` (its `before` hooks, then its `after` hooks)."""
        for hook in (*self._before.get(step, ()), *self._after.get(step, ())):
            hook(subject)
