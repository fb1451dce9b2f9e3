"""The registrar's handle: one class wherever its actor lives, callable from any thread.

A `Registrar` is what user code holds. Its surface is written here once: each blocking
method, its awaitable twin and `watch`. Each runs one *operation* where the registrar's
actor lives, the handle's `_actor` (as pykka's one `ActorRef` puts a message into
whichever inbox its actor has):

```
 reg.call(...)        ─► blocking(       reg._actor.steps(Here.call, ...)) the thread blocks
 await reg.acall(...) ─► run_steps_async(reg._actor.steps(Here.call, ...)) the loop awaits
                                                  │
   Here: the actor in this process ───────────────┼─► Here.call(here, ...), here: send the
     (a ResourceRegistrar's)                      │   actor its message (`messages.py`;
                                                  │   `calls.py` for a call), yield the
                                                  │   future of its answer, return it
   There: in another process of the system ───────┴─► one `Run` of Here.call there, over
     (`_process/remote.py`, a RemoteRegistrar's)      the carrier; its answer wakes the
                                                      thread or the loop here
 task cancelled, KeyboardInterrupt ─► thrown in at the yield: the call is withdrawn as a
                                      timeout withdraws it (its id given back), then raised
```

An operation is a method of `Here` that returns its *steps* (`_core/replies.py`: a
generator that yields `(future, deadline)` for each wait): `run_steps` drives them on the
calling thread, `loops.run_steps_async` on the running loop, so both twins have the same
arguments, results, errors and timeouts, and no thread waits per awaited call. The names
of the twins follow the prefix Django gave its async ORM (`aget`, `asave`) and the
language its own (`anext`, `aclose`): `acall` is `call`, awaited. A protocol built on
a call (`Supervisor.call_with_retry`, `_supervision/retry.py`) takes the call's steps
(`call_steps`) among its own, and is driven the same two ways (`blocking`).

`ResourceRegistrar` is the handle on a registrar started in this process (its `start`,
`subscribe`); `rr_actors.testing.RemoteRegistrar` (`_process/remote.py`) the handle on one
in a manager process (its start, `kill`). The handle never touches the catalog itself,
and the rest of the package reaches an actor of this process only through its `Here`
(`tell`, `ask`, `wait_stopped`, `crash`, `ping`, `ref`): nothing else holds the actor's
ref or builds a message to it from a closure. Starting the actor, before there is a
handle, is `actor.py`'s (`launch`).
"""

from __future__ import annotations

import asyncio
import dataclasses
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
from rr_actors.config import RegistrarConfig, check_seconds
from rr_actors.errors import CallTimeoutError, ConfigError, RegistrarStoppedError

__all__ = [
    "STOP_WAITS_FOR_UNLOADS",
    "Here",
    "Placement",
    "Registrar",
    "RegistrarFacts",
    "ResourceRegistrar",
    "StatusWatch",
    "blocking",
    "call_steps",
    "snapshot",
    "start_registrar",
]

T = TypeVar("T")
P = ParamSpec("P")

STOP_WAITS_FOR_UNLOADS = 0.5
"""The share of `stop()`'s timeout it waits for the unloads under way (the rest is left
to write the backup and stop the servers): 5 s with the default `call_timeout`."""


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
    ) -> Steps[T]:
        """The steps of the operation `op(here, timeout, *args)`, run where the actor is."""
        ...

    def stop(self, timeout: float | None) -> Steps[None]:
        """The steps of stopping the registrar (rule 12); a stopped one is a no-op."""
        ...

    def is_alive(self) -> bool:
        """Whether the registrar is running."""
        ...

    def state(self) -> str:
        """What the handle's `repr` says of it ("running", a pid; or nothing)."""
        ...


