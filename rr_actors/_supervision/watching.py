"""What a supervisor shows of its tree: its event stream and the observer's page.

`TreeWatch` is the part of [`Supervisor`][rr_actors.Supervisor] behind `subscribe` and
`flush_events` (the supervisor's methods document them), and what the lab's observer
(`rr_actors_lab.observe.observe(sup)`, `graph(sup)`) reads of a tree (`access`, `opened`). How the
tree's events reach its subscribers, in the supervisor's process:

```
 supervisors (Node) ── ChildStarted/Exited/Restarted, SupervisorGaveUp ──► publish ──┐
 a process manager's heartbeat ── ManagerOverloaded ────────────────────► publish ──┤
 thread manager's registrar ── relay_to ─────────────────────────────────► deliver ──┤
 process manager's registrar ─► its process's hub ─► Forwarder ─► control pipe       ├─► tree
      ─► ManagerProcess watcher thread ─► EventRelay.deliver ────────────► deliver ──┘  publisher
                                                                                  ─► subscriptions
```

Manager processes forward their events only while the tree has a listener (a tree
nobody watches builds none); the switch reaches each process asynchronously, so a
forwarded event older than the last switch on (by its `at`, on `hlc.CLOCK`) is dropped.
The observer is the lab's, which the runtime never imports: the lab's entry points take
the supervisor, and find its `TreeWatch` (`Supervisor`'s `tree_watch`).
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

if TYPE_CHECKING:
    from rr_actors._registrar import ResourceRegistrar

SWITCH_TIMEOUT = 2.0
"""Seconds a first subscriber waits, at most, for the manager processes to forward."""


class EventRelay:
    """A tree's publisher, and the switch of its manager processes' forwarding."""

    def __init__(self) -> None:
        self.publisher: Publisher[events.Event] = events.publisher(EVENT_LOG)
        self._lock = runtime.Lock()
        self._listened = False
        self._since = 0.0  # `hlc.CLOCK.wall()` of the last switch on: older events are dropped
        self._processes: list[ManagerProcess] = []
        self.publisher.watch_listeners(self._switch)

    @property
    def forwarding(self) -> bool:
        return self._listened

    def attach(self, process: ManagerProcess, *, forwarding: bool) -> None:
        """Switch a manager process with the others from now on (`forwarding`: what it was
        started with; told at once if that changed since)."""
        with self._lock:
            self._processes = [p for p in self._processes if not p.exited.is_set()]
            self._processes.append(process)
            if self._listened != forwarding:
                process.forward_events(self._listened)

    def sync(self, timeout: float) -> bool:
        """Block until what every manager process forwarded before the call was delivered;
        whether every one answered within `timeout` seconds."""
        deadline = runtime.monotonic() + timeout
        with self._lock:
            processes = [p for p in self._processes if not p.exited.is_set()]
        answered = True
        for process in processes:  # (every one, also after one did not answer)
            answered = process.sync_events(max(0.0, deadline - runtime.monotonic())) and answered
        return answered

    def deliver(self, batch: list[Any]) -> None:
        """Hand forwarded events to the tree's subscribers (the watcher thread)."""
        since = self._since
        for event in batch:
            if getattr(event, "at", since) >= since:
                self.publisher.deliver(event)

    def overloaded(self, supervisor: str, manager: str, pid: int, late: Late) -> None:
        """Publish a `ManagerOverloaded`: `manager` answered its heartbeat late, excused."""
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

    def version(self) -> int: ...

    def wait_changed(self, since: int, *, timeout: float) -> int: ...

    def wake(self) -> None: ...


class _Carrying(Protocol):
    @property
    def network(self) -> object: ...


class Watched(Changes, Protocol):
    """What a tree shares that its watch reads (the supervision `Tree`, which imports this
    module: a protocol, so neither imports the other)."""

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
    """What `Supervisor.observe` hands the observer besides the supervisor's public methods
    (`restart_due`: child name -> when its restart is due, wall clock, seconds)."""

    spec: SupervisorSpec
    changes: Changes
    restart_due: Mapping[str, float]
    running: Callable[[], bool]
    registrars: Callable[[], list[ResourceRegistrar]]
    network: object = None


class Page(Protocol):
    """An open observer's page, as `Supervisor.observe` returns it
    ([`rr_actors_lab.observe.Observer`][rr_actors_lab.observe.Observer] is the one)."""

    url: str
    keep_serving: bool

    @property
    def closed(self) -> bool: ...

    def set_clock(self, origin: float, label: str = ...) -> None:
        """Show times on the page as seconds since `origin` (wall clock), named `label`."""
        ...

    def refresh(self) -> None: ...

    def source_ended(self) -> None:
        """The supervisor stopped: close the page, or (`keep_serving`) say it ended."""
        ...

    def close(self, *, timeout: float = ...) -> None: ...

    def __enter__(self) -> Self: ...

    def __exit__(self, *_: object) -> None: ...


class _Named(Protocol):
    @property
    def name(self) -> str: ...


class TreeWatch:
    """The event stream and the observers of one supervision tree."""

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
        return self.tree.events.publisher.subscribe(
            callback, maxsize=maxsize, name=f"{self.sup.name}-events"
        )

    def flush_events(self, *, timeout: float) -> bool:
        check_seconds("timeout", timeout)
        return self.tree.events.sync(timeout)

    def opened(self, page: Page) -> Page:
        """`page`, an observer's page of this tree (the lab's `observe(sup)`), closes with it."""
        self.observers.append(page)
        return page

    def last_look(self) -> None:
        """Observers that outlive the tree read its catalogs once more."""
        for observer in self.observers:
            if observer.keep_serving:
                observer.refresh()

    def close_observers(self) -> None:
        """The supervisor stopped: close every observer (but those that `keep_serving`)."""
        observers, self.observers = self.observers, []
        for observer in observers:
            observer.source_ended()

    def access(self) -> TreeAccess:
        return TreeAccess(
            spec=self.tree.spec,
            changes=self.tree,
            restart_due=self.tree.restart_due,
            running=self.running,
            registrars=self.registrars,
            network=self.tree.processes.network,
        )
