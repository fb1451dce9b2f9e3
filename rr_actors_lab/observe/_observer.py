"""The `Observer` handle: a source, a hub and a server, opened together and closed together.

```
 Supervisor.observe(...) ─► observe_supervisor ─┐                ┌─► LiveSource (threads)
 rr-actors observe --state DIR ─► observe_backups ┤─► Observer ──┼─► Hub
 rr-actors observe --system ... ─► observe_system ┘              └─► Server (uvicorn thread)
```

Across hosts, the source keeps this host's own hub, a `Share` (`_share.py`) publishes it
to the system and a `SystemView` keeps the page's hub with every host's state.

The server's dependencies (Starlette, sse-starlette, uvicorn) are the `observe` extra;
they are imported only here, when an observer opens.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import secrets
import socket
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

from rr_actors._extras import needs
from rr_actors.config import NAME, is_loopback
from rr_actors.errors import ConfigError
from rr_actors_lab.observe._faults import Faults
from rr_actors_lab.observe._hub import Hub
from rr_actors_lab.observe._sources import (
    BackupSource,
    LiveSource,
    Observable,
    TreeAccess,
    event_dict,
)

if TYPE_CHECKING:
    from rr_actors._supervision.supervisor import Supervisor
    from rr_actors._transport.zenoh.net import Services
    from rr_actors_lab.observe._server import Server
    from rr_actors_lab.observe._share import Share
    from rr_actors_lab.observe._system import SystemView

__all__ = [
    "START_TIMEOUT",
    "Observer",
    "graph",
    "graph_of",
    "observe",
    "observe_backups",
    "observe_supervisor",
    "observe_system",
]

logger = logging.getLogger("rr_actors")

START_TIMEOUT = 10.0
"""Seconds the web server may take to start serving."""


def require_extra() -> None:
    """Check that the observer's web server can start, before anything else does.

    Raises:
        MissingExtraError: the `observe` extra (Starlette, sse-starlette, uvicorn) is not
            installed; the one-line message names it and the command that installs it
            (a `ConfigError`).
    """
    with needs("observe", "the observer"):  # (commands name their option: --observe)
        from rr_actors_lab.observe import _server  # noqa: F401, PLC0415 - the observe extra


LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})


def allowed_hosts(host: str) -> frozenset[str]:
    """The names a request's `Host` header may give (its port aside) for an observer on `host`.

    The loopback names, `host` itself and, for a wildcard address (`0.0.0.0`, `::`), this
    machine's host name, its fully qualified name and the addresses they resolve to.
    Anything else is refused: a page of another site whose name resolves to this
    machine (DNS rebinding) cannot read the page, even with `allow_remote`.
    """
    names = set(LOOPBACK_NAMES) | {host.lower().strip("[]")}
    if host in ("0.0.0.0", "::", ""):  # noqa: S104 - recognising the wildcard, not binding it
        for name in {socket.gethostname(), socket.getfqdn()}:
            names.add(name.lower())
            with contextlib.suppress(OSError):
                names.update(str(info[4][0]).lower() for info in socket.getaddrinfo(name, None))
    return frozenset(names)


def _bind(host: str, port: int, *, allow_remote: bool) -> socket.socket:
    """A listening TCP socket on `host:port`, or a `ConfigError` that says why not."""
    if not isinstance(host, str) or not host:
        raise ConfigError(f"host must be a non-empty string, got {host!r}")
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ConfigError(f"port must be an int from 0 to 65535, got {port!r}")
    if not is_loopback(host) and not allow_remote:
        raise ConfigError(
            f"host {host!r} is not a loopback address: the observer would be reachable from "
            "other machines (it shows every catalog, and with allow_faults its buttons kill "
            "managers). Pass allow_remote=True (--allow-remote) to do that on purpose"
        )
    address = "127.0.0.1" if host == "localhost" else host
    family = socket.AF_INET6 if ":" in address else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((address, port))
        sock.listen(64)
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise ConfigError(f"port {port} on {host} is in use: choose another port") from exc
        raise ConfigError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from exc
    return sock


def _adopt(sock: socket.socket, *, allow_remote: bool) -> str:
    """Check a listening socket given to serve on; the address it listens on.

    Raises:
        ConfigError: it is not a listening TCP socket (IPv4 or IPv6), or it listens on
            an address that is not a loopback one and `allow_remote` is false.
    """
    if not isinstance(sock, socket.socket):
        raise ConfigError(f"sock must be a socket.socket, got {sock!r}")
    accepting = getattr(socket, "SO_ACCEPTCONN", None)  # (not on every platform)
    try:
        listening = True if accepting is None else sock.getsockopt(socket.SOL_SOCKET, accepting)
        address = sock.getsockname()
    except OSError as exc:
        raise ConfigError(f"sock cannot be served on: {exc.strerror or exc}") from exc
    if (
        sock.family not in (socket.AF_INET, socket.AF_INET6)
        or sock.type != socket.SOCK_STREAM
        or not listening
    ):
        raise ConfigError(f"sock must be a listening TCP socket (listen() called), got {sock!r}")
    host = str(address[0])
    if not is_loopback(host) and not allow_remote:
        raise ConfigError(
            f"sock listens on {host!r}, not a loopback address: the observer would be "
            "reachable from other machines. Pass allow_remote=True to do that on purpose"
        )
    return host


class _Source(Protocol):
    hub: Hub

    def start(self) -> None: ...
    def close(self, timeout: float = ...) -> None: ...


class _Nothing:
    """The source of a page that shows only other hosts (`observe_system`)."""

    def __init__(self, hub: Hub) -> None:
        self.hub = hub

    def start(self) -> None:
        """Nothing to start."""

    def close(self, timeout: float = 5.0) -> None:
        """Nothing to close."""


class Observer:
    """An open observer page: its `url`, and `close()`.

    Made by [`Supervisor.observe`][rr_actors.Supervisor.observe] (a live tree) or by
    `rr-actors observe --state DIR` (backups); not constructed directly.

    Attributes:
        url: the page's address, with its token (`?token=...`), which every request must
            carry: whoever has the URL sees every catalog (and may use the teaching
            buttons); give it only to them.
        host: the address it listens on.
        port: the port it listens on.
        allow_faults: whether the teaching mode's buttons work (for this host's own
            managers; across hosts, each host decides for its own).
        member: this host's member name when the page shows every host (`None`: this one).
        keep_serving: whether the page outlives the supervisor (showing the final state
            until `close()`).
    """

    def __init__(
        self,
        source: LiveSource | BackupSource | _Source,
        hub: Hub,
        *,
        host: str,
        port: int,
        allow_remote: bool,
        hello: dict[str, Any],
        faults: Faults | None,
        keep_serving: bool = False,
        view: SystemView | None = None,
        share: Share | None = None,
        sock: socket.socket | None = None,
        control: Callable[[dict[str, Any]], dict[str, Any]] | None = None,
    ) -> None:
        require_extra()
        from rr_actors_lab.observe import _server  # noqa: PLC0415 - the observe extra

        self._source = source
        self._hub = hub
        self._faults = faults
        self._view = view
        self._share = share
        self.member = view.member if view is not None else None
        self._lock = threading.Lock()
        self._closed = False
        if sock is None:
            sock = _bind(host, port, allow_remote=allow_remote)
        else:
            try:
                host = _adopt(sock, allow_remote=allow_remote)
            except ConfigError:
                if isinstance(sock, socket.socket):
                    sock.close()  # (it is the observer's once given)
                raise
        self.host = host
        self.port: int = sock.getsockname()[1]
        self.allow_faults = faults is not None
        self.keep_serving = keep_serving
        self._token = secrets.token_urlsafe(18)
        name = f"[{host}]" if ":" in host else host
        self.url = f"http://{name}:{self.port}/?token={self._token}"
        try:
            app = _server.build_app(
                hub,
                hello={**hello, "faults": faults is not None},
                faults=faults,
                remote=None if view is None else view.fault,
                member=self.member,
                fault_events=source.hub,
                token=self._token,
                hosts=allowed_hosts(host),
                cookie=f"rr-observer-{self.port}",
                control=control,
            )
            self._server: Server = _server.Server(app, sock, f"rr-observe-http-{self.port}")
        except BaseException:
            sock.close()
            raise
        source.start()
        if not self._server.start(START_TIMEOUT):
            self.close()
            raise ConfigError(f"the observer's web server did not start within {START_TIMEOUT:g} s")

    @property
    def closed(self) -> bool:
        """Whether it was closed."""
        return self._closed

    def set_clock(self, origin: float, label: str = "mission time") -> None:
        """Show times on the page also as seconds since `origin`, under `label`.

        Args:
            origin: the wall-clock time (`time.time()` seconds) of "0 s".
            label: what that clock is called on the page.
        """
        self._hub.put("clock", {"origin": origin, "label": label})
        if self._hub is not self._source.hub:
            self._source.hub.put("clock", {"origin": origin, "label": label})

    def refresh(self) -> None:
        """Read every catalog now, on the calling thread (a live tree only; errors logged)."""
        if isinstance(self._source, LiveSource) and not self._closed:
            try:
                self._source.snapshot()
            except Exception:
                logger.exception("observer: reading the catalogs failed")

    def source_ended(self) -> None:
        """What it shows will not change any more (its supervisor stopped).

        Without `keep_serving`, the observer closes. With it, the page keeps showing the final
        state until `close()`; across hosts, that state is shared, and on this host's own page,
        before this returns (at most `_share.FLUSH_TIMEOUT` seconds each).
        """
        if not self.keep_serving:
            self.close()
            return
        with self._lock:
            if self._closed:
                return
        self._source.close(5.0)
        if isinstance(self._source, LiveSource):  # its final state: the tree stopped
            try:
                tree, _ = self._source.snapshot()
                self._source.hub.put("tree", tree)
            except Exception:
                logger.exception("observer: reading the final state failed")
        self._source.hub.put("ended", {"at": time.time()})
        if self._share is not None:  # (before the network closes: other hosts see it end)
            self._share.flush()
        if self._view is not None:  # (this host's own final state, on its own page too)
            self._view.flush()

    def close(self, *, timeout: float = 5.0) -> None:
        """Stop serving: open pages show that they are disconnected. Idempotent.

        A manager a hang button stopped gets SIGCONT. Waits for the observer's threads at most
        `timeout` seconds each, on the calling thread.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._source.close(timeout)
        if self._view is not None:
            self._view.close(timeout)
        if self._share is not None:
            self._share.close(timeout)
        self._hub.close()
        self._server.close(timeout)
        if self._faults is not None:
            self._faults.resume_all()

    def __enter__(self) -> Observer:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"<Observer {self.host}:{self.port} {state}>"


