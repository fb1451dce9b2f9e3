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
    "Phase",
    "Probes",
    "Server",
    "Shared",
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


@dataclasses.dataclass
class Server:
    """A registered resource server (its `label(request)`: `display.py`)."""

    name: str
    ref: pykka.ActorRef[Any]  # (a `provider.ServerActor`)
    on_status: StatusCallback | None
    closing: bool = False
    label: Callable[[Any], Any] | None = None


@dataclasses.dataclass
class Waiter:
    """A caller waiting for a load: its consumer id, its registrar, where to answer."""

    query_id: str
    origin_rr: str
    reply: Reply


class OpenReply:
    """A handle request's reply, known to its actor until answered (a crash fails it).

    Answered on the actor thread, or, for `send_status`, on the thread of the last
    acknowledgement: so `open_requests` (a dict used as an ordered set: in the order the
    requests came) is only ever changed by single dict operations (set an item, pop
    one) and read as a copy (`list(...)`), each atomic.
    """

    __slots__ = ("open", "reply")

    def __init__(self, reply: Reply, open_requests: dict[OpenReply, None]) -> None:
        self.reply = reply
        self.open = open_requests
        open_requests[self] = None

    def set_result(self, value: Any) -> None:
        self.open.pop(self, None)
        self.reply.set_result(value)

    def set_error(self, error: BaseException) -> None:
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
        self.events = published
        self.held_in_doubt: set[str] = set()
        # this run of the registrar (`new_life`), the same in every `ReconcileAsk`,
        # `Reconcile` and `Load` it sends (`consumer.py`'s `Flights.kept_at`; a
        # provider fences the loads of an earlier run: `provider.py`'s `Lives`)
        self.life = life or new_life()

    @property
    def stopping(self) -> bool:
        """Whether it stops (or ended): it takes no new loads and keeps no new answers."""
        return self.phase is Phase.STOPPING or self.phase is Phase.ENDED

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
                logger.warning(
                    "registrar %s: %s; changes wait in memory, new loads are refused until "
                    "a write succeeds",
                    self.name,
                    exc,
                )
            return exc
        if written and told:
            self.probe("events_written", told)  # (committed with them, not yet published)
        self.publish(*told)
        return None

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
        if not saver.durable or saver.failure is None or saver.retry():
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
