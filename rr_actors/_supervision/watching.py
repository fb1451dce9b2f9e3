"""What a supervisor shows of its tree: its event stream and the observer's page.

`TreeWatch` is the part of [`Supervisor`][rr_actors.Supervisor] that lets people and
programs see the tree work; the supervisor holds one and hands it `subscribe` and
`flush_events` (the tree's event stream, manager processes included, `relay.py`),
`observe` (a live web page) and `graph` (the same picture as text). The supervisor's
methods document them.

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
from rr_actors._core.bus import Subscription
from rr_actors.config import SupervisorSpec, check_seconds
from rr_actors.errors import ConfigError

if TYPE_CHECKING:
    import socket

    from rr_actors._registrar import ResourceRegistrar
    from rr_actors._supervision.tree import Tree

__all__ = ["Changes", "Observing", "Page", "TreeAccess", "TreeWatch", "attach_observer"]


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
        tree: Tree,
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