def services_of(network: object, *, required: bool) -> Services | None:
    """The Zenoh services of a supervisor's `network`, or `None` if it has none.

    Raises:
        ConfigError: `required` and `network` is not a `ZenohNetwork`.
    """
    services = getattr(network, "services", None)
    if not callable(services):
        if required:
            raise ConfigError(
                "across_hosts=True needs a supervisor whose network is an rr.ZenohNetwork "
                f"(Supervisor(..., network=net)), not {network!r}"
            )
        return None
    made: Services = services()
    return made


def member_name(services: Services) -> str:
    """This host's member name: its certificate's common name; without TLS, the machine's
    host name and this process's pid (two hosts of one machine, such as network
    namespaces, share a host name)."""
    if services.member is not None:
        return services.member
    name = f"{socket.gethostname()}-{os.getpid()}"[-64:].lstrip(".-")
    return name if NAME.fullmatch(name) else f"host-{os.getpid()}"


def observe_supervisor(
    sup: Observable,
    access: TreeAccess,
    *,
    host: str,
    port: int,
    allow_faults: bool,
    allow_remote: bool,
    keep_serving: bool = False,
    across_hosts: bool | None = None,
    sock: socket.socket | None = None,
) -> Observer:
    """Open the live page of a supervision tree (what `Supervisor.observe` does)."""
    services = None
    if across_hosts is not False:
        services = services_of(access.network, required=across_hosts is True)
    require_extra()  # (before anything is shared)
    local = Hub(convert=event_dict)
    source = LiveSource(sup, access, local)
    faults = (
        Faults(sup, access.spec, lambda name: local.get(f"catalog/{name}"))
        if allow_faults
        else None
    )
    hello: dict[str, Any] = {"mode": "live", "title": f"supervisor {sup.name}", "pid": os.getpid()}
    clock = {"origin": time.time(), "label": "since the observer opened"}
    local.put("clock", clock)
    view = share = None
    hub = local
    try:
        if services is not None:
            from rr_actors_lab.observe._share import Share  # noqa: PLC0415
            from rr_actors_lab.observe._system import SystemView  # noqa: PLC0415

            member = member_name(services)
            title = f"supervisor {sup.name}"
            subscribe = getattr(access.network, "subscribe_events", None)
            share = Share(
                local,
                services,
                member,
                host={"title": title, "pid": os.getpid()},
                faults=faults,
                all_events=subscribe is None,
            )
            hub = Hub()
            hub.put("clock", clock)
            view = SystemView(hub, services, member, share, subscribe)
            system = services.keys.prefix.removeprefix("rr/")
            hello.update(
                system=system, member=member, title=f"system {system}: {title} on {member}"
            )
        return Observer(
            source,
            hub,
            host=host,
            port=port,
            allow_remote=allow_remote,
            hello=hello,
            faults=faults,
            keep_serving=keep_serving,
            view=view,
            share=share,
            sock=sock,
        )
    except BaseException:
        for part in (source, view, share, sock):
            if part is not None:
                with contextlib.suppress(Exception):
                    part.close()
        raise


