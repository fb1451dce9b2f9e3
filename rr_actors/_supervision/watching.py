"""What a supervisor shows of its tree: its event stream and the observer's page.

`TreeWatching` is the part of [`Supervisor`][rr_actors.Supervisor] that lets people and
programs see the tree work: `subscribe` and `flush_events` (the tree's event stream, manager
processes included, `relay.py`), `observe` (a live web page, `rr_actors.observe`, an extra
imported when called) and `graph` (the same picture as text).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, cast

from rr_actors import events
from rr_actors._core.bus import DEFAULT_MAXSIZE, Subscription
from rr_actors.config import SupervisorSpec, check_seconds
from rr_actors.errors import ConfigError

if TYPE_CHECKING:
    from rr_actors._registrar import ResourceRegistrar
    from rr_actors._supervision.supervisor import Supervisor
    from rr_actors._supervision.tree import Tree
    from rr_actors.observe import Observer

__all__ = ["TreeWatching"]


class TreeWatching:
    """The event stream and the observer of a supervision tree (a part of `Supervisor`)."""

    _spec: SupervisorSpec
    _tree: Tree
    _registrars: list[ResourceRegistrar]
    _observers: list[Observer]
    _started: bool
    _stopped: bool

    def _supervisor(self) -> Supervisor:
        return cast("Supervisor", self)  # (only `Supervisor` derives from this class)

    @property
    def name(self) -> str:
        """This supervisor's name."""
        return self._spec.name

    def _last_look(self) -> None:
        """Observers that outlive the tree read its catalogs once more, before it stops."""
        for observer in self._observers:
            if observer.keep_serving:
                observer.refresh()

    def _close_observers(self) -> None:
        observers, self._observers = self._observers, []
        for observer in observers:
            observer.source_ended()  # (closes it, unless it was opened with keep_serving)

    # -- events -------------------------------------------------------------------------

    def subscribe(
        self,
        callback: Callable[[events.Event], object],
        *,
        maxsize: int = DEFAULT_MAXSIZE,
    ) -> Subscription[events.Event]:
        """Call `callback(event)` for every event of the tree from now on, until closed.

        Events are the frozen dataclasses of `rr_actors.events`: what every supervisor of
        the tree does with its children (`ChildStarted`, `ChildExited`, `ChildRestarted`,
        `SupervisorGaveUp`) and what every registrar of the tree does (its managers', in
        threads or in processes, and those of `registrar()`). Events of manager processes
        are forwarded to this process while anyone subscribes; subscribe before `start`
        to see the children start.

        The callback runs on a subscriber thread of its own, never in a registrar's
        mailbox or the supervisor's, one event at a time, in the order they reached this
        process (a manager process's own events in the order they happened there). A slow
        callback never slows the tree: past `maxsize` queued events new ones are dropped,
        counted (`Subscription.dropped`) and reported by one `EventsDropped`.

        Args:
            callback: `callback(event)`; what it raises is logged.
            maxsize: events queued for it before new ones are dropped.

        Returns:
            The subscription; `close()` it, or use it as a context manager
            (`with sup.subscribe(cb): ...`).

        Raises:
            ConfigError: `maxsize` is not a positive int.
        """
        return self._tree.events.publisher.subscribe(
            callback, maxsize=maxsize, name=f"{self.name}-events"
        )

    def flush_events(self, *, timeout: float = 5.0) -> bool:
        """Bring the events of every manager process that happened before the call here.

        A manager process forwards its events in batches, so they reach this process a
        little after they happened. This returns once each running manager process has
        handed everything it had to this process's subscriptions (their queues); then
        `Subscription.wait_delivered` waits for the callbacks.

        Args:
            timeout: the longest wait, in seconds.

        Returns:
            Whether every manager process answered within `timeout`.

        Raises:
            ConfigError: `timeout` is not a positive number of seconds.
        """
        check_seconds("timeout", timeout)
        return self._tree.events.sync(timeout)

    # -- the observer -------------------------------------------------------------------

    def observe(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        allow_faults: bool = False,
        allow_remote: bool = False,
        keep_serving: bool = False,
    ) -> Observer:
        """Serve a live web page of this tree at the returned observer's `url`.

        The page shows the supervision tree (state, pid, restarts, last exit, backoff
        countdown; a restart flashes), each registrar's catalog, the dependency graph
        across registrars (the TeMoto thesis's figure 2.7, live) and a timeline of the
        status notifications with their hops and latencies. It follows the tree's
        events (`subscribe`) and reads each registrar's catalog in the registrar's own
        process (`run_in`), at most twice a second. The server runs on a
        thread of its own in this process (uvicorn); the observer is closed with the
        supervisor (`stop`), unless `keep_serving`, or by its `close()`. May be called
        before `start` (the page then sees the children start) but not after `stop`.

        Every request to the page must carry the token of its `url` (`?token=...`):
        the page shows every catalog, request values included, so only whoever has
        the URL sees it. At most 32 pages are open at once.

        Args:
            host: the address to listen on. A loopback address (the default) keeps the
                page on this machine; any other needs `allow_remote=True`.
            port: the port (0: a free one; the `url` says which).
            allow_faults: teaching mode: buttons on the page SIGKILL a process manager,
                SIGSTOP it (a hang; its heartbeat makes the supervisor kill and restart
                it, or a resume button sends SIGCONT) and send FATAL on a resource, each
                after a confirmation. The buttons send the `url`'s token back:
                share the URL only with whom may use them.
            allow_remote: allow a `host` that other machines can reach. They then see
                every catalog (requests and responses as `repr`s), and with
                `allow_faults` whoever has the URL can kill managers. Nothing from the
                browser is ever unpickled.
            keep_serving: after the supervisor stops, keep serving its final state
                (the page says it ended) until the observer's `close()`, so that it
                can be discussed (`rr-actors demo --observe --linger`).

        Returns:
            The open [`Observer`][rr_actors.observe.Observer] (`url`, `close()`).

        Raises:
            ConfigError: the `observe` extra is not installed (`pip install
                'rr-actors[observe]'`), the port is in use, `host` is not a loopback
                address and `allow_remote` is false, or the supervisor was stopped.
        """
        if self._stopped:
            raise ConfigError(f"supervisor {self.name!r} was stopped: nothing to observe")
        from rr_actors.observe._observer import observe_supervisor  # noqa: PLC0415 - an extra

        observer = observe_supervisor(
            self._supervisor(),
            self._observed(),
            host=host,
            port=port,
            allow_faults=allow_faults,
            allow_remote=allow_remote,
            keep_serving=keep_serving,
        )
        self._observers.append(observer)
        return observer

    def graph(self, format: str = "mermaid") -> str:
        """The tree and the dependency graph across its registrars, as text, now.

        Supervisors are hexagons with an arrow to each child; a manager's registrar is
        a box holding its resources; each query is a dashed arrow from the resource that
        holds it as a dependency (or the registrar, for a top-level call) to the
        provider's resource (the TeMoto thesis's figure 2.7). Catalogs are read in the
        registrars' own processes, as the observer does; a manager that is down is
        drawn without its resources.

        Args:
            format: `"mermaid"` (a flowchart, for Markdown) or `"dot"` (Graphviz).

        Returns:
            The text, ending with a newline.

        Raises:
            ConfigError: `format` is neither.
        """
        from rr_actors.observe._sources import LiveSource  # noqa: PLC0415
        from rr_actors.observe._text import render  # noqa: PLC0415

        tree, graph = LiveSource(self._supervisor(), self._observed()).snapshot()
        return render(graph, tree, format)

    def _observed(self) -> Any:
        """What the observer needs of this tree besides the public methods."""
        from rr_actors.observe._sources import TreeAccess  # noqa: PLC0415

        return TreeAccess(
            spec=self._spec,
            cond=self._tree.cond,
            restart_due=self._tree.restart_due,
            running=lambda: self._started and not self._stopped,
            registrars=lambda: list(self._registrars),
        )
