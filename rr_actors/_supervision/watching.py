"""What a supervisor shows of its tree: its event stream and the observer's page.

`TreeWatch` is the part of [`Supervisor`][rr_actors.Supervisor] that lets people and
programs see the tree work; the supervisor holds one and hands it `subscribe` and
`flush_events` (the tree's event stream, manager processes included: `EventRelay`),
`observe` (a live web page) and `graph` (the same picture as text). The supervisor's
methods document them.

How the tree's events reach its subscribers, in the supervisor's process:

```
 supervisors (Node) ── ChildStarted/Exited/Restarted, SupervisorGaveUp ──► publish ──┐
 a process manager's heartbeat ── ManagerOverloaded ────────────────────► publish ──┤
 thread manager's registrar ── relay_to ─────────────────────────────────► deliver ──┤
 process manager's registrar ─► its process's hub ─► Forwarder ─► control pipe       ├─► tree
      ─► ManagerProcess watcher thread ─► EventRelay.deliver ────────────► deliver ──┘  publisher
                                                                                  ─► subscriptions
```

Each event is logged at INFO once, where it happened (a manager process logs its own);
the tree's publisher only logs the supervisors' events. Manager processes forward their
events only while the tree has a listener, so a tree nobody watches builds no event in
its manager processes (`watch_listeners` switches them on and off). The switch reaches
each process asynchronously: what a process made before it heard "off" may still arrive
after a new listener came, so a forwarded event older than the last switch on (by its
`at`: the switch's time is read from the clock events' `at` is, `hlc.CLOCK`, a skewed
one included) is dropped; a new listener hears what happens from the moment it
subscribed.

The observer is the lab's (`rr_actors.observe`), which the runtime never imports: a
supervisor finds it through `Observing`, a protocol this module owns, in a slot the
observer fills (`attach_observer`) when it is imported, and `rr_actors` fills at a
supervisor's first use (`rr.Supervisor`: the observer itself is imported only at the
first `observe` or `graph`). What the supervisor hands it is `TreeAccess`; what it keeps
of an open page, a `Page`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, Protocol, Self

from rr_actors import events
from rr_actors._core import hlc, runtime
from rr_actors._core.bus import Publisher, Subscription
from rr_actors._process.heartbeat import Late
from rr_actors._process.manager import ManagerProcess
from rr_actors._registrar.actor import EVENT_LOG
from rr_actors.config import SupervisorSpec, check_seconds
from rr_actors.errors import ConfigError

if TYPE_CHECKING:
    import socket

    from rr_actors._registrar import ResourceRegistrar

__all__ = [
    "SWITCH_TIMEOUT",
    "Changes",
    "EventRelay",
    "Observing",
    "Page",
    "TreeAccess",
    "TreeWatch",
    "Watched",
    "attach_observer",
]

SWITCH_TIMEOUT = 2.0
"""Seconds a first subscriber waits, at most, for the manager processes to forward."""


class EventRelay:
    """A tree's publisher, and the switch of its manager processes' forwarding.

    Attributes:
        publisher: where the tree's events are published (`Supervisor.subscribe`).
    """

    def __init__(self) -> None:
        self.publisher: Publisher[events.Event] = events.publisher(EVENT_LOG)
        self._lock = runtime.Lock()
        self._listened = False
        self._since = 0.0  # `hlc.CLOCK.wall()` of the last switch on: older events are dropped
        self._processes: list[ManagerProcess] = []
        self.publisher.watch_listeners(self._switch)

    @property
    def forwarding(self) -> bool:
        """Whether manager processes should forward their events now (someone listens)."""
        return self._listened

    def attach(self, process: ManagerProcess, *, forwarding: bool) -> None:
        """Switch a manager process with the others from now on.

        `forwarding` is what it was started with; if the tree's listeners changed since,
        it is told at once, so no switch is missed.
        """
        with self._lock:
            self._processes = [p for p in self._processes if not p.exited.is_set()]
            self._processes.append(process)
            if self._listened != forwarding:
                process.forward_events(self._listened)

    def sync(self, timeout: float) -> bool:
        """Block until what every manager process forwarded before the call was delivered.

        Returns:
            Whether every one answered within `timeout` seconds.
        """
        deadline = runtime.monotonic() + timeout
        with self._lock:
            processes = [p for p in self._processes if not p.exited.is_set()]
        answered = True
        for process in processes:  # (every one, also after one did not answer)
            answered = process.sync_events(max(0.0, deadline - runtime.monotonic())) and answered
        return answered

    def deliver(self, batch: list[Any]) -> None:
        """Hand events a manager process forwarded to the tree's subscribers (watcher
        thread); one made before the last switch on was made while nobody listened."""
        since = self._since
        for event in batch:
            if getattr(event, "at", since) >= since:
                self.publisher.deliver(event)

    def overloaded(self, supervisor: str, manager: str, pid: int, late: Late) -> None:
        """Manager process `manager` of `supervisor` answered its heartbeat late, excused
        (its watcher thread): a `ManagerOverloaded`, published here, where it was seen
        (logged at INFO too; the heartbeat's WARNING said it first)."""
        if self.publisher.active:
            self.publisher.publish(
                events.ManagerOverloaded(
                    supervisor,
                    manager,
                    pid,
                    late.silent,
                    late.bound,
                    late.excused,
                    late.busy,
                    late.queued,
                )
            )

    def _switch(self, listened: bool) -> None:
        with self._lock:
            if listened and not self._listened:
                self._since = hlc.CLOCK.wall()  # (the clock events' `at` reads)
            self._listened = listened
            self._processes = [p for p in self._processes if not p.exited.is_set()]
            for process in self._processes:
                process.forward_events(listened)
        if listened:  # the new listener hears what happens from now on: they all switched
            self.sync(SWITCH_TIMEOUT)


class Changes(Protocol):
    """How the observer learns that the tree published a change (the supervision `Tree`)."""

    def version(self) -> int:
        """How many changes the tree has published so far."""
        ...

    def wait_changed(self, since: int, *, timeout: float) -> int:
        """Block until the tree publishes a change after `since` (or is woken, or
        `timeout` seconds pass); the version then."""
        ...

    def wake(self) -> None:
        """Wake every `wait_changed` now (the observer closes)."""
        ...


class _Carrying(Protocol):
    @property
    def network(self) -> object: ...


class Watched(Changes, Protocol):
    """What a tree shares that its watch reads (the supervision `Tree`, which imports this
    module for its `EventRelay`: a protocol here, so neither imports the other)."""

    @property
    def spec(self) -> SupervisorSpec: ...

    @property
    def events(self) -> EventRelay: ...

    @property
    def restart_due(self) -> Mapping[str, float]: ...

    @property
    def processes(self) -> _Carrying: ...


@dataclasses.dataclass(frozen=True)
class TreeAccess:
    """What `Supervisor.observe` hands the observer besides the supervisor's public methods.

    Attributes:
        spec: the whole tree's specs.
        changes: the tree's published changes (a wait for the next one).
        restart_due: child name -> when its scheduled restart is due (wall clock, s).
        running: whether the supervisor has started and not stopped.
        registrars: the consumer registrars `Supervisor.registrar` started (this process).
        network: the carrier given to the supervisor (`Supervisor(network=)`), or `None`.
    """

    spec: SupervisorSpec
    changes: Changes
    restart_due: Mapping[str, float]
    running: Callable[[], bool]
    registrars: Callable[[], list[ResourceRegistrar]]
    network: object = None


class Page(Protocol):
    """An open observer's page, as `Supervisor.observe` returns it
    ([`rr_actors.observe.Observer`][rr_actors.observe.Observer] is the one)."""

    url: str
    keep_serving: bool

    @property
    def closed(self) -> bool:
        """Whether the page was closed."""
        ...

    def set_clock(self, origin: float, label: str = ...) -> None:
        """Show times on the page as seconds since `origin` (wall clock), named `label`."""
        ...

    def refresh(self) -> None:
        """Read the tree's catalogs once more, now."""
        ...

    def source_ended(self) -> None:
        """The supervisor stopped: close the page, or (`keep_serving`) say it ended."""
        ...

    def close(self, *, timeout: float = ...) -> None:
        """Stop serving the page."""
        ...

    def __enter__(self) -> Self: ...

    def __exit__(self, *_: object) -> None: ...


class _Named(Protocol):
    @property
    def name(self) -> str: ...


class Observing(Protocol):
    """The observer as supervisors find it (`attach_observer`): `sup` is the supervisor,
    whose public methods it reads; `access` the rest (`TreeAccess`)."""

    def observe(
        self,
        sup: Any,
        access: TreeAccess,
        *,
        host: str,
        port: int,
        allow_faults: bool,
        allow_remote: bool,
        keep_serving: bool,
        across_hosts: bool | None,
        sock: socket.socket | None,
    ) -> Page:
        """Open the live page of a tree (`Supervisor.observe`)."""
        ...

    def graph(self, sup: Any, access: TreeAccess, format: str) -> str:
        """Draw the tree and its dependency graph as text (`Supervisor.graph`)."""
        ...


_FOUND: list[Callable[[], Observing]] = []  # where this process's observer is (one slot)


def attach_observer(find: Callable[[], Observing]) -> None:
    """Tell every supervisor of this process where its observer is: `find()` returns it
    (and may import it: it is called at each `observe` and `graph`). The last call wins."""
    _FOUND[:] = [find]


def _observer() -> Observing:
    """This process's observer (`attach_observer`)."""
    if not _FOUND:
        raise ConfigError(
            "no observer is attached in this process: import rr_actors.observe (a "
            "supervisor made as rr.Supervisor finds it by itself)"
        )
    return _FOUND[0]()


class TreeWatch:
    """The event stream and the observers of one supervision tree.

    Args:
        sup: the supervisor (its public methods are what the observer reads).
        tree: what the tree shares (its events, its published changes, its specs).
        running: whether the supervisor has started and not stopped.
        registrars: the consumer registrars `Supervisor.registrar` started.
    """

    def __init__(
        self,
        sup: _Named,
        tree: Watched,
        *,
        running: Callable[[], bool],
        registrars: Callable[[], list[ResourceRegistrar]],
    ) -> None:
        self.sup = sup
        self.tree = tree
        self.running = running
        self.registrars = registrars
        self.observers: list[Page] = []

    def subscribe(
        self, callback: Callable[[events.Event], object], *, maxsize: int
    ) -> Subscription[events.Event]:
        """`Supervisor.subscribe`."""
        return self.tree.events.publisher.subscribe(
            callback, maxsize=maxsize, name=f"{self.sup.name}-events"
        )

    def flush_events(self, *, timeout: float) -> bool:
        """`Supervisor.flush_events`."""
        check_seconds("timeout", timeout)
        return self.tree.events.sync(timeout)

    def observe(
        self,
        host: str,
        port: int,
        *,
        allow_faults: bool,
        allow_remote: bool,
        keep_serving: bool,
        across_hosts: bool | None,
        sock: socket.socket | None = None,
    ) -> Page:
        """`Supervisor.observe` (once the supervisor checked it is not stopped)."""
        observer = _observer().observe(
            self.sup,
            self.access(),
            host=host,
            port=port,
            allow_faults=allow_faults,
            allow_remote=allow_remote,
            keep_serving=keep_serving,
            across_hosts=across_hosts,
            sock=sock,
        )
        self.observers.append(observer)
        return observer

    def graph(self, format: str) -> str:
        """`Supervisor.graph`."""
        return _observer().graph(self.sup, self.access(), format)

    def last_look(self) -> None:
        """Observers that outlive the tree read its catalogs once more, before it stops."""
        for observer in self.observers:
            if observer.keep_serving:
                observer.refresh()

    def close_observers(self) -> None:
        """The supervisor stopped: close every observer opened so far, but those opened
        with `keep_serving`, which go on showing the final state until their `close()`."""
        observers, self.observers = self.observers, []
        for observer in observers:
            observer.source_ended()

    def access(self) -> TreeAccess:
        """What the observer needs of this tree besides the supervisor's public methods."""
        return TreeAccess(
            spec=self.tree.spec,
            changes=self.tree,
            restart_due=self.tree.restart_due,
            running=self.running,
            registrars=self.registrars,
            network=self.tree.processes.network,
        )
