"""A handle on a registrar that lives in a manager process of a system.

`RemoteRegistrar` implements the same `Registrar` protocol as `ResourceRegistrar`: each
method runs the registrar's own method in the registrar's process over the system's
carrier (`Transport.run`, any carrier) and returns its result or re-raises its error. Tests run
one body over both placements with it (`rr_actors.testing` re-exports it).

Its awaitable twins (`acall`, ...: `_registrar/aio.py`, the same for both handles) run
the operation's steps (`_forwarding`): in the registrar's own process its handle's
steps, awaited on the loop; from another process one `Run` of those steps there, whose
answer wakes the loop (no thread here waits for it). An awaited `acall` that is
cancelled, or times out here, gives back what the call there still gets (its id is
released there), as a withdrawn call does.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import os
import signal
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, cast

import cloudpickle

from rr_actors._core.directory import DIRECTORY
from rr_actors._core.replies import Steps, on_own_thread, run_steps
from rr_actors._process.manager import ManagerExit, ManagerProcess
from rr_actors._registrar.aio import AsyncSurface, StatusWatch
from rr_actors._registrar.handle import RegistrarFacts, ResourceRegistrar
from rr_actors._registrar.life import gone_for_good
from rr_actors._registrar.messages import LOADING, LoadContext
from rr_actors._registrar.protocol import LoadCallback, UnloadCallback
from rr_actors._transport.base import Address, Transport
from rr_actors._transport.messenger import Remote
from rr_actors._types import Query, Status, StatusCallback
from rr_actors.config import RegistrarConfig
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
)

__all__ = ["FORWARD_MARGIN", "RemoteRegistrar"]

FORWARD_MARGIN = 10.0
"""Seconds a forwarded call may take beyond its own `timeout` (transport and scheduling)."""


class RemoteRegistrar(AsyncSurface):
    """A handle on a registrar that lives in a manager process of a system.

    It has the methods and properties of a `ResourceRegistrar`, with the same arguments,
    results and errors: each method runs the registrar's own method in the registrar's
    process (over the system's authenticated channel) and returns its result or re-raises
    its error (rr_actors errors pickle). Arguments, callbacks and results are cloudpickled,
    so callbacks may be closures; they run in the registrar's process, on the threads a
    local registrar would use. The handle itself pickles: a callback that captured it and
    runs in the registrar's own process calls the registrar directly on its own thread (so
    a call inside a `load` callback is still recorded as a dependency), and from any
    other process of the system it forwards again.

    Start one with [`start`][rr_actors.testing.RemoteRegistrar.start] (the *owner*
    handle, which owns the manager process and can [`kill`][rr_actors.testing.RemoteRegistrar.kill]
    it), or reach an existing registrar of a system (a supervised manager, say) with the
    constructor. When an owned manager process dies without being stopped, the owner tells
    every registrar of the system that this consumer is gone (death watch), as a
    supervisor does for a child it will not restart (unless a restart is expected:
    `rr_actors.testing.expect_restart`): its consumers' ids are released and the ids
    held there get `FATAL` at their consumers (rule 19).
    """

    def __init__(
        self,
        config: RegistrarConfig | str,
        address: Address,
        *,
        restored: bool = False,
        in_doubt: tuple[Query, ...] = (),
    ) -> None:
        """Make a handle on the running registrar `config.name` of the system at `address`.

        Args:
            config: the registrar's configuration (its `call_timeout` is the default
                timeout of this handle's methods), or just its name.
            address: the system's address (any carrier's `Address`; it pickles).
            restored: what `restored` reports (the owner handle learns it at start).
            in_doubt: what `in_doubt` reports (likewise).
        """
        self._config = RegistrarConfig(name=config) if isinstance(config, str) else config
        self._address = address
        self._facts = RegistrarFacts(self._config, restored, in_doubt)
        self._process: ManagerProcess | None = None
        self._stopping = False
        self._down = threading.Event()

    @classmethod
    def start(
        cls,
        config: RegistrarConfig | str,
        system: Transport | Address,
        *,
        setup: Callable[[ResourceRegistrar], None] | None = None,
        start_timeout: float = 10.0,
    ) -> RemoteRegistrar:
        """Start a registrar in a new manager process of `system`; return the owner handle.

        The process is started with the forkserver (or spawn) context; there it attaches
        the system, starts the registrar (restoring its catalog), runs `setup(registrar)`
        and serves it. It dies with this process.

        Args:
            config: the registrar's configuration, or just its name.
            system: the system the registrar joins: any carrier's `Transport` (the
                AF_UNIX `System`, a `ZenohNetwork`) or its `Address`.
            setup: cloudpickled and run in the manager process before it serves.
            start_timeout: seconds the manager may take to be ready.

        Returns:
            The owner handle.

        Raises:
            ConfigError: `config` is invalid or `setup` does not pickle.
            RegistrarUnavailableError: the manager failed to start (its traceback, say a
                `DuplicateNameError` or `CatalogCorruptError`, is in the message).
            CallTimeoutError: it was not ready within `start_timeout` seconds.
        """
        if isinstance(config, str):
            config = RegistrarConfig(name=config)
        elif not isinstance(config, RegistrarConfig):
            raise ConfigError(f"config must be a RegistrarConfig or a name, got {config!r}")
        # a Transport has its `address`; an Address has none (both are protocols)
        address = cast("Address", getattr(system, "address", system))
        try:
            payload = cloudpickle.dumps(setup)
        except Exception as exc:
            raise ConfigError(
                f"setup of registrar {config.name!r} is not picklable: {exc}"
            ) from exc
        handle = cls(config, address)
        handle._process = ManagerProcess.start(
            config.name,
            payload,
            config,
            address,
            start_timeout=start_timeout,
            heartbeat=None,
            heartbeat_timeout=start_timeout,
            on_exit=handle._exited,
        )
        try:
            restored, in_doubt = handle.run(_restored_and_in_doubt, timeout=start_timeout)
            handle._facts = RegistrarFacts(config, restored, in_doubt)
        except BaseException:
            handle.kill()
            raise
        return handle

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickle as a plain (non-owner) handle: the manager process stays with its owner."""
        facts = self._facts
        return (_rebuild, (facts.config, self._address, facts.restored, facts.in_doubt))

    # -- properties -------------------------------------------------------------------

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
        """Loads a crash cut short in the last run (see `ResourceRegistrar.in_doubt`)."""
        return self._facts.in_doubt

    @property
    def pid(self) -> int | None:
        """The manager process's pid (owner handle), else `None`."""
        return None if self._process is None else self._process.pid

    def is_alive(self) -> bool:
        """Whether the registrar (for the owner: its manager process) is running."""
        if self._process is not None:
            return not self._process.exited.is_set()
        try:
            alive: bool = self._forward(lambda reg: reg.is_alive(), None)
        except RrError:
            return False
        return alive

    # -- running code in the registrar's process ---------------------------------------

    def run(self, fn: Callable[[ResourceRegistrar], Any], *, timeout: float | None = None) -> Any:
        """Run `fn(registrar)` in the registrar's process and return its result.

        `fn` is cloudpickled (closures work); in the registrar's own process it runs on
        the calling thread, elsewhere on a fresh thread of the registrar's process.

        Args:
            fn: called with the `ResourceRegistrar`; its result must pickle.
            timeout: seconds to wait for the result (default: the config's `call_timeout`).

        Returns:
            What `fn` returned.

        Raises:
            CallTimeoutError: no result within `timeout` seconds.
            RegistrarUnavailableError: the registrar's process died or is unreachable.
            RegistrarStoppedError: the registrar was stopped.
            UnknownServerError: no registrar of that name was ever served on the system.
            ConfigError: `fn` does not pickle.
            Exception: whatever `fn` raised, re-raised here.
        """
        limit = self._config.call_timeout if timeout is None else timeout
        return self._address.attach().run(self.name, fn, timeout=limit)

    def _forward(self, fn: Callable[[ResourceRegistrar], Any], timeout: object) -> Any:
        """Run a method remotely; wait for it a margin beyond its own `timeout`.

        An invalid `timeout` is passed on untouched (the registrar rejects it with the same
        `ConfigError` as a local one); the wait then uses the default.
        """
        valid = isinstance(timeout, int | float) and not isinstance(timeout, bool) and timeout > 0
        limit = float(timeout) if valid else self._config.call_timeout  # type: ignore[arg-type]
        return self.run(fn, timeout=limit + FORWARD_MARGIN)

    def _forwarding(
        self,
        steps_of: Callable[[ResourceRegistrar], Steps[Any]],
        timeout: object,
        *,
        give_back: bool = False,
    ) -> Steps[Any]:
        """The steps of one operation, `steps_of(registrar)`, run where the registrar is.

        Served in this process: its handle's own steps, here. Elsewhere: one `Run` that
        drives them there (on a thread of that process), waited for a margin beyond the
        operation's own `timeout`. With `give_back` (a call), a wait that ends early
        here (cancelled, timed out) gives back the query the call there still gets.
        """
        transport = self._address.attach()
        valid = isinstance(timeout, int | float) and not isinstance(timeout, bool) and timeout > 0
        limit = (float(timeout) if valid else self._config.call_timeout) + FORWARD_MARGIN  # type: ignore[arg-type]
        peer = transport.resolve(self.name)
        if not isinstance(peer, Remote):  # served here (or unknown: `run` says so)
            local: ResourceRegistrar = transport.run(self.name, _itself, timeout=limit)
            return (yield from steps_of(local))
        context = LOADING.get()
        reply = peer.submit(functools.partial(_drive_there, steps_of, context))
        try:
            settled = yield reply.future, time.monotonic() + limit
        except BaseException:
            if give_back:
                reply.future.add_done_callback(functools.partial(_give_back, peer))
            raise
        if not settled:
            if give_back:
                reply.future.add_done_callback(functools.partial(_give_back, peer))
            raise CallTimeoutError(f"run() on registrar {self.name!r} timed out after {limit:g} s")
        return reply.future.get(timeout=0)

    # -- the steps of the awaitable twins (`_registrar/aio.py`) -------------------------

    def _register_server_steps(
        self,
        name: str,
        load: LoadCallback,
        unload: UnloadCallback,
        on_status: StatusCallback | None,
        timeout: float | None,
        label: Callable[[Any], str] | None,
    ) -> Steps[None]:
        return self._forwarding(
            lambda reg: reg._register_server_steps(name, load, unload, on_status, timeout, label),
            timeout,
        )

    def _unregister_server_steps(self, name: str, timeout: float | None) -> Steps[None]:
        return self._forwarding(lambda reg: reg._unregister_server_steps(name, timeout), timeout)

    def _call_steps(
        self,
        target_rr: str,
        server: str,
        request: Any,
        on_status: StatusCallback | None,
        timeout: float | None,
        query_id: str | None,
    ) -> Steps[Query]:
        return self._forwarding(
            lambda reg: reg._call_steps(target_rr, server, request, on_status, timeout, query_id),
            timeout,
            give_back=True,
        )

    def _unload_steps(self, query_id: str, timeout: float | None) -> Steps[None]:
        return self._forwarding(lambda reg: reg._unload_steps(query_id, timeout), timeout)

    def _send_status_steps(
        self, query_id: str, status: Status, message: str, timeout: float | None
    ) -> Steps[None]:
        return self._forwarding(
            lambda reg: reg._send_status_steps(query_id, status, message, timeout), timeout
        )

    def _server_queries_steps(self, server: str, timeout: float | None) -> Steps[list[Query]]:
        return self._forwarding(lambda reg: reg._server_queries_steps(server, timeout), timeout)

    def _fetch_queries_steps(
        self, target_rr: str, server: str, timeout: float | None
    ) -> Steps[list[Query]]:
        return self._forwarding(
            lambda reg: reg._fetch_queries_steps(target_rr, server, timeout), timeout
        )

    def _client_queries_steps(self, timeout: float | None) -> Steps[list[Query]]:
        return self._forwarding(lambda reg: reg._client_queries_steps(timeout), timeout)

    def _set_status_callback_steps(
        self, query_id: str, callback: StatusCallback, timeout: float | None
    ) -> Steps[None]:
        return self._forwarding(
            lambda reg: reg._set_status_callback_steps(query_id, callback, timeout), timeout
        )

    def _update_response_steps(
        self, query_id: str, response: Any, timeout: float | None
    ) -> Steps[None]:
        return self._forwarding(
            lambda reg: reg._update_response_steps(query_id, response, timeout), timeout
        )

    def _save_catalog_steps(self, timeout: float | None) -> Steps[None]:
        return self._forwarding(lambda reg: reg._save_catalog_steps(timeout), timeout)

    def _stop_steps(self, timeout: float | None) -> Steps[None]:
        if self._process is not None:  # the owner: the process, as `stop` does
            stop = functools.partial(RemoteRegistrar.stop, self, timeout=timeout)  # (its own)
            yield from on_own_thread(stop, f"rr-stop-{self.name}")
            return
        try:
            yield from self._forwarding(lambda reg: reg._stop_steps(timeout), timeout)
        except (RegistrarStoppedError, RegistrarUnavailableError):
            return

    def watch(self, query_id: str, *, maxsize: int = 256) -> StatusWatch:
        """Not here: a query's statuses reach the registrar that holds it, in its process.

        Raises:
            ConfigError: always; watch it from a registrar of this process that holds
                it (`ResourceRegistrar.watch`), or register a status callback there
                (`aset_status_callback`: it runs in the registrar's process).
        """
        raise ConfigError(
            f"watch() needs the registrar that holds the query in this process; "
            f"{self.name!r} runs in another: watch from a registrar of this process, or "
            "set a status callback (it runs in the registrar's process)"
        )

    # -- the ResourceRegistrar API ----------------------------------------------------

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
        """`ResourceRegistrar.register_server`; the callbacks run in the registrar's process.

        Raises:
            ConfigError: a callback is not callable or does not pickle, or the name is bad.
            DuplicateNameError: a server with this name exists on the registrar.
            RegistrarUnavailableError: the registrar's process died.
        """
        self._forward(
            lambda reg: reg.register_server(
                name, load=load, unload=unload, on_status=on_status, timeout=timeout, label=label
            ),
            timeout,
        )

    def unregister_server(self, name: str, *, timeout: float | None = None) -> None:
        """`ResourceRegistrar.unregister_server`.

        Raises:
            UnknownServerError: no such server there.
            CallTimeoutError: not finished within `timeout` seconds.
            RegistrarUnavailableError: the registrar's process died.
        """
        self._forward(lambda reg: reg.unregister_server(name, timeout=timeout), timeout)

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
        """`ResourceRegistrar.call`, made by the remote registrar.

        Made from inside a `load` callback (of any process), the call carries that load's
        context, exactly as a local handle's call would: a dependency when the load runs
        on this registrar, and part of the chain for cycle detection.

        Raises:
            ResourceLoadError: `load` raised there or further down.
            DependencyCycleError: the load would wait for itself further up its chain.
            UnknownServerError: no such registrar or server.
            CallTimeoutError: no answer in time.
            RegistrarUnavailableError: the provider (or this registrar's process) died.
            RegistrarStoppedError: this registrar or the provider was stopped.
            ConfigError: `on_status` is not callable, or the request does not pickle.
        """
        context = LOADING.get()
        args = (target_rr, server, request)
        kw = {"on_status": on_status, "timeout": timeout, "query_id": query_id}
        query: Query = self._forward(
            functools.partial(_call_in_context, context, args, kw), timeout
        )
        return query

    def unload(self, query_id: str, *, timeout: float | None = None) -> None:
        """`ResourceRegistrar.unload`.

        Raises:
            UnknownQueryError: the id is unknown there or already released.
            CallTimeoutError: not finished within `timeout` seconds.
            RegistrarUnavailableError: the registrar's process died; or the provider
                did, and it releases the id when it reconciles after its restart (the
                registrar no longer holds it, see `ResourceRegistrar.unload`).
        """
        self._forward(lambda reg: reg.unload(query_id, timeout=timeout), timeout)

    def send_status(
        self, query_id: str, status: Status, message: str = "", *, timeout: float | None = None
    ) -> None:
        """`ResourceRegistrar.send_status`.

        Raises:
            UnknownQueryError: `query_id` is not a consumer id of a resource served there.
            CallTimeoutError: not delivered everywhere within `timeout` seconds.
            ConfigError: `status` is not an `rr_actors.Status`.
            RegistrarUnavailableError: the registrar's process died.
        """
        self._forward(
            lambda reg: reg.send_status(query_id, status, message, timeout=timeout), timeout
        )

    def server_queries(self, server: str, *, timeout: float | None = None) -> list[Query]:
        """`ResourceRegistrar.server_queries`.

        Raises:
            UnknownServerError: no such server there.
            RegistrarUnavailableError: the registrar's process died.
        """
        result: list[Query] = self._forward(
            lambda reg: reg.server_queries(server, timeout=timeout), timeout
        )
        return result

    def fetch_queries(
        self, target_rr: str, server: str, *, timeout: float | None = None
    ) -> list[Query]:
        """`ResourceRegistrar.fetch_queries`.

        Raises:
            UnknownServerError: no such registrar or server.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarUnavailableError: the provider or the registrar's process died.
        """
        result: list[Query] = self._forward(
            lambda reg: reg.fetch_queries(target_rr, server, timeout=timeout), timeout
        )
        return result

    def client_queries(self, *, timeout: float | None = None) -> list[Query]:
        """`ResourceRegistrar.client_queries`.

        Raises:
            RegistrarUnavailableError: the registrar's process died.
        """
        result: list[Query] = self._forward(
            lambda reg: reg.client_queries(timeout=timeout), timeout
        )
        return result

    def set_status_callback(
        self, query_id: str, callback: StatusCallback, *, timeout: float | None = None
    ) -> None:
        """`ResourceRegistrar.set_status_callback`; `callback` runs in the registrar's process.

        Raises:
            UnknownQueryError: the registrar holds no such query.
            ConfigError: `callback` is not callable or does not pickle.
            RegistrarUnavailableError: the registrar's process died.
        """
        self._forward(
            lambda reg: reg.set_status_callback(query_id, callback, timeout=timeout), timeout
        )

    def update_response(
        self, query_id: str, response: Any, *, timeout: float | None = None
    ) -> None:
        """`ResourceRegistrar.update_response`.

        Raises:
            UnknownQueryError: `query_id` is not a consumer id of a resource served there.
            RegistrarUnavailableError: the registrar's process died.
        """
        self._forward(lambda reg: reg.update_response(query_id, response, timeout=timeout), timeout)

    def save_catalog(self, *, timeout: float | None = None) -> None:
        """`ResourceRegistrar.save_catalog`.

        Raises:
            RegistrarUnavailableError: the registrar's process died.
        """
        self._forward(lambda reg: reg.save_catalog(timeout=timeout), timeout)

    def stop(self, *, timeout: float | None = None) -> None:
        """Stop the registrar (rule 12) and, for the owner handle, its manager process.

        Stopping a stopped (or dead) registrar is a no-op.

        Args:
            timeout: seconds the stop may take (default: the config's `call_timeout`);
                the owner kills the process after that.

        Raises:
            CallTimeoutError: not finished within `timeout` seconds (the process was killed).
            RegistrarUnavailableError: the registrar died (or its process exited) while it
                stopped; the reason is in the message.
        """
        limit = self._config.call_timeout if timeout is None else timeout
        if self._process is None:
            with contextlib.suppress(RegistrarStoppedError, RegistrarUnavailableError):
                self._forward(lambda reg: reg.stop(timeout=limit), limit)
            return
        if self._process.exited.is_set():
            return
        self._stopping = True
        result = self._process.stop(limit)
        self._down.wait(limit)
        if result.normal:
            return
        if result.reason.startswith("killed: no clean stop"):
            raise CallTimeoutError(f"stop() of registrar {self.name!r}: {result.reason}")
        raise RegistrarUnavailableError(
            f"registrar {self.name!r} did not stop cleanly: {result.reason}"
        )

    def kill(self, *, timeout: float = 5.0) -> None:
        """SIGKILL the registrar's manager process; return once it is dead.

        For the owner handle, this also waits until the system's registrars were told
        that this consumer is gone (death watch). From another handle, the process kills
        itself and its owner does the rest.

        Args:
            timeout: seconds to wait for the death.

        Raises:
            CallTimeoutError: it was not seen dead within `timeout` seconds.
        """
        if self._process is None:
            with contextlib.suppress(RegistrarUnavailableError, RegistrarStoppedError):
                self.run(_kill_own_process, timeout=timeout)
            return
        self._process.kill()
        if not self._down.wait(timeout):
            raise CallTimeoutError(f"manager {self.name!r} not dead within {timeout:g} s")

    def __enter__(self) -> RemoteRegistrar:
        return self

    def __exit__(self, *_: object) -> None:
        self.stop()

    def __repr__(self) -> str:
        where = "" if self._process is None else f" pid {self._process.pid}"
        return f"<RemoteRegistrar {self.name!r}{where}>"

    # -- the owner's watcher ------------------------------------------------------------

    def _exited(self, how: ManagerExit) -> None:
        """Runs on the manager's watcher thread when the process ended."""
        try:
            gone = not how.clean and not self._stopping
            if gone and not DIRECTORY.restart_expected(self.name):
                _consumer_down(self._address, self.name)
        finally:
            self._down.set()