class Registrar:
    """A handle on a registrar, wherever its actor lives: in this process or in another.

    Its methods may be called from any thread, including from inside callbacks; each
    waits for the registrar at most `timeout` seconds (default: the config's
    `call_timeout`) and raises `CallTimeoutError` when they run out. Each has an
    awaitable twin for event loops (`acall`, `aunload`, ..., `watch`): the same
    operation, errors and timeout, awaited from any running event loop, any number at
    once, with no thread held while it waits. Cancelling the awaiting task withdraws
    what it waits for as its timeout would: a cancelled `acall` gives its query id back
    (if its load completes later, the id is released; nothing is left held) and raises
    `asyncio.CancelledError`; a cancelled `aunload`, `asend_status`, ... stops waiting
    for what was already sent, exactly as one that timed out.

    A registrar of this process is a [`ResourceRegistrar`][rr_actors.ResourceRegistrar],
    one in a manager process a
    [`RemoteRegistrar`][rr_actors.testing.RemoteRegistrar]: code written against
    `Registrar` (an application's actions, `Supervisor.call_with_retry`) does not change
    between them. For the latter, arguments, callbacks and results cross processes
    cloudpickled (callbacks may be closures) and callbacks run in the registrar's
    process, on the threads a registrar there would use.
    """

    _actor: Placement

    def __init__(self, facts: RegistrarFacts, actor: Placement) -> None:
        """Made by a kind of handle (`ResourceRegistrar`, `RemoteRegistrar`), with where
        its actor lives; user code starts or reaches a registrar through those."""
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

    def is_alive(self) -> bool:
        """Whether the registrar is running (for the owner of a manager process: it)."""
        return self._actor.is_alive()

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
        blocking(self._actor.steps(Here.settle_in_doubt, timeout, query_id))

    async def asettle_in_doubt(
        self, query_id: str | None = None, *, timeout: float | None = None
    ) -> None:
        """`settle_in_doubt`, awaited (rule 16): for a `setup` that cleans up what the
        in-doubt loads started with coroutines of its own (`asyncio.run` inside it), and
        settles each entry as its clean-up ends, without holding up the others.

        Raises what `settle_in_doubt` raises.
        """
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

        Under overload, its loads queued or running are bounded by `max_pending` (a call
        past it waits and asks again within its timeout, then gets `OverloadedError`),
        and a queued load whose caller's timeout
        would run out before it ends (by what its recent loads took) fails at once with
        `DeadlineExceededError` without running.

        Args:
            name: server name, unique on this registrar.
            load: `load(request) -> response`; runs on a worker thread of the registrar's
                process.
            unload: `unload(request, response) -> None`; runs on a worker thread, after the
                resource's dependencies were released.
            on_status: `on_status(query, update)`, run once on a worker thread when a status
                about one of this server's resources is sent or passes through.
            timeout: seconds to wait for the registrar.
            label: `label(request) -> str`, a short name for a resource that the observer
                shows (`lidar2` rather than the whole request). It runs once per resource,
                when its load starts, on a worker thread of the registrar's process,
                bounded by `RegistrarConfig.compare_timeout`; the text is kept in the
                catalog (and its backup), cut to 40 characters. If it raises (anything,
                `SystemExit` included), returns something else than a `str` or overruns
                the bound, the label reads `<label failed: ...>`; the load is not
                affected, but a load that ends first waits for its label (at most that
                bound) while someone listens to events, so that its
                `ResourceLoaded.label` is this one. Without it, the observer shows what
                tells the server's requests apart.
            max_pending: new loads this server may have queued or running at once
                (an int >= 1); `None`: the registrar's `RegistrarConfig.max_pending`
                (default 1000). A server whose loads are heavy (memory, a device) takes
                a small one; a dedup hit, or a call joining a load under way, is never
                refused.

        Raises:
            ConfigError: a callback is not callable (or, to a registrar in another
                process, does not pickle), the name is invalid, or `max_pending` is not
                an int >= 1 (nor `None`).
            DuplicateNameError: a server with this name exists on this registrar.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
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
        """`register_server`, awaited.

        `load`, `unload` and `on_status` may be coroutine functions (`async def`): they
        then run on the event loop of the registrar's process (one thread for all of
        them), a slow one awaiting without holding a thread; plain ones run on worker
        threads. Either kind may be registered through either twin.

        Raises what `register_server` raises, and `ConfigError` when `label` is a coroutine
        function.
        """
        steps = self._actor.steps(
            Here.register_server, timeout, name, load, unload, on_status, label, max_pending
        )
        await run_steps_async(steps)

    def unregister_server(self, name: str, *, timeout: float | None = None) -> None:
        """Remove a server: send `FATAL` to its consumers and unload all it serves (rule 12).

        Raises:
            UnknownServerError: no such server here.
            CallTimeoutError: not finished within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        blocking(self._actor.steps(Here.unregister_server, timeout, name))

    async def aunregister_server(self, name: str, *, timeout: float | None = None) -> None:
        """`unregister_server`, awaited (rule 12): the same errors."""
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

        The provider runs `load(request)` unless an equal (`==`) request is loaded or
        loading there; either way this call becomes one more consumer with its own id.
        Made from inside a `load` callback (of any process), the call carries that load's
        context: the query is recorded as a dependency of the resource being loaded when
        that load runs on this registrar, and is part of its chain for cycle detection.
        Made while an OpenTelemetry span is current (the `otel` extra), the call carries
        its W3C trace context to the provider: `rr_actors.otel` makes its spans that
        span's children, and the provider's `load` runs under them.

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
            if_overloaded: what a call refused because the server has its
                `max_pending` loads does: `"wait"` (pause as long as the provider says,
                its `retry_after`, and ask again while `timeout` lasts) or `"raise"`
                (`OverloadedError` at once, for a caller that cannot wait; nothing is
                held at the provider).

        Returns:
            The `Query`, with the provider's `response` (in one process, the very object
            `load` returned, shared by every consumer: treat it as read-only).

        Raises:
            ResourceLoadError: `load` raised here or further down; `stack` says where.
            DependencyCycleError: the load would wait for itself further up its chain.
            UnknownServerError: no such registrar or server.
            CallTimeoutError: no answer in time; the query id is released if it loads later.
            OverloadedError: the server has its `max_pending` loads, and this caller does
                not wait (`if_overloaded="raise"`) or its time left is too short for
                another try; nothing is held.
            RegistrarUnavailableError: the provider died (it may have executed the load).
            RegistrarStoppedError: this registrar or the provider was stopped.
            ConfigError: `target_rr` or `server` is not a str, `query_id` not a
                non-empty str, `on_status` not callable, `if_overloaded` neither `"wait"`
                nor `"raise"`; or the request, or the response,
                cannot be pickled where it must be: across processes, or into this
                registrar's backup (its client record); the provider then holds nothing.
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
        """`call`, awaited (rules 1-6, 17): the provider's answer wakes the loop.

        Awaited inside a coroutine `load` of this registrar, the query is recorded as a
        dependency of the resource being loaded, as `call` inside a plain `load` is.
        `on_status` may be a coroutine function: it then runs on the loop this call was
        awaited from, one update at a time (see `StatusWatch` for an iterator instead).

        Raises what `call` raises, and `asyncio.CancelledError` when the awaiting task is
        cancelled: the call is then withdrawn as a timed-out one is (nothing is left held).
        """
        steps = self._actor.steps(
            Here.call, timeout, target_rr, server, request, on_status, query_id, if_overloaded
        )
        return await run_steps_async(steps)

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
        blocking(self._actor.steps(Here.unload, timeout, query_id))

    async def aunload(self, query_id: str, *, timeout: float | None = None) -> None:
        """`unload`, awaited (rules 7-8): the same errors."""
        await run_steps_async(self._actor.steps(Here.unload, timeout, query_id))

    def send_status(
        self, query_id: str, status: Status, message: str = "", *, timeout: float | None = None
    ) -> StatusDelivery:
        """Tell every consumer of the resource behind `query_id` about its status (rule 9).

        This server's `on_status` runs once; each consumer's status callback runs with its
        own query id, on a worker thread of the consumer's process (a coroutine one: on its
        loop); the status climbs every dependency path to the top consumers. Returns once
        every callback on the way has run, or was given up on: a consumer's callback
        (plain or coroutine) that has not returned within the patience (half of `timeout`,
        or all of it but 1 s if that is more), and at once while its id's earlier callback
        is still given up on. A given-up id's statuses queue behind its callback, coalesced
        (its latest, and every `FATAL`, in arrival order), and run once it returns. A
        server's own `on_status` (this one's, and those up the dependency paths) is never
        given up on: it is waited for, within `timeout`; its statuses queue behind it,
        each run once, in order (one thread held, not one of its registrar's workers each).

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
            MessageTooLargeError: the status is over the `max_message_bytes` of a
                consumer registrar in another process (named): that one did not hear it,
                the others did (a `FATAL` still marks the resource, rule 1).
            CallTimeoutError: not delivered everywhere within `timeout` seconds (a
                consumer's process that did not answer; a server's `on_status` on the way
                that did not return: those are not given up on).
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        steps = self._actor.steps(Here.send_status, timeout, query_id, status, message)
        delivery: StatusDelivery = blocking(steps)
        return delivery

    async def asend_status(
        self, query_id: str, status: Status, message: str = "", *, timeout: float | None = None
    ) -> StatusDelivery:
        """`send_status`, awaited (rule 9): done once every callback on the way has run
        (a coroutine one: once it returned) or was given up on.

        Returns and raises what `send_status` does.
        """
        steps = self._actor.steps(Here.send_status, timeout, query_id, status, message)
        delivery: StatusDelivery = await run_steps_async(steps)
        return delivery

    def server_queries(self, server: str, *, timeout: float | None = None) -> list[Query]:
        """Every consumer query of this registrar's `server`, each id once (rule 10).

        Its subscribers hear the answer's ids (`events.ServerQueriesListed`).

        Raises:
            UnknownServerError: no such server here.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        return blocking(self._actor.steps(Here.server_queries, timeout, server))

    async def aserver_queries(self, server: str, *, timeout: float | None = None) -> list[Query]:
        """`server_queries`, awaited (rule 10): the same errors."""
        return await run_steps_async(self._actor.steps(Here.server_queries, timeout, server))

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
        return blocking(self._actor.steps(Here.fetch_queries, timeout, target_rr, server))

    async def afetch_queries(
        self, target_rr: str, server: str, *, timeout: float | None = None
    ) -> list[Query]:
        """`fetch_queries`, awaited (rule 10): the same errors."""
        steps = self._actor.steps(Here.fetch_queries, timeout, target_rr, server)
        return await run_steps_async(steps)

    def client_queries(self, *, timeout: float | None = None) -> list[Query]:
        """Every query this registrar holds at servers (its own included), oldest first.

        Raises:
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        return blocking(self._actor.steps(Here.client_queries, timeout))

    async def aclient_queries(self, *, timeout: float | None = None) -> list[Query]:
        """`client_queries`, awaited: the same errors."""
        return await run_steps_async(self._actor.steps(Here.client_queries, timeout))

    def set_status_callback(
        self, query_id: str, callback: StatusCallback, *, timeout: float | None = None
    ) -> None:
        """Attach (or replace) the client status callback of a query this registrar holds.

        Status callbacks are code, so they are not in the backup: re-attach them after a
        restart (rule 11). The callback runs in the registrar's process.

        Raises:
            UnknownQueryError: this registrar holds no such query.
            ConfigError: `callback` is not callable (or, to a registrar in another
                process, does not pickle).
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        blocking(self._actor.steps(Here.set_status_callback, timeout, query_id, callback))

    async def aset_status_callback(
        self, query_id: str, callback: StatusCallback, *, timeout: float | None = None
    ) -> None:
        """`set_status_callback`, awaited (rule 11); a coroutine `callback` runs on the
        loop this was awaited from.

        Raises what `set_status_callback` raises.
        """
        steps = self._actor.steps(Here.set_status_callback, timeout, query_id, callback)
        await run_steps_async(steps)

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
            ConfigError: the response cannot be pickled and this registrar keeps a backup
                (nothing changes), or a consumer registrar of this process that keeps one
                refused it (its client record keeps the old response, as below).
            MessageTooLargeError: the response is over the `max_message_bytes` of a
                consumer registrar in another process (named): its client record keeps
                the old response; this registrar's catalog and the others have the new.
            CallTimeoutError: not delivered within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        blocking(self._actor.steps(Here.update_response, timeout, query_id, response))

    async def aupdate_response(
        self, query_id: str, response: Any, *, timeout: float | None = None
    ) -> None:
        """`update_response`, awaited (rule 11): the same errors."""
        steps = self._actor.steps(Here.update_response, timeout, query_id, response)
        await run_steps_async(steps)

    def save_catalog(self, *, timeout: float | None = None) -> None:
        """Write every pending change of the catalog to the backup now (no-op without one).

        Raises:
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: this registrar was stopped.
            RegistrarUnavailableError: this registrar died.
        """
        blocking(self._actor.steps(Here.save_catalog, timeout))

    async def asave_catalog(self, *, timeout: float | None = None) -> None:
        """`save_catalog`, awaited: the same errors."""
        await run_steps_async(self._actor.steps(Here.save_catalog, timeout))

    def stop(self, *, timeout: float | None = None) -> None:
        """Stop the registrar (rule 12); for the owner of a manager process, the process too.

        Unloads everything it holds as a consumer (newest first), waits for the unloads of
        its own resources that are under way (their `unload` callbacks running, on worker
        threads) until `STOP_WAITS_FOR_UNLOADS` of `timeout` has passed, then stops its servers
        and clients. An unload still under way then is cut short: it stops anyway and
        publishes `events.UnloadCutShort`; that resource stays in the backup as unloading
        (in doubt at the next start, rule 16). What its servers serve stays in the
        catalog for a restart. With `erase_on_destruct` the backup is removed. Stopping a
        stopped (or dead) registrar is a no-op.

        Args:
            timeout: seconds the whole stop may take (`None`: the registrar's
                `call_timeout`); the owner of a manager process kills it after that.

        Raises:
            CallTimeoutError: not finished within `timeout` seconds (a manager process
                was killed).
            RegistrarUnavailableError: the registrar died (or its process exited) while it
                stopped; the reason is in the message.
        """
        blocking(self._actor.stop(timeout))

    async def astop(self, *, timeout: float | None = None) -> None:
        """`stop`, awaited (rule 12): the same errors."""
        await run_steps_async(self._actor.stop(timeout))

    def watch(self, query_id: str, *, maxsize: int = 256) -> StatusWatch:
        """The status updates of query `query_id`, as an async iterator.

        ```python
        async for update in reg.watch(query.id):   # rr.StatusUpdate, in order
            print(update.status, update.message)
        ```

        Once opened (its first step, or `async with`) it is the query's status callback
        (it replaces the one the call was made with, as `aset_status_callback` does).
        Iteration ends after a `FATAL` (the resource is gone for good, rule 19) or once
        the watch is closed (`aclose()`, or leaving its `async with` block; a closed
        watch drops what comes; `closed` says whether it is). An `async for` that
        breaks, or whose task is cancelled (a stream whose client left), leaves it
        open: use `async with` to close it. It does not end when the query is
        released: its reader decides when to stop. Updates are queued for it on the
        loop it was opened on; past `maxsize` the oldest is dropped (and counted in
        `dropped`), so a reader that falls behind never holds the registrar.

        Args:
            query_id: a query this registrar holds (from `call` or `acall`).
            maxsize: updates kept for a reader that falls behind.

        Returns:
            The watch: iterate it with `async for` from a coroutine on one loop.

        Raises:
            ConfigError: the registrar runs in another process (watch from a registrar
                of this process that holds the query, or register a status callback
                there: `aset_status_callback`, it runs in the registrar's process); or
                `maxsize` is not a positive int (at once). The first step of the
                iteration raises what `aset_status_callback` raises (an unknown id:
                `UnknownQueryError`).
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
    """The actor in this process (a `ResourceRegistrar`'s): its ref, the call protocol on
    the caller's thread (`calls.py`), its client actors; an operation's steps run here."""

    def __init__(self, launched: Launched) -> None:
        config = launched.config
        self.config = config
        self.ref: pykka.ActorRef[RegistrarActor] = launched.ref
        self.clients = launched.clients  # one cache: the actor starts, the handle looks up
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
        """`op`'s steps, here (on the thread or loop that drives them)."""
        return op(self, timeout, *args, **kwargs)

    def is_alive(self) -> bool:
        """Whether the registrar actor is running."""
        return self.ref.is_alive()

    def state(self) -> str:
        """What the handle's `repr` says: "running" or "stopped"."""
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
        if if_overloaded not in ("wait", "raise"):
            raise ConfigError(f"if_overloaded must be 'wait' or 'raise', got {if_overloaded!r}")
        if not (isinstance(target_rr, str) and isinstance(server, str)):
            _check_names(target_rr=target_rr, server=server)
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
        if self.config.backup_path is not None:  # its client record is stored
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
            traces.begin(),  # (in the caller's thread or task: its OpenTelemetry context)
            wait_overloaded=if_overloaded == "wait",
        )
        client = self.clients.get(target_rr, server)
        if client is None or not client.is_alive():  # (it exists from the first call)
            return _after(self.client(target_rr, server, limit), steps)
        return steps

    def unload(self, timeout: float | None, query_id: str) -> Steps[None]:
        release = Release(query_id, FutureReply(), traces.begin())
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
        _check_names(target_rr=target_rr, server=server)
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
        if self.config.backup_path is not None:  # the catalog stores it
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
        """`timeout`, checked, or the registrar's `call_timeout` for `None`."""
        if timeout is None:
            return self.config.call_timeout
        check_seconds("timeout", timeout)
        return float(timeout)

    def tell(self, message: Any) -> bool:
        """Send the actor `message` without waiting; whether the actor was running."""
        try:
            self.ref.tell(message)
        except pykka.ActorDeadError:
            return False
        return True

    def ask(self, message: Asked, timeout: float | None, what: str) -> Any:
        """Send the actor `message` and wait at most `timeout` seconds for its answer.

        Raises:
            CallTimeoutError: no answer in time (`what` names the operation).
            RegistrarStoppedError, RegistrarUnavailableError: it was stopped, or it died.
            RrError: the error the actor answered with.
        """
        return blocking(self.asking(message, timeout, what))

    def asking(self, message: Asked, timeout: float | None, what: str) -> Steps[Any]:
        """`ask`'s steps: send `message`, wait for its answer."""
        limit = self.limit(timeout)
        if not self.tell(message):
            raise DIRECTORY.gone_error(self.config.name) from None
        future = message.reply.future
        if not (yield future, runtime.monotonic() + limit):
            raise CallTimeoutError(f"{what} timed out after {limit:g} s")
        return future.get()

    def wait_stopped(self, timeout: float | None = None) -> bool:
        """Block until the actor's thread ended (stopped, or died and its death handled:
        its backup closed, its callers answered); whether it did within `timeout` s.

        pykka marks an actor stopped before its `on_failure` runs: a supervisor that
        restarted a crashed registrar at that mark had the old one's backup still open.
        """
        deadline = None if timeout is None else runtime.monotonic() + timeout
        if not self.ref.actor_stopped.wait(timeout):
            return False
        left = None if deadline is None else max(0.0, deadline - runtime.monotonic())
        return self.ended.wait(left)

    def crash(self) -> None:
        """Make the actor die as if a bug hit it (`testing.crash`, a forced stop)."""
        self.ref.tell(Crash())

    def ping(self, reply: Reply) -> None:
        """Ask the actor to answer `reply` (`None`) once it gets to it (a heartbeat)."""
        self.tell(Ping(reply))

    def client(
        self, target_rr: str, server: str, timeout: float
    ) -> Steps[pykka.ActorRef[ClientActor]]:
        """The client actor for `target_rr/server`, asked of the actor on first use."""
        client = self.clients.get(target_rr, server)
        if client is None or not client.is_alive():
            started: pykka.ActorRef[ClientActor] = yield from self.asking(
                OpenClient(target_rr, server, FutureReply()), timeout, "starting a client"
            )
            return started
        return client


class ResourceRegistrar(Registrar):
    """A manager's resource registrar in this process (thesis 4.3.1, `RrBase`).

    Start one with [`ResourceRegistrar.start`][rr_actors.ResourceRegistrar.start]. It is
    the one handle, [`Registrar`][rr_actors.Registrar], whose actor is here; its
    callbacks run on worker threads of this process (coroutine ones on its event loop).
    """

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
        published = self._actor.published
        return published.subscribe(callback, maxsize=maxsize, name=f"{self.name}-events")


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
        """Whether it was closed (`aclose()`, or its `async with` block was left): it
        then drops every update that comes. An iteration that ended after a `FATAL`
        leaves it open until then."""
        return self._closed

    async def _receive(self, _query: Query, update: StatusUpdate) -> None:
        """The query's status callback, on the watch's loop."""
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
            UnknownQueryError: the registrar holds no such query.
            CallTimeoutError: no answer within `timeout` seconds.
            RegistrarStoppedError: the registrar was stopped.
            RegistrarUnavailableError: the registrar died.
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
        """Stop collecting: updates that come later are dropped; iteration ends, also
        for a reader that waits for the next update (in another task of the loop)."""
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
    """A consistent copy of `registrar`'s catalog rows and servers, made on its actor thread.

    For `rr_actors.testing.catalog_snapshot` (with `check`: the catalog's invariants are
    checked first) and the observer (without). Runs on the caller's thread, in the
    registrar's process; the actor is held for the copy only.

    Raises:
        AssertionError: with `check`, an index of the catalog disagrees with its rows.
        CallTimeoutError: no answer within `timeout` seconds.
        RegistrarStoppedError, RegistrarUnavailableError: it was stopped, or it died.
    """
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
    """The steps `consumer.call(...)` runs blocking and `acall` awaits, for a protocol
    built on a call that drives them among its own (`Supervisor.call_with_retry` and its
    twin, `_supervision/retry.py`).

    Raises:
        ConfigError: an argument is invalid (at once; see `Registrar.call`).
    """
    actor = consumer._actor
    return actor.steps(Here.call, timeout, target_rr, server, request, on_status, query_id)


def _after(first: Steps[Any], then: Steps[T]) -> Steps[T]:
    """The steps of `first`, then those of `then` (its result)."""
    yield from first
    return (yield from then)


def blocking(steps: Steps[T]) -> T:
    """Run an operation's `steps` on the calling thread (`replies.run_steps`): each
    blocking method of the handle, and `Supervisor.call_with_retry`, which is built on
    `call_steps`.

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
            "(acall, aunload, asend_status, ..., Supervisor.acall_with_retry)"
        )
    return run_steps(steps)


def _check_names(**names: object) -> None:
    """`ConfigError` naming the first argument that is not a str (a registrar's or a
    server's name): refused here, before anything is sent or recorded."""
    for field, value in names.items():
        if not isinstance(value, str):
            raise ConfigError(f"{field} must be a name (a str), got {value!r}")
