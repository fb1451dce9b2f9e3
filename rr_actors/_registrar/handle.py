"""The registrar's handle: what user code holds, callable from any thread.

Each method sends the registrar actor one message of `messages.py` (`RegisterServer`,
`Release`, ...: data that carries its reply) and waits for the answer at most `timeout`
seconds; `call` runs the call protocol on the caller's own thread (`calls.py`). The
handle never touches the catalog itself. Starting the actor, before there is a handle,
is `starting.py`'s.

The rest of the package reaches the actor only through the handle's small internal
surface (`_tell`, `_ask`, `_wait_stopped`, `_crash`, `_ping`, `_actor_ref`): nothing
else holds the actor's ref or builds a message to it from a closure.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any, TypeVar

import pykka

from rr_actors import events
from rr_actors._core.bus import DEFAULT_MAXSIZE, Publisher, Subscription
from rr_actors._core.directory import DIRECTORY, Reply
from rr_actors._core.exit import REGISTRARS, stop_at_exit
from rr_actors._core.ids import new_id
from rr_actors._core.loops import OnLoop, is_coroutine_function, on_process_loop, process_loop
from rr_actors._core.replies import FutureReply, Steps, asked, run_steps
from rr_actors._registrar.actor import Launched, RegistrarActor, launch
from rr_actors._registrar.aio import AsyncSurface
from rr_actors._registrar.calls import Calls
from rr_actors._registrar.consumer import ClientActor
from rr_actors._registrar.life import CatalogView, Network, check_network, serve_on
from rr_actors._registrar.messages import (
    LOADING,
    Asked,
    Crash,
    FetchVia,
    ListClientQueries,
    ListServerQueries,
    OpenClient,
    Ping,
    Ready,
    RegisterServer,
    Release,
    Save,
    SendStatus,
    SetStatusCallback,
    SettleInDoubt,
    Snapshot,
    Stop,
    UnregisterServer,
    UpdateResponse,
    check_picklable,
)
from rr_actors._registrar.protocol import LoadCallback, UnloadCallback
from rr_actors._registrar.state import Probes
from rr_actors._types import Query, Status, StatusCallback
from rr_actors.config import RegistrarConfig, check_seconds
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    RegistrarStoppedError,
)

__all__ = [
    "STOP_WAITS_FOR_UNLOADS",
    "RegistrarFacts",
    "ResourceRegistrar",
    "snapshot",
    "start_registrar",
]

T = TypeVar("T")

STOP_WAITS_FOR_UNLOADS = 0.5
"""The share of `stop()`'s timeout it waits for the unloads under way (the rest is left
to write the backup and stop the servers): 5 s with the default `call_timeout`."""


@dataclasses.dataclass(frozen=True)
class RegistrarFacts:
    """What a registrar handle knows without asking its actor; every handle holds one.

    Attributes:
        config: the configuration it was started with.
        restored: whether the catalog was restored from an existing backup at start.
        in_doubt: loads (or unloads) a crash cut short in the last run, found at restore.
    """

    config: RegistrarConfig
    restored: bool = False
    in_doubt: tuple[Query, ...] = ()


class ResourceRegistrar(AsyncSurface):
    """A manager's resource registrar (thesis 4.3.1, `RrBase`).

    Start one with [`ResourceRegistrar.start`][rr_actors.ResourceRegistrar.start]. Its
    methods may be called from any thread, including from inside callbacks; each sends a
    message to the registrar actor and waits for the answer at most `timeout` seconds
    (default: the config's `call_timeout`). Each has an awaitable twin for event loops
    (`acall`, `aunload`, ..., `watch`; the prefix as Django's async ORM has it): the
    same operation, errors and timeout, with no thread held while it waits.
    """

    def __init__(self, launched: Launched) -> None:
        """Wrap a registrar `launch` started (use `ResourceRegistrar.start`)."""
        config = launched.config
        ref = launched.ref
        self._ref = ref
        self._config = config
        self._facts = RegistrarFacts(config, launched.restored, launched.in_doubt)
        self._in_doubt_texts = launched.in_doubt_texts
        self._clients = launched.clients  # one cache: the actor starts, the handle looks up
        self._died = launched.died  # set when a crash of the actor was fully handled
        self._ended = launched.ended  # set when the actor handed on its last message
        self._due = launched.due  # shared with the actor
        self._probes: Probes | None = None  # `rr_actors.testing.intercept`
        self._events = launched.published
        self._calls = Calls(
            ref,
            config.name,
            self._due,
            commit_first=config.save_on_modify and config.backup_path is not None,
            stored=config.backup_path is not None,
            probes=lambda: self._probes,
            listened=lambda: launched.published.active,
        )

    @property
    def name(self) -> str:
        """The registrar's name."""
        return self._facts.config.name

    @property
    def config(self) -> RegistrarConfig:
        """The configuration it was started with."""
        return self._facts.config

    @property
    def restored(self) -> bool:
        """Whether the catalog was restored from an existing backup at start."""
        return self._facts.restored

    @property
    def in_doubt(self) -> tuple[Query, ...]:
        """Loads (or unloads) a crash cut short in the last run, found at restore (rule 16).

        Each is a `Query` whose `id` is the resource id, whose `request` is what the load
        was for and whose `response` is `None` for a load that never finished. They are
        no longer in the catalog and their dependencies were released; the manager
        decides whether something its callback started must be cleaned up.

        The backup keeps them until the manager's `setup` has returned (or the manager
        called `settle_in_doubt`): if the manager dies during `setup`, the next restore
        reports the same entries again. A registrar started without `setup` forgets
        them at once.
        """
        return self._facts.in_doubt

    def settle_in_doubt(self, query_id: str | None = None, *, timeout: float | None = None) -> None:
        """Say that in-doubt entry `query_id` (default: every one) is handled (rule 16).

        Its row leaves the backup, so a restart no longer reports it in `in_doubt`.
        The registrar does this itself once `setup` returns; call it from `setup` to
        settle each entry as soon as what its load started was cleaned up (a long
        `setup` that dies later then offers only the others again). Settling an entry
        again is a no-op.

        Args:
            query_id: the `id` of one of `in_doubt`'s queries, or `None` for all.
            timeout: seconds to wait for the registrar.

        Raises:
            UnknownQueryError: `query_id` is not the id of an entry of `in_doubt`.
            CatalogWriteError: the backup could not be written (a full disk): the entry
                is settled here, but a restart before the next write that succeeds
                offers it again.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        self._ask(SettleInDoubt(query_id, FutureReply()), timeout, f"settle_in_doubt({query_id!r})")

    @classmethod
    def start(
        cls,
        config: RegistrarConfig | str,
        *,
        setup: Callable[[ResourceRegistrar], object] | None = None,
        network: Network | None = None,
    ) -> ResourceRegistrar:
        """Start a registrar, restoring its catalog first if its backup exists.

        Args:
            config: a `RegistrarConfig`, or just a name (all other fields default).
            setup: `setup(registrar)`, run on the calling thread after the catalog was
                restored and before the registrar serves other registrars: loads that
                arrive meanwhile for servers it has not registered yet wait for it (a
                manager's start-up). If it raises, the registrar is stopped and the error
                propagates. The `in_doubt` entries stay in the backup until it returned
                (`settle_in_doubt`).
            network: a carrier (any `Transport`: an AF_UNIX `System`, a `ZenohNetwork`)
                to serve it on, after `setup`, from the calling thread: the registrars
                of the system's other processes (and hosts) reach it by name from then
                on, and it reaches theirs. It stops being served when it stops or dies.
                `None`: reachable from this process only (unless a system this process
                serves on reaches it otherwise).

        Returns:
            The handle of the running registrar.

        Raises:
            DuplicateNameError: a registrar with this name is already running here, or
                (with `network`) another process of the system serves that name; it was
                stopped again.
            CatalogCorruptError: the backup exists but cannot be read (it is left as is).
            ConfigError: the configuration, or its backup path, is invalid; `network` is
                not a carrier, or cannot serve it; or this process was forked from one
                whose state a forked child cannot use (it had opened a Zenoh session): the
                message says to start the process with the `spawn` or `forkserver` method.
            RegistrarStoppedError: this process left `network`'s system (it was closed).

        Fork: a process forked (`os.fork`, `multiprocessing`'s "fork" method) from one
        that runs rr_actors may start registrars of its own and call, on the AF_UNIX
        systems its parent joined (the same `System` object, or its address's
        `attach()`): at the fork the child lets go of its parent's listeners,
        connections and threads. Its parent's registrars are not the child's: a handle
        of one used in the child raises `RegistrarUnavailableError` at once (reach that
        registrar by name from a registrar of the child's instead). A child of a process
        that had opened a Zenoh session is refused (`ConfigError`, above): use `spawn`
        or `forkserver` there.
        """
        check_network(network)
        registrar = start_registrar(config, setup=setup)
        if network is not None:
            serve_on(network, registrar)
        return registrar

    # -- properties -------------------------------------------------------------------

    def is_alive(self) -> bool:
        """Whether the registrar actor is running."""
        return self._ref.is_alive()

    def subscribe(
        self,
        callback: Callable[[events.Event], object],
        *,
        maxsize: int = DEFAULT_MAXSIZE,
    ) -> Subscription[events.Event]:
        """Call `callback(event)` for every event of this registrar from now on.

        Events are the frozen dataclasses of `rr_actors.events` (a load, a failed load,
        an unload, a consumer added or released, a status sent or delivered here, an
        in-doubt query at restore). The callback runs on a subscriber thread of its own,
        never in the registrar's mailbox, one event at a time in the order they happened;
        a slow callback never slows the registrar: past `maxsize` queued events, new ones
        are dropped, counted (`Subscription.dropped`) and reported by an `EventsDropped`.

        Args:
            callback: `callback(event)`; what it raises is logged.
            maxsize: events queued for it before new ones are dropped.

        Returns:
            The subscription; `close()` it (or use it in a `with` block).

        Raises:
            ConfigError: `callback` is not callable, or `maxsize` not a positive int.
        """
        return self._events.subscribe(callback, maxsize=maxsize, name=f"{self.name}-events")

    # -- servers ----------------------------------------------------------------------

    def register_server(
        self,
        name: str,
        *,
        load: LoadCallback,
        unload: UnloadCallback,
        on_status: StatusCallback | None = None,
        timeout: float | None = None,
        label: Callable[[Any], str] | None = None,
    ) -> None:
        """Register a resource server `"<registrar>/<name>"`.

        Args:
            name: server name, unique on this registrar.
            load: `load(request) -> response`; runs on a worker thread of this process.
            unload: `unload(request, response) -> None`; runs on a worker thread, after the
                resource's dependencies were released.
            on_status: `on_status(query, update)`, run once on a worker thread when a status
                about one of this server's resources is sent or passes through.
            timeout: seconds to wait for the registrar.
            label: `label(request) -> str`, a short name for a resource that the observer
                shows (`lidar2` rather than the whole request). It runs once per resource,
                when its load starts, on a worker thread of this process, bounded by
                `RegistrarConfig.compare_timeout`; the text is kept in the catalog (and
                its backup), cut to 40 characters. If it raises (anything, `SystemExit`
                included), returns something else than a `str` or overruns the bound,
                the label reads `<label failed: ...>`; the load is not affected, but a
                load that ends first waits for its label (at most that bound) while
                someone listens to events, so that its `ResourceLoaded.label` is this
                one. Without it, the observer shows what tells the server's requests
                apart.

        Raises:
            ConfigError: a callback is not callable or the name is invalid.
            DuplicateNameError: a server with this name exists on this registrar.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        _blocking(self._register_server_steps(name, load, unload, on_status, timeout, label))

    def _register_server_steps(
        self,
        name: str,
        load: LoadCallback,
        unload: UnloadCallback,
        on_status: StatusCallback | None,
        timeout: float | None,
        label: Callable[[Any], str] | None,
    ) -> Steps[None]:
        if not isinstance(name, str) or not name or "/" in name:
            raise ConfigError(f"server name must be a non-empty string without '/', got {name!r}")
        callbacks = (("load", load), ("unload", unload), ("on_status", on_status), ("label", label))
        for arg, fn in callbacks:
            if fn is not None and not callable(fn):
                raise ConfigError(f"{arg} must be callable, got {fn!r}")
        if label is not None and is_coroutine_function(label):
            raise ConfigError(
                f"label must be a plain function (it runs once, briefly), got {label!r}"
            )
        if on_status is not None and is_coroutine_function(on_status):
            on_status = OnLoop(on_status, process_loop())  # a server's: the process's loop
        return self._asking(
            RegisterServer(name, load, unload, on_status, label, FutureReply()),
            timeout,
            f"register_server({name!r})",
        )

    def unregister_server(self, name: str, *, timeout: float | None = None) -> None:
        """Remove a server: send `FATAL` to its consumers and unload all it serves (rule 12).

        Raises:
            UnknownServerError: no such server here.
            CallTimeoutError: not finished within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        _blocking(self._unregister_server_steps(name, timeout))

    def _unregister_server_steps(self, name: str, timeout: float | None) -> Steps[None]:
        return self._asking(
            UnregisterServer(name, FutureReply()), timeout, f"unregister_server({name!r})"
        )

    # -- consumer API -----------------------------------------------------------------

    def call(
        self,
        target_rr: str,
        server: str,
        request: Any,
        *,
        on_status: StatusCallback | None = None,
        timeout: float | None = None,
        query_id: str | None = None,
    ) -> Query:
        """Ask `target_rr/server` for the resource `request` describes (rules 1-6, 17).

        The provider runs `load(request)` unless an equal (`==`) request is loaded or
        loading there; either way this call becomes one more consumer with its own id.
        Called from inside a `load` callback of this registrar, the query is recorded as
        a dependency of the resource being loaded.

        Args:
            target_rr: name of the provider registrar (this one's own name works too).
            server: server name on it.
            request: any value; equal requests mean the same resource. Between
                registrars of one process it is passed, not copied (as pykka passes
                messages): do not change it after the call, or the provider's catalog
                holds the changed value and may no longer match equal requests to it.
            on_status: client status callback `on_status(query, update)`, run on a worker
                thread of this registrar's process.
            timeout: seconds to wait for the answer.
            query_id: the id to use (default: a fresh UUID4). Retrying with the same id is
                idempotent: it never loads twice nor adds a second consumer.

        Returns:
            The `Query`, with the provider's `response` (in one process, the very object
            `load` returned, shared by every consumer: treat it as read-only).

        Raises:
            ResourceLoadError: `load` raised here or further down; `stack` says where.
            DependencyCycleError: the load would wait for itself further up its chain.
            UnknownServerError: no such registrar or server.
            CallTimeoutError: no answer in time; the query id is released if it loads later.
            RegistrarUnavailableError: the provider died (it may have executed the load).
            RegistrarStoppedError: this registrar or the provider was stopped.
            ConfigError: `target_rr` or `server` is not a str, `query_id` not a
                non-empty str, `on_status` not callable; or the request, or the response,
                cannot be pickled where it must be: across processes, or into this
                registrar's backup (its client record); the provider then holds nothing.
        """
        return _blocking(self._call_steps(target_rr, server, request, on_status, timeout, query_id))

    def _call_steps(
        self,
        target_rr: str,
        server: str,
        request: Any,
        on_status: StatusCallback | None,
        timeout: float | None,
        query_id: str | None,
    ) -> Steps[Query]:
        if on_status is not None and not callable(on_status):
            raise ConfigError(f"on_status must be callable, got {on_status!r}")
        _check_names(target_rr=target_rr, server=server)
        if query_id is not None and not (isinstance(query_id, str) and query_id):
            raise ConfigError(
                f"query_id must be a non-empty str (or None: a fresh id), got {query_id!r}"
            )
        if on_status is not None and is_coroutine_function(on_status):
            on_status = OnLoop.bind(on_status)  # the loop it was registered from
        limit = self._timeout(timeout)
        deadline = time.monotonic() + limit
        context = LOADING.get()
        parent: str | None = None
        chain: tuple[str, ...] = ()
        if context is not None:
            chain = context.chain
            if context.registrar == self.name:
                parent = context.resource_id
        if self._config.backup_path is not None:  # its client record is stored
            check_picklable(request, f"the request of a call to '{target_rr}/{server}'")
        steps = self._calls.steps(
            query_id or new_id(),
            target_rr,
            server,
            request,
            parent,
            chain,
            on_status,
            limit,
            deadline,
        )
        client = self._clients.get(target_rr, server)
        if client is None or not client.is_alive():  # (it exists from the first call)
            return _after(self._client_steps(target_rr, server, limit), steps)
        return steps

    def unload(self, query_id: str, *, timeout: float | None = None) -> None:
        """Release one consumer id obtained from `call` (rules 7-8).

        The provider's `unload` callback runs when the last consumer id of the resource is
        released, after that resource's own dependencies were released; this returns
        when that is done.

        Raises:
            UnknownQueryError: the id is unknown here or already released (nothing changes).
            CallTimeoutError: not finished within `timeout` seconds.
            RegistrarUnavailableError: the provider died (or could not be reached) before
                it answered: it may or may not have released the id. The release is
                done all the same: this registrar no longer holds the id (a second
                `unload` raises `UnknownQueryError`), the provider releases it when it
                reconciles with this registrar after its restart (its `unload` callback
                runs once in all), and nobody gets `FATAL` for it (rule 20).
            RegistrarStoppedError: this registrar was stopped; or the provider was (the
                id is released as for `RegistrarUnavailableError`, at its next start).
        """
        _blocking(self._unload_steps(query_id, timeout))

    def _unload_steps(self, query_id: str, timeout: float | None) -> Steps[None]:
        return self._asking(Release(query_id, FutureReply()), timeout, f"unload({query_id!r})")

    def send_status(
        self, query_id: str, status: Status, message: str = "", *, timeout: float | None = None
    ) -> None:
        """Tell every consumer of the resource behind `query_id` about its status (rule 9).

        This server's `on_status` runs once; each consumer's status callback runs with its
        own query id; the status climbs every dependency path to the top consumers.
        Returns once every callback on the way has run.

        Args:
            query_id: any consumer id of a resource this registrar serves.
            status: the status code.
            message: free text.
            timeout: seconds to wait for delivery along the whole path.

        Raises:
            UnknownQueryError: `query_id` is not a consumer id of a resource served here.
            ConfigError: `status` is not a `Status`, `query_id` or `message` not a str.
            MessageTooLargeError: the status is over the `max_message_bytes` of a
                consumer registrar in another process (named): that one did not hear it,
                the others did (a `FATAL` still marks the resource, rule 1).
            CallTimeoutError: not delivered everywhere within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        _blocking(self._send_status_steps(query_id, status, message, timeout))

    def _send_status_steps(
        self, query_id: str, status: Status, message: str, timeout: float | None
    ) -> Steps[None]:
        if not isinstance(status, Status):
            raise ConfigError(f"status must be an rr_actors.Status, got {status!r}")
        return self._asking(
            SendStatus(query_id, status, message, FutureReply()),
            timeout,
            f"send_status({query_id!r})",
        )

    def server_queries(self, server: str, *, timeout: float | None = None) -> list[Query]:
        """Every consumer query of this registrar's `server`, each id once (rule 10).

        Raises:
            UnknownServerError: no such server here.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        return _blocking(self._server_queries_steps(server, timeout))

    def _server_queries_steps(self, server: str, timeout: float | None) -> Steps[list[Query]]:
        return self._asking(
            ListServerQueries(server, FutureReply()), timeout, f"server_queries({server!r})"
        )

    def fetch_queries(
        self, target_rr: str, server: str, *, timeout: float | None = None
    ) -> list[Query]:
        """The queries this registrar holds at `target_rr/server`, as the provider has them.

        Used after a restart to learn what this registrar had asked for (thesis 4.2.5).

        Raises:
            UnknownServerError: no such registrar or server.
            ConfigError: `target_rr` or `server` is not a str.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarUnavailableError: the provider died.
        """
        return _blocking(self._fetch_queries_steps(target_rr, server, timeout))

    def _fetch_queries_steps(
        self, target_rr: str, server: str, timeout: float | None
    ) -> Steps[list[Query]]:
        _check_names(target_rr=target_rr, server=server)
        limit = self._timeout(timeout)
        deadline = time.monotonic() + limit
        reply = FutureReply()
        client = yield from self._client_steps(target_rr, server, limit)
        client.tell(FetchVia(server, reply))
        result: list[Query] = yield from asked(
            reply.future, deadline, limit, f"fetch_queries({target_rr!r})"
        )
        return result

    def client_queries(self, *, timeout: float | None = None) -> list[Query]:
        """Every query this registrar holds at servers (its own included), oldest first.

        Raises:
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        return _blocking(self._client_queries_steps(timeout))

    def _client_queries_steps(self, timeout: float | None) -> Steps[list[Query]]:
        return self._asking(ListClientQueries(FutureReply()), timeout, "client_queries()")

    def set_status_callback(
        self, query_id: str, callback: StatusCallback, *, timeout: float | None = None
    ) -> None:
        """Attach (or replace) the client status callback of a query this registrar holds.

        Status callbacks are code, so they are not in the backup: re-attach them after a
        restart (rule 11).

        Raises:
            UnknownQueryError: this registrar holds no such query.
            ConfigError: `callback` is not callable.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        _blocking(self._set_status_callback_steps(query_id, callback, timeout))

    def _set_status_callback_steps(
        self, query_id: str, callback: StatusCallback, timeout: float | None
    ) -> Steps[None]:
        if not callable(callback):
            raise ConfigError(f"callback must be callable, got {callback!r}")
        if is_coroutine_function(callback):
            callback = OnLoop.bind(callback)  # the loop it was registered from
        return self._asking(
            SetStatusCallback(query_id, callback, FutureReply()),
            timeout,
            f"set_status_callback({query_id!r})",
        )

    def update_response(
        self, query_id: str, response: Any, *, timeout: float | None = None
    ) -> None:
        """Replace the stored response of the resource behind `query_id` (asynchronous loads).

        Like TeMoto's catalog response update (thesis 4.3.2). Returns once every
        consumer's client record holds the new response too (a consumer that cannot be
        reached is logged and skipped).

        Args:
            query_id: any consumer id of a resource this registrar serves.
            response: the new response (it must pickle when the catalog has a backup).
            timeout: seconds to wait for the update to reach every consumer.

        Raises:
            UnknownQueryError: `query_id` is not a consumer id of a resource served here.
            MessageTooLargeError: the response is over the `max_message_bytes` of a
                consumer registrar in another process (named): its client record keeps
                the old response; this registrar's catalog and the others have the new.
            CallTimeoutError: not delivered within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        _blocking(self._update_response_steps(query_id, response, timeout))

    def _update_response_steps(
        self, query_id: str, response: Any, timeout: float | None
    ) -> Steps[None]:
        return self._asking(
            UpdateResponse(query_id, response, FutureReply()),
            timeout,
            f"update_response({query_id!r})",
        )

    def save_catalog(self, *, timeout: float | None = None) -> None:
        """Write every pending change of the catalog to the backup now (no-op without one).

        Raises:
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        _blocking(self._save_catalog_steps(timeout))

    def _save_catalog_steps(self, timeout: float | None) -> Steps[None]:
        return self._asking(Save(FutureReply()), timeout, "save_catalog()")

    def stop(self, *, timeout: float | None = None) -> None:
        """Stop the registrar (rule 12).

        Unloads everything it holds as a consumer (newest first), waits for the unloads of
        its own resources that are under way (their `unload` callbacks running, on worker
        threads) until `STOP_WAITS_FOR_UNLOADS` of `timeout` has passed, then stops its servers
        and clients. An unload still under way then is cut short: it stops anyway and
        publishes `events.UnloadCutShort`; that resource stays in the backup as unloading
        (in doubt at the next start, rule 16). What its servers serve stays in the
        catalog for a restart. With `erase_on_destruct` the backup is removed. Stopping a
        stopped registrar is a no-op.

        Args:
            timeout: seconds the whole stop may take (`None`: the registrar's
                `call_timeout`).

        Raises:
            CallTimeoutError: not finished within `timeout` seconds.
            RegistrarUnavailableError: the registrar died while it stopped.
        """
        _blocking(self._stop_steps(timeout))

    def _stop_steps(self, timeout: float | None) -> Steps[None]:
        if not self._ref.is_alive():
            return
        limit = self._timeout(timeout)
        deadline = time.monotonic() + limit
        try:
            until = deadline - limit * (1.0 - STOP_WAITS_FOR_UNLOADS)
            yield from self._asking(Stop(FutureReply(), until), limit, "stop()")
        except RegistrarStoppedError:
            return
        # Stop ended the actor; what reached its mailbox meanwhile (an answer to give
        # back, a notice to acknowledge) is handled once its thread has handed it on.
        if not (yield self._ended, deadline):
            raise CallTimeoutError(f"stop() of {self.name!r} timed out after {limit:g} s")

    def __enter__(self) -> ResourceRegistrar:
        return self

    def __exit__(self, *_: object) -> None:
        self.stop()

    def __repr__(self) -> str:
        state = "running" if self._ref.is_alive() else "stopped"
        return f"<ResourceRegistrar {self.name!r} {state}>"

    # -- plumbing ---------------------------------------------------------------------

    def _timeout(self, timeout: float | None) -> float:
        if timeout is None:
            return self._config.call_timeout
        check_seconds("timeout", timeout)
        return float(timeout)

    # -- the internal surface: how the package reaches the actor ----------------------

    def _tell(self, message: Any) -> bool:
        """Send the actor `message` without waiting; whether the actor was running."""
        try:
            self._ref.tell(message)
        except pykka.ActorDeadError:
            return False
        return True

    def _ask(self, message: Asked, timeout: float | None, what: str) -> Any:
        """Send the actor `message` and wait at most `timeout` seconds for its answer.

        Raises:
            CallTimeoutError: no answer in time (`what` names the operation).
            RegistrarStoppedError, RegistrarUnavailableError: it was stopped, or it died.
            RrError: the error the actor answered with.
        """
        return _blocking(self._asking(message, timeout, what))

    def _asking(self, message: Asked, timeout: float | None, what: str) -> Steps[Any]:
        """`_ask`'s steps: send `message`, wait for its answer (`replies.Steps`)."""
        limit = self._timeout(timeout)
        if not self._tell(message):
            raise DIRECTORY.gone_error(self.name) from None
        future = message.reply.future
        if not (yield future, time.monotonic() + limit):
            raise CallTimeoutError(f"{what} timed out after {limit:g} s")
        return future.get()

    def _wait_stopped(self, timeout: float | None = None) -> bool:
        """Block until the actor's thread ended (stopped or died); whether it did."""
        return self._ref.actor_stopped.wait(timeout)

    def _crash(self) -> None:
        """Make the actor die as if a bug hit it (`testing.crash`, a forced stop)."""
        self._ref.tell(Crash())

    def _ping(self, reply: Reply) -> None:
        """Ask the actor to answer `reply` (`None`) once it gets to it (a heartbeat)."""
        self._tell(Ping(reply))

    def _actor_ref(self) -> pykka.ActorRef[RegistrarActor]:
        """The actor's pykka ref (`rr_actors.testing.actor_ref` gives it to tests)."""
        return self._ref

    def _client_steps(
        self, target_rr: str, server: str, timeout: float
    ) -> Steps[pykka.ActorRef[ClientActor]]:
        """The client actor for `target_rr/server`, asked of the actor on first use."""
        client = self._clients.get(target_rr, server)
        if client is None or not client.is_alive():
            started: pykka.ActorRef[ClientActor] = yield from self._asking(
                OpenClient(target_rr, server, FutureReply()), timeout, "starting a client"
            )
            return started
        return client


def start_registrar(
    config: RegistrarConfig | str,
    *,
    setup: Callable[[ResourceRegistrar], object] | None = None,
    upstream: Publisher[events.Event] | None = None,
    hold_in_doubt: bool = False,
) -> ResourceRegistrar:
    """`ResourceRegistrar.start`, with its events also relayed to `upstream` from the first.

    A supervisor passes its tree's publisher, so the events of a restore (`InDoubt`)
    reach the tree's subscribers too. With `hold_in_doubt` the in-doubt entries stay in
    the backup until the caller settles them (`settle_in_doubt`: a manager process runs
    its `setup` itself); with `setup`, they do until `setup` returned.
    """
    launched = launch(
        config,
        setting_up=setup is not None,
        upstream=upstream,
        hold_in_doubt=hold_in_doubt or setup is not None,
    )
    handle = ResourceRegistrar(launched)
    stop_at_exit(
        REGISTRARS,
        f"registrar {handle.name!r}",
        handle.is_alive,
        lambda timeout: handle.stop(timeout=timeout),
    )
    if setup is not None:
        try:
            setup(handle)
        except BaseException:
            handle.stop()  # (what was in doubt stays in doubt: no setup saw it through)
            raise
        try:
            handle.settle_in_doubt()
            handle._ask(Ready(FutureReply()), None, "ready")
        except BaseException:
            handle.stop()  # (not left running when its start failed)
            raise
    return handle


def snapshot(registrar: ResourceRegistrar, *, timeout: float, check: bool) -> CatalogView:
    """A consistent copy of `registrar`'s catalog rows and servers, made on its actor thread.

    For `rr_actors.testing.catalog_snapshot` (with `check`: the catalog's invariants are
    checked first) and the observer (without). Runs on the caller's thread, in the
    registrar's process; the actor is held for the copy only.

    Raises:
        AssertionError: with `check`, an index of the catalog disagrees with its rows.
        CallTimeoutError: no answer within `timeout` seconds.
        RegistrarStoppedError, RegistrarUnavailableError: it was stopped, or it died.
    """
    view: CatalogView = registrar._ask(
        Snapshot(check, FutureReply()),
        timeout,
        "catalog_snapshot()" if check else "a snapshot of the catalog",
    )
    return dataclasses.replace(view, in_doubt=registrar._in_doubt_texts)


def _after(first: Steps[Any], then: Steps[T]) -> Steps[T]:
    """The steps of `first`, then those of `then` (its result)."""
    yield from first
    return (yield from then)


def _blocking(steps: Steps[T]) -> T:
    """Run an operation's `steps` on the calling thread (`replies.run_steps`).

    Raises:
        ConfigError: the calling thread is the process's own event loop (a coroutine
            `load`, `unload` or status callback runs there): blocking it would stall
            every coroutine callback of the process, and a call to a coroutine server
            would wait for itself; await the operation's async twin instead.
    """
    if on_process_loop():
        steps.close()
        raise ConfigError(
            "a blocking registrar method was called on rr_actors' event loop (from a "
            "coroutine load, unload or status callback): await its async twin instead "
            "(acall, aunload, asend_status, ...)"
        )
    return run_steps(steps)


def _check_names(**names: object) -> None:
    """`ConfigError` naming the first argument that is not a str (a registrar's or a
    server's name): refused here, before anything is sent or recorded."""
    for field, value in names.items():
        if not isinstance(value, str):
            raise ConfigError(f"{field} must be a name (a str), got {value!r}")
