"""The registrar's handle: one class wherever its actor lives, callable from any thread.

```
 reg.call(...)        ─► blocking(       reg._actor.steps(Here.call, ...)) the thread blocks
 await reg.acall(...) ─► run_steps_async(reg._actor.steps(Here.call, ...)) the loop awaits
                                                  │
   Here: the actor in this process ───────────────┼─► Here.call(here, ...): send the actor
     (a ResourceRegistrar's)                      │   its message, yield the future of its
                                                  │   answer, return it
   There: in another process ─────────────────────┴─► one `Run` of Here.call there,
     (`_process/remote.py`)                           over the carrier
 task cancelled, KeyboardInterrupt ─► thrown in at the yield: the call is withdrawn as a
                                      timeout withdraws it, then raised
```

An operation is a method of `Here` that returns its *steps* (`_core/replies.py`: a
generator yielding `(future, deadline)` per wait): `run_steps` drives them on the calling
thread, `loops.run_steps_async` on the running loop, so both twins have the same
arguments, results, errors and timeouts (`acall` is `call`, awaited: Django's `aget`).
The rest of the package reaches an actor of this process only through its `Here`;
starting the actor is `actor.py`'s (`launch`).
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
import sys
from collections.abc import Callable
from typing import Any, Concatenate, ParamSpec, Protocol, Self, TypeVar

import pykka

from rr_actors import events
from rr_actors._core import hlc, runtime, traces
from rr_actors._core.bus import DEFAULT_MAXSIZE, Publisher, Subscription
from rr_actors._core.directory import DIRECTORY, Reply
from rr_actors._core.exit import REGISTRARS, stop_at_exit
from rr_actors._core.loops import (
    OnLoop,
    is_coroutine_function,
    on_process_loop,
    process_loop,
    run_steps_async,
)
from rr_actors._core.replies import FutureReply, Steps, asked, run_steps
from rr_actors._registrar.actor import Launched, RegistrarActor, launch
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
from rr_actors._registrar.state import Probes
from rr_actors._types import (
    IfOverloaded,
    LoadCallback,
    Query,
    Status,
    StatusCallback,
    StatusDelivery,
    StatusUpdate,
    UnloadCallback,
)
from rr_actors.config import RegistrarConfig, check_choice, check_seconds, check_strs
from rr_actors.errors import CallTimeoutError, ConfigError, RegistrarStoppedError

T = TypeVar("T")
P = ParamSpec("P")

STOP_WAITS_FOR_UNLOADS = 0.5
"""The share of `stop()`'s timeout it waits for the unloads under way (the rest: to write
the backup and stop the servers)."""

_SECONDS = (float, int)  # a timeout's types checked without `check_seconds` (not bool)


@dataclasses.dataclass(frozen=True)
class RegistrarFacts:
    """What a handle knows without asking its actor (its properties of the same names)."""

    config: RegistrarConfig
    restored: bool = False
    in_doubt: tuple[Query, ...] = ()


class Placement(Protocol):
    """Where a handle's actor lives: `Here`, or `There` (`_process/remote.py`)."""

    def steps(
        self,
        op: Callable[Concatenate[Here, float | None, P], Steps[T]],
        timeout: float | None,
        *args: P.args,
        **kwargs: P.kwargs,
    ) -> Steps[T]: ...

    def stop(self, timeout: float | None) -> Steps[None]:
        """The steps of stopping the registrar (rule 12); a stopped one is a no-op."""
        ...

    def is_alive(self) -> bool: ...

    def state(self) -> str:
        """What the handle's `repr` says of it ("running", a pid; or nothing)."""
        ...


