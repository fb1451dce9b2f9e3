"""What a supervisor shows of its tree: its event stream and the observer's page.

`TreeWatch` is the part of [`Supervisor`][rr_actors.Supervisor] that lets people and
programs see the tree work; the supervisor holds one and hands it `subscribe` and
`flush_events` (the tree's event stream, manager processes included, `relay.py`),
`observe` (a live web page, `rr_actors.observe`, an extra imported when called) and
`graph` (the same picture as text). The supervisor's methods document them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from rr_actors import events
from rr_actors._core.bus import Subscription
from rr_actors.config import check_seconds

if TYPE_CHECKING:
    import socket

    from rr_actors._registrar import ResourceRegistrar
    from rr_actors._supervision.tree import Tree
    from rr_actors.observe import Observer
    from rr_actors.observe._sources import Observable, TreeAccess

__all__ = ["TreeWatch"]


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
        sup: Observable,
        tree: Tree,
        *,
        running: Callable[[], bool],
        registrars: Callable[[], list[ResourceRegistrar]],
    ) -> None:
        self.sup = sup
        self.tree = tree
        self.running = running
        self.registrars = registrars
        self.observers: list[Observer] = []

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
    ) -> Observer:
        """`Supervisor.observe` (once the supervisor checked it is not stopped)."""
        from rr_actors.observe._observer import observe_supervisor  # noqa: PLC0415 - an extra

        observer = observe_supervisor(
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
        from rr_actors.observe._sources import LiveSource  # noqa: PLC0415
        from rr_actors.observe._text import render  # noqa: PLC0415

        tree, graph = LiveSource(self.sup, self.access()).snapshot()
        return render(graph, tree, format)

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
        from rr_actors.observe._sources import TreeAccess  # noqa: PLC0415

        return TreeAccess(
            spec=self.tree.spec,
            changes=self.tree,
            restart_due=self.tree.restart_due,
            running=self.running,
            registrars=self.registrars,
            network=self.tree.processes.network,
        )