def graph_of(sup: Observable, access: TreeAccess, format: str) -> str:
    """The tree and its dependency graph as text (what `Supervisor.graph` does)."""
    from rr_actors_lab.observe._text import render  # noqa: PLC0415

    tree, graph = LiveSource(sup, access).snapshot()
    return render(graph, tree, format)


def observe(
    sup: Supervisor,
    host: str = "127.0.0.1",
    port: int = 0,
    *,
    allow_faults: bool = False,
    allow_remote: bool = False,
    keep_serving: bool = False,
    across_hosts: bool | None = None,
    sock: socket.socket | None = None,
) -> Observer:
    """Serve a live web page of supervisor `sup`'s tree at the returned observer's `url`.

    The tree, each registrar's catalog, the dependency graph (the TeMoto thesis's
    figure 2.7, live) and a timeline of status notifications. The server runs on a
    thread of its own (uvicorn); the observer closes with the supervisor unless
    `keep_serving`. Every request must carry the `url`'s token (`?token=...`); at
    most 32 pages are open at once. The observer's reference page says more.

    Args:
        sup: the `rr_actors.Supervisor` (started or not; not stopped).
        host: the address to listen on. A loopback address (the default) keeps the
            page on this machine; any other needs `allow_remote=True`.
        port: the port (0: a free one; the `url` says which).
        allow_faults: teaching mode: buttons that SIGKILL or SIGSTOP a process
            manager and send FATAL on a resource (whoever has the URL may use them).
        allow_remote: allow a `host` that other machines can reach (they see every
            catalog; nothing from the browser is ever unpickled).
        keep_serving: after the supervisor stops, keep serving its final state
            until the observer's `close()`.
        across_hosts: share this host's tree with the system's other hosts and show
            theirs (`None`: when its `network` is a `ZenohNetwork`).
        sock: a listening TCP socket to serve on instead of binding `host:port`;
            the observer closes it when it closes, or fails to open.

    Returns:
        The open `Observer` (`url`, `close()`).

    Raises:
        ConfigError: the `observe` extra is not installed, the port is in use,
            `host` (or `sock`) is not on a loopback address without `allow_remote`,
            the supervisor was stopped, `across_hosts=True` without a
            `ZenohNetwork`, or `sock` is not a listening TCP socket.
    """
    from rr_actors._supervision.supervisor import tree_watch  # noqa: PLC0415 - the feed imports none

    watch = tree_watch(sup, observing=True)
    page = observe_supervisor(
        sup,
        watch.access(),
        host=host,
        port=port,
        allow_faults=allow_faults,
        allow_remote=allow_remote,
        keep_serving=keep_serving,
        across_hosts=across_hosts,
        sock=sock,
    )
    watch.opened(page)
    return page