def _rebuild(
    config: RegistrarConfig, address: Address, restored: bool, in_doubt: tuple[Query, ...]
) -> RemoteRegistrar:
    return RemoteRegistrar(config, address, restored=restored, in_doubt=in_doubt)


def _restored_and_in_doubt(registrar: ResourceRegistrar) -> tuple[bool, tuple[Query, ...]]:
    return registrar.restored, registrar.in_doubt


def _call_in_context(
    context: LoadContext | None, args: tuple[Any, ...], kw: Any, registrar: ResourceRegistrar
) -> Query:
    """`registrar.call(*args, **kw)` as if made from a thread whose load context is `context`."""
    if context is None:
        return registrar.call(*args, **kw)
    scope = contextvars.copy_context()
    scope.run(LOADING.set, context)
    return scope.run(registrar.call, *args, **kw)


def _itself(registrar: ResourceRegistrar) -> ResourceRegistrar:
    return registrar


def _drive_there(
    steps_of: Callable[[ResourceRegistrar], Steps[Any]],
    context: LoadContext | None,
    registrar: ResourceRegistrar,
) -> Any:
    """In the registrar's process, on a thread of its own: run the operation's steps,
    in the load context of the caller (`_call_in_context`)."""
    if context is None:
        return run_steps(steps_of(registrar))
    scope = contextvars.copy_context()
    scope.run(LOADING.set, context)
    return scope.run(lambda: run_steps(steps_of(registrar)))


def _give_back(peer: Remote, future: Any) -> None:
    """A call whose caller stopped waiting here got its answer there: release its id
    there (on the answering thread; nobody waits for it)."""
    try:
        query = future.get(timeout=0)
    except Exception:  # noqa: BLE001 - failed there: nothing is held
        return
    if isinstance(query, Query):
        peer.submit(functools.partial(_release, query.id))


def _release(query_id: str, registrar: ResourceRegistrar) -> None:
    with contextlib.suppress(RrError):
        registrar.unload(query_id)


def _kill_own_process(_: ResourceRegistrar) -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def _consumer_down(address: Address, name: str) -> None:
    """Death watch: tell every registrar of the system (and of this process) `name` is
    gone for good (rule 19; `presence.py` handles it)."""
    served: list[str] = []
    with contextlib.suppress(RrError):
        served = address.attach().names()
    gone_for_good(name, also=served)


if TYPE_CHECKING:  # mypy checks that the handle implements the protocol
    from rr_actors._registrar import Registrar

    _implements: type[Registrar] = RemoteRegistrar
