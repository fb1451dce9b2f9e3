"""Helpers for testing code built on rr_actors (and rr_actors itself).

Placement-independent helpers: [`crash`][rr_actors.testing.crash] and
[`catalog_snapshot`][rr_actors.testing.catalog_snapshot] accept a `ResourceRegistrar` (a
registrar in this process) or a [`RemoteRegistrar`][rr_actors.testing.RemoteRegistrar] (a
registrar in a manager process of a system). A `RemoteRegistrar` has the methods of a
`ResourceRegistrar`, so one test body exercises both placements.

State that a test shares with callbacks which may run in another process (journals,
events, barriers) comes from [`SharedObjects`][rr_actors.testing.SharedObjects].

Seams for tests that must make a race happen on purpose, or look at what a registrar
still waits for. They name the registrar's steps (`intercept`) and what it holds
(`pending_work`) in words that are part of this module's contract, so a test never
reaches into private handler tables, and renaming a step breaks such a test loudly
(`ConfigError`) instead of turning it into a test that races nothing:

- [`run_on_actor`][rr_actors.testing.run_on_actor]: run code on a registrar's actor
  thread (hold it busy at a chosen moment);
- [`intercept`][rr_actors.testing.intercept]: run hooks before or after one of its named
  steps ([`STEPS`][rr_actors.testing.STEPS]);
- [`call_futures`][rr_actors.testing.call_futures]: choose the future class its callers
  wait on (to make an answer race a timeout);
- [`pending_work`][rr_actors.testing.pending_work]: what it still waits for;
- [`expect_restart`][rr_actors.testing.expect_restart]: say a restart is coming, as a
  supervisor does (no death watch when the registrar dies).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import threading
from collections.abc import Callable, Iterator
from multiprocessing.managers import BaseProxy, SyncManager
from typing import Any, TypeVar

import cloudpickle
import pykka

from rr_actors._core.actor import OneShotFuture
from rr_actors._core.directory import DIRECTORY, LocalPeer, Reply
from rr_actors._core.replies import FutureReply, wait
from rr_actors._process.manager import mp_context
from rr_actors._process.remote import FORWARD_MARGIN, RemoteRegistrar
from rr_actors._registrar import ResourceRegistrar
from rr_actors._registrar.actor import RegistrarActor
from rr_actors._registrar.lifecycle import CatalogView
from rr_actors._registrar.messages import Crash, Request
from rr_actors._registrar.probes import STEPS, Hook, Probes
from rr_actors.errors import ConfigError, RegistrarUnavailableError

__all__ = [
    "STEPS",
    "CatalogView",
    "Installed",
    "PendingWork",
    "Records",
    "RemoteRegistrar",
    "SharedObjects",
    "actor_ref",
    "call_futures",
    "catalog_snapshot",
    "crash",
    "expect_restart",
    "intercept",
    "pending_work",
    "run_on_actor",
    "running_actors",
]

T = TypeVar("T")


# -- placement-independent helpers -----------------------------------------------------


def crash(registrar: ResourceRegistrar | RemoteRegistrar, *, timeout: float = 5.0) -> None:
    """Make a registrar die as if it hit a bug: no cleanup the way `stop()` would do it.

    For a `ResourceRegistrar` its actor dies (the in-process analogue of SIGKILL); for a
    `RemoteRegistrar` its manager process gets SIGKILL. Either way its callers get
    `RegistrarUnavailableError`, its backup keeps what was written, and unless a supervisor
    will restart it, the providers release its consumer ids (death watch). Returns once it
    is dead and the providers were told.

    Args:
        registrar: the registrar to kill.
        timeout: seconds to wait for its death.
    """
    if isinstance(registrar, RemoteRegistrar):
        registrar.kill(timeout=timeout)
        return
    registrar._ref.tell(Crash())
    registrar._died.wait(timeout)  # the actor's death handling ran, death watch included


def catalog_snapshot(
    registrar: ResourceRegistrar | RemoteRegistrar, *, timeout: float = 5.0
) -> CatalogView:
    """A copy of the registrar's catalog rows, after checking the catalog's invariants.

    Args:
        registrar: a registrar of this process, or a `RemoteRegistrar` (the snapshot is
            taken in its process and sent back).
        timeout: seconds to wait for the registrar.

    Raises:
        AssertionError: an index of the catalog disagrees with its rows.
        CallTimeoutError: no answer within `timeout` seconds.
        RegistrarUnavailableError: the registrar died.
    """
    if isinstance(registrar, RemoteRegistrar):
        snapshot = functools.partial(catalog_snapshot, timeout=timeout)
        remote: CatalogView = registrar.run(snapshot, timeout=timeout + FORWARD_MARGIN)
        return remote
    reply = FutureReply()
    registrar._ref.tell(Request(lambda actor, r: actor.lifecycle.op_snapshot(r), reply))
    view: CatalogView = wait(reply.future, timeout, "catalog_snapshot()")
    return view


def running_actors() -> list[Any]:
    """The pykka actors still running in this process."""
    return list(pykka.ActorRegistry.get_all())


# -- seams for making races happen on purpose -------------------------------------------


def _local(registrar: ResourceRegistrar | RemoteRegistrar, what: str) -> ResourceRegistrar:
    if isinstance(registrar, RemoteRegistrar):
        raise ConfigError(
            f"{what} needs a registrar of this process; for a RemoteRegistrar, call it "
            "inside the registrar's process (`registrar.run(fn)` or `Supervisor.run_in`)"
        )
    return registrar


def _ask_actor(
    ref: pykka.ActorRef[Any], op: Callable[[RegistrarActor, Reply], None]
) -> FutureReply:
    reply = FutureReply()
    try:
        ref.tell(Request(op, reply))
    except pykka.ActorDeadError:
        reply.set_error(RegistrarUnavailableError("the registrar actor is not running"))
    return reply


def run_on_actor(registrar: ResourceRegistrar, fn: Callable[[], T]) -> pykka.Future[T]:
    """Run `fn()` on the registrar's actor thread, in order with the messages it handles.

    While `fn` runs the registrar handles nothing else: a test holds a registrar busy at a
    chosen moment this way (`fn` waits on an event the test sets later).

    Args:
        registrar: a registrar of this process.
        fn: runs on the actor's thread; what it returns (or raises) settles the future.

    Returns:
        A future of `fn`'s result (`get(timeout=...)`).

    Raises:
        ConfigError: `registrar` is a `RemoteRegistrar` (call this in its process).
    """
    local = _local(registrar, "run_on_actor")

    def op(_actor: RegistrarActor, reply: Reply) -> None:
        try:
            result = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test through the future
            reply.set_error(exc)
        else:
            reply.set_result(result)

    future: pykka.Future[T] = _ask_actor(local._ref, op).future
    return future


def actor_ref(
    registrar: ResourceRegistrar, *, client: tuple[str, str] | None = None
) -> pykka.ActorRef[Any]:
    """The pykka `ActorRef` of the registrar's actor, or of one of its client actors.

    Args:
        registrar: a registrar of this process.
        client: `(target registrar, server)`: the ref of the client actor the registrar
            uses for that server (it exists once the registrar has called it).

    Raises:
        ConfigError: `registrar` is a `RemoteRegistrar`, or it has no such client.
    """
    local = _local(registrar, "actor_ref")
    if client is None:
        return local._ref
    ref = local._clients.get(client)
    if ref is None:
        raise ConfigError(f"registrar {local.name!r} has no client for {client!r}")
    return ref


class Installed:
    """What `intercept` or `call_futures` installed; `close()` takes it away again.

    Also a context manager: `with intercept(registrar, "abandon", before=hold): ...`.
    """

    def __init__(self, undo: Callable[[], None]) -> None:
        self._undo: Callable[[], None] | None = undo

    def close(self) -> None:
        """Take it away (idempotent)."""
        undo, self._undo = self._undo, None
        if undo is not None:
            undo()

    def __enter__(self) -> Installed:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


def intercept(
    registrar: ResourceRegistrar,
    step: str,
    *,
    before: Hook | None = None,
    after: Hook | None = None,
) -> Installed:
    """Run `before(subject)` and `after(subject)` around one of a registrar's named steps.

    A message step (`"load"`, `"abandon"`, `"pending"`, `"client_loaded"`, ...) runs its
    hooks on the registrar's actor thread around the handling of that message; `subject`
    is the message (its fields, such as `query_id`, are stable). A point
    (`"unload_resource"`, `"close_resource"`, `"stop_drained"`, and on the caller's
    thread `"send_load"` and `"withdraw"`) runs them where it is reached. `STEPS` lists every name
    with what it is. A hook that blocks holds the registrar there; one that raises fails
    that step as a bug would.

    Args:
        registrar: a registrar of this process.
        step: the step's name, one of `STEPS`.
        before: runs before the step (or at the point).
        after: runs after the step (or at the point, after `before`).

    Returns:
        The installed hooks; `close()` them (or use a `with` block).

    Raises:
        ConfigError: no step has that name, or `registrar` is a `RemoteRegistrar`.
    """
    local = _local(registrar, "intercept")
    if step not in STEPS:
        raise ConfigError(f"no registrar step is named {step!r}; steps: {sorted(STEPS)}")
    probes = local._probes
    if probes is None:
        probes = Probes()
        installed = probes

        def install(actor: RegistrarActor, reply: Reply) -> None:
            actor.shared.probes = installed
            reply.set_result(None)

        wait(_ask_actor(local._ref, install).future, 10.0, "installing probes")
        local._probes = probes
    probes.add(step, before=before, after=after)
    return Installed(functools.partial(probes.remove, step, before=before, after=after))


def call_futures(registrar: ResourceRegistrar, future_type: type[OneShotFuture[Any]]) -> Installed:
    """Make the registrar's callers wait on `future_type` futures until `close()`.

    A caller waits for its answer on a one-shot future that the answering thread settles,
    or that the caller claims when its time runs out (see
    `docs/explanation/failure-semantics.md`). A subclass that overrides `wait`, `claim`,
    `reserve`, `set` or `set_exception` to wait on events makes an answer race a timeout
    at a chosen instant.

    Returns:
        What was installed; `close()` it, or use it as a context manager.

    Raises:
        ConfigError: `registrar` is a `RemoteRegistrar`, or `future_type` is not a
            subclass of the one-shot future.
    """
    local = _local(registrar, "call_futures")
    if not (isinstance(future_type, type) and issubclass(future_type, OneShotFuture)):
        raise ConfigError(f"future_type must subclass OneShotFuture, got {future_type!r}")
    calls = local._calls
    before, calls.future_type = calls.future_type, future_type
    return Installed(lambda: setattr(calls, "future_type", before))


@contextlib.contextmanager
def expect_restart(name: str) -> Iterator[None]:
    """While the block runs, registrar `name` dying is not a consumer gone for good.

    A supervisor says so for every child it will restart: the providers then keep the
    dead registrar's consumer ids for its restored catalog (no death watch).
    """
    known = name in DIRECTORY.restart_expected
    DIRECTORY.restart_expected.add(name)
    try:
        yield
    finally:
        if not known:
            DIRECTORY.restart_expected.discard(name)


@dataclasses.dataclass(frozen=True)
class PendingWork:
    """What a registrar still waits for, as query ids (a snapshot from its actor thread).

    Attributes:
        waiting_loads: callers waiting for a load here (including loads parked behind an
            unload of an equal request, and loads whose request is being compared off
            the actor thread); an id counted twice is a retry with the same id.
        held_loads: loads held until `setup` registers their server.
        answers_due: its own calls whose answer it has not recorded yet.
        parked_notices: its queries whose notices wait for their answer.
        open_requests: handle requests it has not answered yet.
        queued_callbacks: callbacks (loads, unloads, status callbacks, comparisons of
            requests) waiting for a worker thread, all `max_workers` being busy.
    """

    waiting_loads: collections.Counter[str]
    held_loads: tuple[str, ...]
    answers_due: frozenset[str]
    parked_notices: frozenset[str]
    open_requests: int
    queued_callbacks: int = 0


def _pending_work(actor: RegistrarActor, reply: Reply) -> None:
    provider, consumer = actor.provider, actor.consumer
    ids = [w.query_id for waiters in provider.loads.values() for w in waiters]
    ids += [load.query_id for loads in provider.after_unload.values() for load in loads]
    ids += [load.query_id for load in provider.matching.waiting()]
    reply.set_result(
        PendingWork(
            waiting_loads=collections.Counter(ids),
            held_loads=tuple(load.query_id for load in provider.held_loads),
            answers_due=consumer.due.ids(),
            parked_notices=frozenset(consumer.parked_notices),
            open_requests=len(actor.lifecycle.open_requests) - 1,  # (not this request)
            queued_callbacks=actor.shared.workers.queued,
        )
    )


def pending_work(
    registrar: ResourceRegistrar | RemoteRegistrar | str, *, timeout: float = 5.0
) -> PendingWork:
    """What a registrar still waits for (asked on its actor thread, in mailbox order).

    Args:
        registrar: a registrar of this process, a `RemoteRegistrar` (asked in its
            process), or the name of a registrar of this process that is still starting
            (its `setup` runs, so no handle was returned yet).
        timeout: seconds to wait for the answer.

    Raises:
        CallTimeoutError: no answer within `timeout` seconds.
        RegistrarUnavailableError: the registrar is not running.
    """
    if isinstance(registrar, RemoteRegistrar):
        remote: PendingWork = registrar.run(
            functools.partial(pending_work, timeout=timeout), timeout=timeout + FORWARD_MARGIN
        )
        return remote
    if isinstance(registrar, str):
        peer = DIRECTORY.lookup(registrar)
        if not isinstance(peer, LocalPeer) or peer.ref is None:
            raise RegistrarUnavailableError(f"registrar {registrar!r} is not running here")
        ref = peer.ref
    else:
        ref = registrar._ref
    work: PendingWork = wait(_ask_actor(ref, _pending_work).future, timeout, "pending_work()")
    return work


# -- state shared with callbacks in other processes ------------------------------------


class _RecordsState:
    """The server side of a `Records` list: cloudpickled items, in order."""

    def __init__(self) -> None:
        self._items: list[bytes] = []
        self._lock = threading.Lock()

    def append(self, item: bytes) -> None:
        with self._lock:
            self._items.append(item)

    def items(self) -> list[bytes]:
        with self._lock:
            return list(self._items)

    def __len__(self) -> int:
        return len(self._items)


class Records(BaseProxy):
    """An append-only list shared between processes (a `multiprocessing` proxy).

    Reads return copies: iterating, indexing, `len` and `==` (with a list or another
    `Records`) work on a snapshot. Items are cloudpickled, so any value a callback sees
    (closures' classes included) can be recorded. Safe from any thread of any process
    started with the same authkey (the children of this process).
    """

    _exposed_ = ("append", "items", "__len__")

    def _ask(self, method: str, *args: Any) -> Any:
        """Call `method` on the shared list (typeshed types `_callmethod` as returning None)."""
        callmethod: Callable[..., Any] = self._callmethod
        return callmethod(method, args)

    def append(self, item: Any) -> None:
        """Add `item` at the end."""
        self._ask("append", cloudpickle.dumps(item))

    def snapshot(self) -> list[Any]:
        """A copy of the items, in the order they were appended."""
        return [cloudpickle.loads(data) for data in self._ask("items")]

    def __len__(self) -> int:
        count: int = self._ask("__len__")
        return count

    def __iter__(self) -> Iterator[Any]:
        return iter(self.snapshot())

    def __getitem__(self, index: Any) -> Any:
        return self.snapshot()[index]

    def __eq__(self, other: object) -> bool:
        if isinstance(other, Records):
            other = other.snapshot()
        return self.snapshot() == other

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"Records({self.snapshot()!r})"

    __str__ = __repr__


class _Manager(SyncManager):
    """A `SyncManager` that also serves `Records`."""


_Manager.register("Records", _RecordsState, Records)


class SharedObjects:
    """Events, barriers, locks and lists that a test shares with callbacks in any process.

    A `multiprocessing` `SyncManager` (one helper process, started with the forkserver or
    spawn context) holds the objects; what you get are proxies that pickle (cloudpickle
    too), so callbacks that captured them work in manager processes. Every process started
    by this one (same authkey) can use them.

    Use as a context manager, or `start()` / `close()`.
    """

    def __init__(self) -> None:
        self._manager = _Manager(ctx=mp_context())
        self._started = False

    def start(self) -> SharedObjects:
        """Start the helper process (returns `self`)."""
        self._manager.start()
        self._started = True
        return self

    @property
    def pid(self) -> int | None:
        """The helper process's pid, or `None` before `start`."""
        process = getattr(self._manager, "_process", None)
        return None if process is None else int(process.pid)

    def event(self) -> threading.Event:
        """A new shared `threading.Event`-like object."""
        event: threading.Event = self._manager.Event()
        return event

    def lock(self) -> threading.Lock:
        """A new shared lock."""
        lock: threading.Lock = self._manager.Lock()
        return lock

    def barrier(self, parties: int, *, timeout: float | None = None) -> threading.Barrier:
        """A new shared `threading.Barrier` for `parties` threads (`timeout` in seconds)."""
        barrier: threading.Barrier = self._manager.Barrier(parties, timeout=timeout)
        return barrier

    def list(self) -> Records:
        """A new shared append-only list."""
        records: Records = self._manager.Records()  # type: ignore[attr-defined]
        return records

    def close(self) -> None:
        """Stop the helper process (its objects stop working)."""
        if self._started:
            self._started = False
            self._manager.shutdown()

    def __enter__(self) -> SharedObjects:
        return self.start()

    def __exit__(self, *_: object) -> None:
        self.close()