def graph(sup: Supervisor, format: str = "mermaid") -> str:
    """Supervisor `sup`'s tree and the dependency graph across its registrars, as text, now.

    Supervisors are hexagons, a registrar a box holding its resources, each query a
    dashed arrow to the provider's resource (the TeMoto thesis's figure 2.7); a
    manager that is down is drawn without its resources.

    Args:
        sup: the `rr_actors.Supervisor`.
        format: `"mermaid"` (a flowchart, for Markdown) or `"dot"` (Graphviz).

    Returns:
        The text, ending with a newline.

    Raises:
        ConfigError: `format` is neither.
    """
    from rr_actors._supervision.supervisor import tree_watch  # noqa: PLC0415 - as in observe

    return graph_of(sup, tree_watch(sup).access(), format)


def observe_system(
    network: object,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    allow_remote: bool = False,
) -> Observer:
    """Open the page of every host of a system from a process without a tree of its own
    (`rr-actors observe --system`): it shares nothing, only shows.

    Args:
        network: an `rr.ZenohNetwork` this process joins the system with (a member).
        host: the address to listen on (a loopback address unless `allow_remote`).
        port: the port (0: a free one).
        allow_remote: allow a `host` that other machines can reach.

    Returns:
        The open observer; `close()` it (the network is the caller's to close).

    Raises:
        ConfigError: `network` is not a `ZenohNetwork`, the port is in use, the host is
            not a loopback address without `allow_remote`, or the `observe` extra is missing.
    """
    services = services_of(network, required=True)
    assert services is not None
    require_extra()
    from rr_actors_lab.observe._system import SystemView  # noqa: PLC0415

    hub = Hub()
    hub.put("clock", {"origin": time.time(), "label": "since the observer opened"})
    subscribe = getattr(network, "subscribe_events", None)
    view = SystemView(hub, services, services.member, None, subscribe)
    system = services.keys.prefix.removeprefix("rr/")
    hello = {
        "mode": "live",
        "title": f"system {system}",
        "pid": os.getpid(),
        "system": system,
        "member": services.member,
    }
    try:
        return Observer(
            _Nothing(hub),
            hub,
            host=host,
            port=port,
            allow_remote=allow_remote,
            hello=hello,
            faults=None,
            view=view,
        )
    except BaseException:
        view.close()
        raise


def observe_backups(
    state_dir: str | os.PathLike[str],
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    allow_remote: bool = False,
) -> Observer:
    """Open the page of a state directory's backups: no live system, nothing written; it follows
    the files every `POLL_INTERVAL` seconds.

    Args:
        state_dir: a supervisor's `state_dir` (its `<name>.db` files).
        host: the address to listen on (a loopback address unless `allow_remote`).
        port: the port (0: a free one).
        allow_remote: allow a `host` that other machines can reach.

    Returns:
        The open observer; `close()` it.

    Raises:
        ConfigError: the directory does not exist or holds no backup; the port is in use;
            the host is not a loopback address without `allow_remote`; the `observe` extra
            is not installed.
        CatalogCorruptError: a backup cannot be read (the error names the file).
    """
    hub = Hub()
    source = BackupSource(state_dir, hub)
    hello = {"mode": "backups", "title": f"backups in {state_dir}", "pid": os.getpid()}
    return Observer(
        source, hub, host=host, port=port, allow_remote=allow_remote, hello=hello, faults=None
    )