class Registrar:
    """A handle on a registrar, wherever its actor lives: in this process or in another.

    Its methods may be called from any thread, including from inside callbacks; each
    waits for the registrar at most `timeout` seconds (default: the config's
    `call_timeout`). Every method raises `CallTimeoutError` when they run out,
    `RegistrarStoppedError` when this registrar was stopped and `RegistrarUnavailableError`
    when it died; a method's docstring lists only its other errors. Each has an
    awaitable twin for event loops (`acall`, `aunload`, ..., `watch`): the same
    operation, errors and timeout, with no thread held while it waits. Cancelling the
    awaiting task withdraws what it waits for as its timeout would (a cancelled `acall`
    gives its query id back) and raises `asyncio.CancelledError`.

    A registrar of this process is a [`ResourceRegistrar`][rr_actors.ResourceRegistrar],
    one in a manager process a [`RemoteRegistrar`][rr_actors.testing.RemoteRegistrar]:
    for the latter, arguments, callbacks and results cross processes cloudpickled and
    callbacks run in the registrar's process.
    """

    _actor: Placement

    def __init__(self, facts: RegistrarFacts, actor: Placement) -> None:
        """Made by `ResourceRegistrar` or `RemoteRegistrar`, with where its actor lives."""
        self._facts = facts
        self._actor = actor

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

        Each is a `Query`: `id` the resource id, `request` what it was for, `response` `None`
        for a load that never finished. They left the catalog, their dependencies released;
        the manager cleans up. The backup keeps them until `setup` returned (or
        `settle_in_doubt`); without `setup`, they are forgotten at once.
        """
        return self._facts.in_doubt

    def is_alive(self) -> bool:
        """Whether the registrar is running (for the owner of a manager process: it)."""
        return self._actor.is_alive()

    def settle_in_doubt(self, query_id: str | None = None, *, timeout: float | None = None) -> None:
        """Say that in-doubt entry `query_id` (default: every one) is handled (rule 16).

        Its row leaves the backup, so a restart no longer reports it. The registrar does this
        once `setup` returns; call it from `setup` to settle each entry as it is cleaned up.
        Settling an entry again is a no-op.

        Args:
            query_id: the `id` of one of `in_doubt`'s queries, or `None` for all.
            timeout: seconds to wait for the registrar.

        Raises:
            UnknownQueryError: `query_id` is not the id of an entry of `in_doubt`.
            CatalogWriteError: the backup could not be written (a full disk): settled here,
                but a restart before the next successful write offers it again.
        """
        blocking(self._actor.steps(Here.settle_in_doubt, timeout, query_id))

    async def asettle_in_doubt(
        self, query_id: str | None = None, *, timeout: float | None = None
    ) -> None:
        """As `settle_in_doubt`, awaited (for a `setup` that cleans up with coroutines)."""
        await run_steps_async(self._actor.steps(Here.settle_in_doubt, timeout, query_id))

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
        max_pending: int | None = None,
    ) -> None:
        """Register a resource server `"<registrar>/<name>"`.

        Args:
            name: server name, unique on this registrar.
            load: `load(request) -> response`; runs on a worker thread of the registrar's
                process.
            unload: `unload(request, response) -> None`; runs on a worker thread, after the
                resource's dependencies were released.
            on_status: `on_status(query, update)`, run once on a worker thread when a status
                about one of this server's resources is sent or passes through.
            timeout: seconds to wait for the registrar.
            label: `label(request) -> str`, the observer's short name for a resource
                (`lidar2`, cut to 40 characters): run on a worker thread as its load starts,
                within `RegistrarConfig.compare_timeout`; if it fails (raises, returns a
                non-`str`, overruns) it reads `<label failed: ...>`, the load goes on.
            max_pending: new loads it may have queued or running (an int >= 1; `None`:
                `RegistrarConfig.max_pending`); past it a call waits within its timeout, then
                gets `OverloadedError` (a dedup hit, or one joining a load, never does). A
                queued load whose caller's timeout would end first: `DeadlineExceededError`.

        Raises:
            ConfigError: a callback is not callable (or, to another process, does not
                pickle), the name is invalid, or `max_pending` is not an int >= 1 (nor `None`).
            DuplicateNameError: a server with this name exists on this registrar.
        """
        op = Here.register_server
        steps = self._actor.steps(op, timeout, name, load, unload, on_status, label, max_pending)
        blocking(steps)

    async def aregister_server(
        self,
        name: str,
        *,
        load: LoadCallback,
        unload: UnloadCallback,
        on_status: StatusCallback | None = None,
        timeout: float | None = None,
        label: Callable[[Any], str] | None = None,
        max_pending: int | None = None,
    ) -> None:
        """As `register_server`, awaited. `load`, `unload` and `on_status` may be coroutine
        functions (through either twin): they then run on the event loop of the registrar's
        process; `ConfigError` if `label` is one."""
        steps = self._actor.steps(
            Here.register_server, timeout, name, load, unload, on_status, label, max_pending
        )
        await run_steps_async(steps)

    def unregister_server(self, name: str, *, timeout: float | None = None) -> None:
        """Remove a server: send `FATAL` to its consumers and unload all it serves (rule 12).

        Raises:
            UnknownServerError: no such server here.
        """
        blocking(self._actor.steps(Here.unregister_server, timeout, name))

    async def aunregister_server(self, name: str, *, timeout: float | None = None) -> None:
        """As `unregister_server`, awaited."""
        await run_steps_async(self._actor.steps(Here.unregister_server, timeout, name))

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
        if_overloaded: IfOverloaded = "wait",
    ) -> Query:
        """Ask `target_rr/server` for the resource `request` describes (rules 1-6, 17).

        The provider runs `load(request)` unless an equal (`==`) request is loaded or loading
        there; either way this call becomes one more consumer with its own id. Made inside a
        `load` callback, the query is a dependency of that resource (and in its chain for
        cycle detection); under an OpenTelemetry span, the provider's spans are its children.

        Args:
            target_rr: name of the provider registrar (this one's own name works too).
            server: server name on it.
            request: any value; equal requests mean the same resource. Within one process
                it is passed, not copied: do not change it after the call.
            on_status: client status callback `on_status(query, update)`, run on a worker
                thread of this registrar's process.
            timeout: seconds to wait for the answer.
            query_id: the id to use (default: a fresh UUID4). Retrying with the same id is
                idempotent: it never loads twice nor adds a second consumer.
            if_overloaded: when the server has its `max_pending` loads: `"wait"` (pause its
                `retry_after` and ask again while `timeout` lasts) or `"raise"`
                (`OverloadedError` at once; nothing is held at the provider).

        Returns:
            The `Query`, with the provider's `response` (in one process, the very object
            `load` returned, shared by every consumer: treat it as read-only).

        Raises:
            ResourceLoadError: `load` raised here or further down; `stack` says where.
            DependencyCycleError: the load would wait for itself further up its chain.
            UnknownServerError: no such registrar or server.
            CallTimeoutError: no answer in time; the query id is released if it loads later.
            OverloadedError: the server has its `max_pending` loads, and this caller does
                not wait or has too little time left to try again; nothing is held.
            RegistrarUnavailableError: the provider died (it may have executed the load).
            RegistrarStoppedError: this registrar or the provider was stopped.
            ConfigError: an argument of the wrong type; or the request or response does not
                pickle where it must (across processes, or into this registrar's backup).
        """
        steps = self._actor.steps(
            Here.call, timeout, target_rr, server, request, on_status, query_id, if_overloaded
        )
        return blocking(steps)

    async def acall(
        self,
        target_rr: str,
        server: str,
        request: Any,
        *,
        on_status: StatusCallback | None = None,
        timeout: float | None = None,
        query_id: str | None = None,
        if_overloaded: IfOverloaded = "wait",
    ) -> Query:
        """As `call`, awaited. Inside a coroutine `load` of this registrar the query is that
        resource's dependency. `on_status` may be a coroutine function: it runs on the loop this
        was awaited from (`watch` gives an iterator instead). Cancelled: withdrawn as on timeout."""
        steps = self._actor.steps(
            Here.call, timeout, target_rr, server, request, on_status, query_id, if_overloaded
        )
        return await run_steps_async(steps)

    def unload(self, query_id: str, *, timeout: float | None = None) -> None:
        """Release one consumer id obtained from `call` (rules 7-8).

        The provider's `unload` runs, after the resource's own dependencies were released,
        when its last consumer id is; this returns when that is done.

        Raises:
            UnknownQueryError: the id is unknown here or already released (nothing changes).
            RegistrarUnavailableError, RegistrarStoppedError: the provider died (or could not
                be reached), or was stopped, before it answered. The id is released all the
                same: the provider releases it when it reconciles at its next start (its
                `unload` runs once), and nobody gets `FATAL` for it (rule 20).
        """
        blocking(self._actor.steps(Here.unload, timeout, query_id))

    async def aunload(self, query_id: str, *, timeout: float | None = None) -> None:
        """As `unload`, awaited."""
        await run_steps_async(self._actor.steps(Here.unload, timeout, query_id))

    def send_status(
        self, query_id: str, status: Status, message: str = "", *, timeout: float | None = None
    ) -> StatusDelivery:
        """Tell every consumer of the resource behind `query_id` about its status (rule 9).

        This server's `on_status` runs once (waited for, within `timeout`); each consumer's
        status callback runs with its own query id on a worker thread of the consumer's
        process (a coroutine one: on its loop), up every dependency path to the top. Returns
        once every callback on the way has run or was given up on: not returned within the
        patience (half of `timeout`, or all of it but 1 s if more), or its id's earlier
        callback still given up on (its statuses then queue, coalesced to the latest and
        every `FATAL`).

        Args:
            query_id: any consumer id of a resource this registrar serves.
            status: the status code.
            message: free text.
            timeout: seconds to wait for delivery along the whole path.

        Returns:
            `StatusDelivery(reached, gave_up)`: the resource's consumer ids not given up
            on, and the ids (at any hop) whose callbacks were given up on.

        Raises:
            UnknownQueryError: `query_id` is not a consumer id of a resource served here.
            ConfigError: `status` is not a `Status`, `query_id` or `message` not a str.
            MessageTooLargeError: the status is over the `max_message_bytes` of a consumer
                registrar in another process (named): it did not hear it, the others did.
            CallTimeoutError: not delivered everywhere within `timeout` seconds.
        """
        steps = self._actor.steps(Here.send_status, timeout, query_id, status, message)
        delivery: StatusDelivery = blocking(steps)
        return delivery

    async def asend_status(
        self, query_id: str, status: Status, message: str = "", *, timeout: float | None = None
    ) -> StatusDelivery:
        """As `send_status`, awaited (a coroutine callback on the way counts once it returned)."""
        steps = self._actor.steps(Here.send_status, timeout, query_id, status, message)
        delivery: StatusDelivery = await run_steps_async(steps)
        return delivery

    def server_queries(self, server: str, *, timeout: float | None = None) -> list[Query]:
        """Every consumer query of this registrar's `server`, each id once (rule 10); its
        subscribers hear the answer's ids (`events.ServerQueriesListed`).

        Raises:
            UnknownServerError: no such server here.
        """
        return blocking(self._actor.steps(Here.server_queries, timeout, server))

    async def aserver_queries(self, server: str, *, timeout: float | None = None) -> list[Query]:
        """As `server_queries`, awaited."""
        return await run_steps_async(self._actor.steps(Here.server_queries, timeout, server))

    def fetch_queries(
        self, target_rr: str, server: str, *, timeout: float | None = None
    ) -> list[Query]:
        """The queries this registrar holds at `target_rr/server`, as the provider has them:
        after a restart, what it had asked for (thesis 4.2.5).

        Raises:
            UnknownServerError: no such registrar or server.
            ConfigError: `target_rr` or `server` is not a str.
            RegistrarUnavailableError: the provider died.
        """
        return blocking(self._actor.steps(Here.fetch_queries, timeout, target_rr, server))

    async def afetch_queries(
        self, target_rr: str, server: str, *, timeout: float | None = None
    ) -> list[Query]:
        """As `fetch_queries`, awaited."""
        steps = self._actor.steps(Here.fetch_queries, timeout, target_rr, server)
        return await run_steps_async(steps)

    def client_queries(self, *, timeout: float | None = None) -> list[Query]:
        """Every query this registrar holds at servers (its own included), oldest first."""
        return blocking(self._actor.steps(Here.client_queries, timeout))

    async def aclient_queries(self, *, timeout: float | None = None) -> list[Query]:
        """As `client_queries`, awaited."""
        return await run_steps_async(self._actor.steps(Here.client_queries, timeout))

    def set_status_callback(
        self, query_id: str, callback: StatusCallback, *, timeout: float | None = None
    ) -> None:
        """Attach (or replace) the client status callback of a query this registrar holds.

        Callbacks are not in the backup: re-attach them after a restart (rule 11). The
        callback runs in the registrar's process.

        Raises:
            UnknownQueryError: this registrar holds no such query.
            ConfigError: `callback` is not callable (or, to a registrar in another
                process, does not pickle).
        """
        blocking(self._actor.steps(Here.set_status_callback, timeout, query_id, callback))

    async def aset_status_callback(
        self, query_id: str, callback: StatusCallback, *, timeout: float | None = None
    ) -> None:
        """As `set_status_callback`, awaited; a coroutine `callback` runs on the awaiting loop."""
        steps = self._actor.steps(Here.set_status_callback, timeout, query_id, callback)
        await run_steps_async(steps)

    def update_response(
        self, query_id: str, response: Any, *, timeout: float | None = None
    ) -> None:
        """Replace the stored response of the resource behind `query_id` (thesis 4.3.2).

        Returns once every consumer's client record holds it too (one unreachable is logged
        and skipped).

        Args:
            query_id: any consumer id of a resource this registrar serves.
            response: the new response (it must pickle when the catalog has a backup).
            timeout: seconds to wait for the update to reach every consumer.

        Raises:
            UnknownQueryError: `query_id` is not a consumer id of a resource served here.
            ConfigError: the response cannot be pickled and this registrar keeps a backup
                (nothing changes), or a consumer registrar of this process that keeps one
                refused it (its record keeps the old response).
            MessageTooLargeError: over the `max_message_bytes` of a consumer registrar in
                another process (named): its record keeps the old response.
        """
        blocking(self._actor.steps(Here.update_response, timeout, query_id, response))

    async def aupdate_response(
        self, query_id: str, response: Any, *, timeout: float | None = None
    ) -> None:
        """As `update_response`, awaited."""
        steps = self._actor.steps(Here.update_response, timeout, query_id, response)
        await run_steps_async(steps)

    def save_catalog(self, *, timeout: float | None = None) -> None:
        """Write every pending change of the catalog to the backup now (no-op without one)."""
        blocking(self._actor.steps(Here.save_catalog, timeout))

    async def asave_catalog(self, *, timeout: float | None = None) -> None:
        """As `save_catalog`, awaited."""
        await run_steps_async(self._actor.steps(Here.save_catalog, timeout))

    def stop(self, *, timeout: float | None = None) -> None:
        """Stop the registrar (rule 12); for the owner of a manager process, the process too.

        Unloads what it holds as a consumer (newest first), waits for its resources' unloads
        under way for `STOP_WAITS_FOR_UNLOADS` of `timeout`, then stops its servers and
        clients; an unload still under way is cut short (`events.UnloadCutShort`; in doubt at
        the next start, rule 16). Its catalog stays for a restart (`erase_on_destruct` removes
        the backup). Stopping a stopped (or dead) registrar is a no-op.

        Args:
            timeout: seconds the whole stop may take (`None`: `call_timeout`); the owner of
                a manager process kills it after that.

        Raises:
            CallTimeoutError: not finished within `timeout` seconds (a manager process
                was killed).
            RegistrarUnavailableError: the registrar died (or its process exited) while it
                stopped; the reason is in the message.
        """
        blocking(self._actor.stop(timeout))

    async def astop(self, *, timeout: float | None = None) -> None:
        """As `stop`, awaited."""
        await run_steps_async(self._actor.stop(timeout))

    def watch(self, query_id: str, *, maxsize: int = 256) -> StatusWatch:
        """The status updates of query `query_id`, as an async iterator (`rr.StatusUpdate`s).

        Once opened (its first step, or `async with`) it is the query's status callback.
        Iteration ends after a `FATAL` (rule 19) or once closed (`aclose()`, leaving its
        `async with`); a `break` or a cancelled task leaves it open. Updates queue on the
        loop it was opened on; past `maxsize` the oldest is dropped (counted in `dropped`).

        Args:
            query_id: a query this registrar holds (from `call` or `acall`).
            maxsize: updates kept for a reader that falls behind.

        Raises:
            ConfigError: the registrar runs in another process (set a status callback
                there instead), or `maxsize` is not a positive int. The first step of the
                iteration raises what `aset_status_callback` raises.
        """
        if not isinstance(self._actor, Here):
            raise ConfigError(
                f"watch() needs the registrar that holds the query in this process; "
                f"{self.name!r} runs in another: watch from a registrar of this process, "
                "or set a status callback (it runs in the registrar's process)"
            )
        if isinstance(maxsize, bool) or not isinstance(maxsize, int) or maxsize < 1:
            raise ConfigError(f"maxsize must be a positive int, got {maxsize!r}")
        return StatusWatch(self, query_id, maxsize)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *_: object) -> None:
        self.stop()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *_: object) -> None:
        await self.astop()

    def __repr__(self) -> str:
        state = self._actor.state()
        return f"<{type(self).__name__} {self.name!r}{' ' if state else ''}{state}>"


class Here:
    """The actor in this process (a `ResourceRegistrar`'s): an operation's steps run here."""

    def __init__(self, launched: Launched) -> None:
        config = launched.config
        self.config = config
        self.ref: pykka.ActorRef[RegistrarActor] = launched.ref
        self.clients = launched.clients
        self.died = launched.died  # set when a crash of the actor was fully handled
        self.ended = launched.ended  # set when the actor handed on its last message
        self.published = launched.published
        self.in_doubt_texts = launched.in_doubt_texts
        self.probes: Probes | None = None  # `rr_actors.testing.intercept`
        self.calls = Calls(
            self.ref,
            config.name,
            launched.due,  # shared with the actor
            commit_first=config.save_on_modify and config.backup_path is not None,
            stored=config.backup_path is not None,
            probes=lambda: self.probes,
            events=launched.published,
            life=launched.life,
        )

    # -- where the actor lives (`Placement`) --------------------------------------------

    def steps(
        self,
        op: Callable[Concatenate[Here, float | None, P], Steps[T]],
        timeout: float | None,
        *args: P.args,
        **kwargs: P.kwargs,
    ) -> Steps[T]:
        return op(self, timeout, *args, **kwargs)

    def is_alive(self) -> bool:
        return self.ref.is_alive()

    def state(self) -> str:
        return "running" if self.ref.is_alive() else "stopped"

    # -- the operations: each returns the steps of one method of `Registrar` ------------

    def settle_in_doubt(self, timeout: float | None, query_id: str | None) -> Steps[None]:
        what = f"settle_in_doubt({query_id!r})"
        return self.asking(SettleInDoubt(query_id, FutureReply()), timeout, what)

    def register_server(
        self,
        timeout: float | None,
        name: str,
        load: LoadCallback,
        unload: UnloadCallback,
        on_status: StatusCallback | None,
        label: Callable[[Any], str] | None,
        max_pending: int | None = None,
    ) -> Steps[None]:
        if not isinstance(name, str) or not name or "/" in name:
            raise ConfigError(f"server name must be a non-empty string without '/', got {name!r}")
        if max_pending is not None and (
            isinstance(max_pending, bool) or not isinstance(max_pending, int) or max_pending < 1
        ):
            raise ConfigError(
                f"max_pending of server {name!r} must be an int >= 1 (or None: the "
                f"registrar's), got {max_pending!r}"
            )
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
        return self.asking(
            RegisterServer(name, load, unload, on_status, label, FutureReply(), max_pending),
            timeout,
            f"register_server({name!r})",
        )

    def unregister_server(self, timeout: float | None, name: str) -> Steps[None]:
        what = f"unregister_server({name!r})"
        return self.asking(UnregisterServer(name, FutureReply()), timeout, what)

    def call(
        self,
        timeout: float | None,
        target_rr: str,
        server: str,
        request: Any,
        on_status: StatusCallback | None,
        query_id: str | None,
        if_overloaded: IfOverloaded = "wait",
    ) -> Steps[Query]:
        if on_status is not None and not callable(on_status):
            raise ConfigError(f"on_status must be callable, got {on_status!r}")
        if if_overloaded not in ("wait", "raise"):  # (config.py off a call's path: checked first)
            check_choice("if_overloaded", if_overloaded, ("wait", "raise"))
        if not (isinstance(target_rr, str) and isinstance(server, str)):
            check_strs(target_rr=target_rr, server=server)
        if query_id is not None and not (isinstance(query_id, str) and query_id):
            raise ConfigError(
                f"query_id must be a non-empty str (or None: a fresh id), got {query_id!r}"
            )
        if on_status is not None and is_coroutine_function(on_status):
            on_status = OnLoop.bind(on_status)  # the loop it was registered from
        limit = self.limit(timeout)
        deadline = runtime.monotonic() + limit
        context = LOADING.get()
        parent: str | None = None
        chain: tuple[str, ...] = ()
        if context is not None:
            chain = context.chain
            if context.registrar == self.config.name:
                parent = context.resource_id
        if self.config.backup_path is not None:
            check_picklable(request, f"the request of a call to '{target_rr}/{server}'")
        steps = self.calls.steps(
            query_id or runtime.new_id(),
            target_rr,
            server,
            request,
            parent,
            chain,
            on_status,
            limit,
            deadline,
            _trace_context(),  # (in the caller's thread or task: its OpenTelemetry context)
            wait_overloaded=if_overloaded == "wait",
        )
        client = self.clients.get((target_rr, server))
        if client is None or not client.is_alive():  # (it exists from the first call)
            return _after(self.client(target_rr, server, limit), steps)
        return steps

    def withdrawn(
        self, _: float | None, qid: str, to: str, server: str, why: str, began: float
    ) -> Steps[None]:
        """Its caller gave up the call of `qid` between its tries (`call_with_retry`, the id
        abandoned): its `CallWithdrawn` (of `why`, begun at `began`, traced as `call`)."""
        attempt = self.calls.new_attempt(_trace_context())
        attempt.started = began
        attempt.withdraw()
        self.calls.withdrawn(qid, attempt, to, server, why)
        yield from ()

    def unload(self, timeout: float | None, query_id: str) -> Steps[None]:
        release = Release(query_id, FutureReply(), _trace_context())
        return self.asking(release, timeout, f"unload({query_id!r})")

    def send_status(
        self, timeout: float | None, query_id: str, status: Status, message: str
    ) -> Steps[StatusDelivery]:
        if not isinstance(status, Status):
            raise ConfigError(f"status must be an rr_actors.Status, got {status!r}")
        limit = self.limit(timeout)
        patience = max(limit / 2, limit - 1.0)  # (the rest: for the answers to come back)
        return self.asking(
            SendStatus(query_id, status, message, FutureReply(), patience),
            timeout,
            f"send_status({query_id!r})",
        )

    def server_queries(self, timeout: float | None, server: str) -> Steps[list[Query]]:
        # The catalog is read after this stamp (as fetch_queries's, only for a subscriber).
        started = hlc.CLOCK.now() if self.published.active else None
        what = f"server_queries({server!r})"
        result: list[Query] = yield from self.asking(
            ListServerQueries(server, FutureReply()), timeout, what
        )
        if started is not None and self.published.active:
            ids = tuple(query.id for query in result)
            self.published.publish(
                events.ServerQueriesListed(self.config.name, server, ids, started)
            )
        return result

    def fetch_queries(
        self, timeout: float | None, target_rr: str, server: str
    ) -> Steps[list[Query]]:
        check_strs(target_rr=target_rr, server=server)
        limit = self.limit(timeout)
        deadline = runtime.monotonic() + limit
        # The provider reads its catalog after this stamp; taken only for a subscriber (it
        # ticks the clock, which a simulated history must not see without one).
        started = hlc.CLOCK.now() if self.published.active else None
        reply = FutureReply()
        client = yield from self.client(target_rr, server, limit)
        client.tell(FetchVia(server, reply))
        result: list[Query] = yield from asked(
            reply.future, deadline, limit, f"fetch_queries({target_rr!r})"
        )
        if started is not None and self.published.active:
            ids = tuple(query.id for query in result)
            self.published.publish(
                events.QueriesFetched(self.config.name, target_rr, server, ids, started)
            )
        return result

    def client_queries(self, timeout: float | None) -> Steps[list[Query]]:
        return self.asking(ListClientQueries(FutureReply()), timeout, "client_queries()")

    def set_status_callback(
        self, timeout: float | None, query_id: str, callback: StatusCallback
    ) -> Steps[None]:
        if not callable(callback):
            raise ConfigError(f"callback must be callable, got {callback!r}")
        if is_coroutine_function(callback):
            callback = OnLoop.bind(callback)  # the loop it was registered from
        return self.asking(
            SetStatusCallback(query_id, callback, FutureReply()),
            timeout,
            f"set_status_callback({query_id!r})",
        )

    def update_response(self, timeout: float | None, query_id: str, response: Any) -> Steps[None]:
        if self.config.backup_path is not None:
            check_picklable(response, f"the new response of {query_id!r}")
        return self.asking(
            UpdateResponse(query_id, response, FutureReply()),
            timeout,
            f"update_response({query_id!r})",
        )

    def save_catalog(self, timeout: float | None) -> Steps[None]:
        return self.asking(Save(FutureReply()), timeout, "save_catalog()")

    def stop(self, timeout: float | None) -> Steps[None]:
        if not self.ref.is_alive():
            return
        limit = self.limit(timeout)
        deadline = runtime.monotonic() + limit
        try:
            until = deadline - limit * (1.0 - STOP_WAITS_FOR_UNLOADS)
            yield from self.asking(Stop(FutureReply(), until), limit, "stop()")
        except RegistrarStoppedError:
            return
        # Stop ended the actor; what reached its mailbox meanwhile (an answer to give
        # back, a notice to acknowledge) is handled once its thread has handed it on.
        if not (yield self.ended, deadline):
            raise CallTimeoutError(f"stop() of {self.config.name!r} timed out after {limit:g} s")

    # -- how the package reaches the actor ----------------------------------------------

    def limit(self, timeout: float | None) -> float:
        if timeout is None:
            return self.config.call_timeout
        if type(timeout) in _SECONDS and 0 < timeout < math.inf:  # (most calls: no look-up)
            return float(timeout)
        check_seconds("timeout", timeout)  # (the error that names it)
        return float(timeout)

    def tell(self, message: Any) -> bool:
        try:
            self.ref.tell(message)
        except pykka.ActorDeadError:
            return False
        return True

    def ask(self, message: Asked, timeout: float | None, what: str) -> Any:
        """The actor's answer to `message`; `CallTimeoutError` names the operation `what`."""
        return blocking(self.asking(message, timeout, what))

    def asking(self, message: Asked, timeout: float | None, what: str) -> Steps[Any]:
        limit = self.limit(timeout)
        if not self.tell(message):
            raise DIRECTORY.gone_error(self.config.name) from None
        future = message.reply.future
        if not (yield future, runtime.monotonic() + limit):
            raise CallTimeoutError(f"{what} timed out after {limit:g} s")
        return future.get()

    def crash(self) -> None:
        self.ref.tell(Crash())

    def ping(self, reply: Reply) -> None:
        """A heartbeat: the actor answers `reply` once it gets to it."""
        self.tell(Ping(reply))

    def client(
        self, target_rr: str, server: str, timeout: float
    ) -> Steps[pykka.ActorRef[ClientActor]]:
        """The client actor for `target_rr/server` (the actor starts it on first use)."""
        client = self.clients.get((target_rr, server))
        if client is None or not client.is_alive():
            started: pykka.ActorRef[ClientActor] = yield from self.asking(
                OpenClient(target_rr, server, FutureReply()), timeout, "starting a client"
            )
            return started
        return client


class ResourceRegistrar(Registrar):
    """A manager's resource registrar in this process (thesis 4.3.1, `RrBase`): the
    [`Registrar`][rr_actors.Registrar] whose actor is here; its callbacks run on worker
    threads of this process (coroutine ones on its event loop)."""

    _actor: Here

    def __init__(self, launched: Launched) -> None:
        """Wrap a registrar `launch` started (use `ResourceRegistrar.start`)."""
        facts = RegistrarFacts(launched.config, launched.restored, launched.in_doubt)
        super().__init__(facts, Here(launched))

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
            setup: `setup(registrar)`, run on the calling thread after the restore, before
                it serves other registrars (their loads wait for it); if it raises, the
                registrar is stopped and the error propagates. `in_doubt` entries stay in
                the backup until it returned (`settle_in_doubt`).
            network: a carrier (any `Transport`: a `System`, a `ZenohNetwork`) to serve it
                on after `setup`, by name, until it stops or dies. `None`: this process only.

        Raises:
            DuplicateNameError: a registrar with this name is already running here, or
                (with `network`) another process of the system serves that name; it was
                stopped again.
            CatalogCorruptError: the backup exists but cannot be read (it is left as is).
            ConfigError: the configuration or its backup path is invalid; `network` is not
                a carrier or cannot serve it; or this process was forked from one with a Zenoh
                session (start it with `spawn` or `forkserver`).
            RegistrarStoppedError: this process left `network`'s system (it was closed).

        A forked child may start registrars of its own; its parent's handles raise
        `RegistrarUnavailableError` there (docs/explanation/failure-semantics.md).
        """
        check_network(network)
        registrar = start_registrar(config, setup=setup)
        if network is not None:
            serve_on(network, registrar)
        return registrar

    def subscribe(
        self,
        callback: Callable[[events.Event], object],
        *,
        maxsize: int = DEFAULT_MAXSIZE,
    ) -> Subscription[events.Event]:
        """Call `callback(event)` for every event of this registrar from now on.

        Events are the frozen dataclasses of `rr_actors.events`. The callback runs on a
        subscriber thread of its own, one event at a time in order; past `maxsize` queued,
        new ones are dropped, counted (`Subscription.dropped`) and reported (`EventsDropped`).
        `close()` the subscription it returns (or use it in a `with` block).

        Args:
            callback: `callback(event)`; what it raises is logged.
            maxsize: events queued for it before new ones are dropped.

        Raises:
            ConfigError: `callback` is not callable, or `maxsize` not a positive int.
        """
        published = self._actor.published
        return published.subscribe(callback, maxsize=maxsize, name=f"{self.name}-events")

    def tell(self, message: object) -> bool:
        """Put `message` in the registrar's mailbox without waiting: how a carrier tells it of
        its peers (`Served`). `False` once it ended; one it does not know is logged, ignored."""
        return self._actor.tell(message)

    def wait_ended(self, timeout: float | None = None) -> bool:
        """Whether it ended (stopped, or died and its death handled) within `timeout` s."""
        deadline = None if timeout is None else runtime.monotonic() + timeout
        if not self._actor.ref.actor_stopped.wait(timeout):
            return False
        left = None if deadline is None else max(0.0, deadline - runtime.monotonic())
        return self._actor.ended.wait(left)


class StatusWatch:
    """A query's status updates as an async iterator (`Registrar.watch` makes one).

    Attributes:
        query_id: the query watched.
        dropped: updates dropped because the reader fell more than `maxsize` behind.
    """

    def __init__(self, registrar: Registrar, query_id: str, maxsize: int) -> None:
        self._registrar = registrar
        self.query_id = query_id
        self._maxsize = maxsize
        self._updates: asyncio.Queue[StatusUpdate | None] | None = None  # None: closed
        self._closed = False
        self._ended = False
        self.dropped = 0

    def __repr__(self) -> str:
        return f"<StatusWatch {self.query_id!r}{' closed' if self._closed else ''}>"

    @property
    def closed(self) -> bool:
        """Whether it was closed (`aclose()`, or its `async with` left): it drops what comes."""
        return self._closed

    async def _receive(self, _query: Query, update: StatusUpdate) -> None:
        updates = self._updates
        if updates is None or self._closed:
            return
        if updates.full():
            updates.get_nowait()
            self.dropped += 1
        updates.put_nowait(update)

    async def open(self, *, timeout: float | None = None) -> StatusWatch:
        """Become the query's status callback now (the first `__anext__` does it too).

        Raises:
            UnknownQueryError: the registrar holds no such query; and as `Registrar`'s methods.
        """
        if self._updates is None:
            self._updates = asyncio.Queue(self._maxsize)
            await self._registrar.aset_status_callback(
                self.query_id, self._receive, timeout=timeout
            )
        return self

    def __aiter__(self) -> StatusWatch:
        return self

    async def __anext__(self) -> StatusUpdate:
        if self._closed or self._ended:
            raise StopAsyncIteration
        await self.open()
        assert self._updates is not None
        update = await self._updates.get()
        if update is None:  # closed while this waited (`aclose`)
            raise StopAsyncIteration
        if update.status is Status.FATAL:
            self._ended = True
        return update

    async def aclose(self) -> None:
        """Stop collecting: later updates are dropped; iteration ends, also for a waiting reader."""
        self._closed = True
        updates = self._updates
        if updates is not None:  # wake a reader waiting for the next update: it ends
            if updates.full():
                updates.get_nowait()  # (unread: a closed watch gives nothing more)
            updates.put_nowait(None)

    async def __aenter__(self) -> StatusWatch:
        return await self.open()

    async def __aexit__(self, *_: object) -> None:
        await self.aclose()


def start_registrar(
    config: RegistrarConfig | str,
    *,
    setup: Callable[[ResourceRegistrar], object] | None = None,
    upstream: Publisher[events.Event] | None = None,
    hold_in_doubt: bool = False,
    announced: bool = False,
    at_exit: bool = True,
) -> ResourceRegistrar:
    """`ResourceRegistrar.start`, its events relayed to `upstream`; `hold_in_doubt`: the caller
    settles the in-doubt entries (a manager process runs its `setup` itself); `announced`: its
    supervisor tells the system when it (re)starts (`announce_started`), so it tells no registrar
    it has no business with; `at_exit`: stopped as the main thread ends (a manager: `os._exit`)."""
    launched = launch(
        config,
        setting_up=setup is not None,
        upstream=upstream,
        hold_in_doubt=hold_in_doubt or setup is not None,
        announced=announced,
    )
    handle = ResourceRegistrar(launched)
    if at_exit:
        stop_at_exit(
            REGISTRARS,
            f"registrar {handle.name!r}",
            handle.is_alive,
            lambda timeout: handle.stop(timeout=timeout),
            provides=(handle.name,),
            holds=lambda timeout: {q.serving_rr for q in handle.client_queries(timeout=timeout)},
        )
    if setup is not None:
        try:
            setup(handle)
        except BaseException:
            handle.stop()  # (what was in doubt stays in doubt: no setup saw it through)
            raise
        try:
            handle.settle_in_doubt()
            handle._actor.ask(Ready(FutureReply()), None, "ready")
        except BaseException:
            handle.stop()  # (not left running when its start failed)
            raise
    return handle


def snapshot(registrar: ResourceRegistrar, *, timeout: float, check: bool) -> CatalogView:
    """A copy of `registrar`'s catalog made on its actor thread; `check`: its invariants
    asserted first (`testing.catalog_snapshot`)."""
    here = registrar._actor
    view: CatalogView = here.ask(
        Snapshot(check, FutureReply()),
        timeout,
        "catalog_snapshot()" if check else "a snapshot of the catalog",
    )
    return dataclasses.replace(view, in_doubt=here.in_doubt_texts)


def call_steps(
    consumer: Registrar,
    target_rr: str,
    server: str,
    request: Any,
    *,
    on_status: StatusCallback | None,
    timeout: float | None,
    query_id: str | None,
) -> Steps[Query]:
    """The steps of `consumer.call(...)`, for a protocol built on one (`call_with_retry`)."""
    actor = consumer._actor
    return actor.steps(Here.call, timeout, target_rr, server, request, on_status, query_id)


def _after(first: Steps[Any], then: Steps[T]) -> Steps[T]:
    yield from first
    return (yield from then)


def blocking(steps: Steps[T]) -> T:
    """Run `steps` on the calling thread; `ConfigError` on the process's event loop."""
    # (a thread that runs no event loop is not the process's loop: nothing to look up;
    # `_get_running_loop` is asyncio's public low-level read, in `asyncio.events.__all__`)
    if asyncio._get_running_loop() is not None and on_process_loop():
        steps.close()
        raise ConfigError(
            "a blocking registrar method was called on rr_actors' event loop (from a "
            "coroutine load, unload or status callback): await its async twin instead "
            "(acall, aunload, asend_status, ..., Supervisor.acall_with_retry)"
        )
    return run_steps(steps)


def _trace_context() -> tuple[str, str] | None:
    """The trace context a call made now carries (`traces.begin`): none until the
    application imported OpenTelemetry, as no span can be current before (one look-up)."""
    return traces.begin() if traces.API in sys.modules else None
