"""Seams for making races happen on purpose, and for looking at what a registrar waits for;
placement-independent helpers: kill a registrar, look at its catalog, list actors.

Each names a registrar's steps or holdings in words that are part of the contract of
`rr_actors.testing`, never its private handler tables.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import pykka

from rr_actors._core.directory import DIRECTORY, LocalPeer, Reply
from rr_actors._core.replies import FutureReply, wait
from rr_actors._process.remote import FORWARD_MARGIN, RemoteRegistrar
from rr_actors._registrar import ResourceRegistrar, snapshot
from rr_actors._registrar.actor import STEPS, RegistrarActor
from rr_actors._registrar.calls import CallAttempt
from rr_actors._registrar.life import CatalogView
from rr_actors._registrar.messages import RunOnActor
from rr_actors._registrar.state import Hook, Probes
from rr_actors.errors import ConfigError, RegistrarUnavailableError, _known_names

__all__ = [
    "Installed",
    "PendingWork",
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
    """Run `op(actor, reply)` on the actor's thread: the one test-only message."""
    reply = FutureReply()
    try:
        ref.tell(RunOnActor(op, reply))
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

    future: pykka.Future[T] = _ask_actor(local._actor.ref, op).future
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
        return local._actor.ref
    target_rr, server = client  # (a list of the two too)
    ref = local._actor.clients.get((target_rr, server))
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

    A message step (`"load"`, `"abandon"`, `"client_loaded"`, ...) runs its
    hooks on the registrar's actor thread around the handling of that message; `subject`
    is the message (its fields, such as `query_id`, are stable). A point
    (`"unload_resource"`, `"close_resource"`, `"stop_drained"`, `"events_written"`: a
    change and the events that tell of it were committed together, and the events, its
    subject, are published next; and on the caller's thread `"send_load"` and
    `"withdraw"`) runs them where it is reached. `STEPS` lists every name
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
        hint = _known_names(step, STEPS, shown=len(STEPS))
        raise ConfigError(f"no registrar step is named {step!r}{hint}")
    here = local._actor
    probes = here.probes
    if probes is None:
        probes = Probes()
        installed = probes

        def install(actor: RegistrarActor, reply: Reply) -> None:
            actor.shared.probes = installed
            reply.set_result(None)

        wait(_ask_actor(here.ref, install).future, 10.0, "installing probes")
        here.probes = probes
    probes.add(step, before=before, after=after)
    return Installed(functools.partial(probes.remove, step, before=before, after=after))


def call_futures(registrar: ResourceRegistrar, future_type: type[CallAttempt]) -> Installed:
    """Make the registrar's callers wait on `future_type` futures until `close()`.

    A caller waits for its answer on the future of its call attempt
    (`rr_actors._registrar.calls.CallAttempt`, a one-shot future with one state), which
    the answering thread settles, or the caller withdraws when its time runs out (see
    `docs/explanation/failure-semantics.md`). A subclass that overrides `wait` or a
    transition (`answer`, `fail`, `take`, `settle`, `withdraw`) to wait on events makes
    an answer race a timeout at a chosen instant.

    Returns:
        What was installed; `close()` it, or use it as a context manager.

    Raises:
        ConfigError: `registrar` is a `RemoteRegistrar`, or `future_type` is not a
            subclass of the one-shot future.
    """
    local = _local(registrar, "call_futures")
    if not (isinstance(future_type, type) and issubclass(future_type, CallAttempt)):
        raise ConfigError(
            f"future_type must subclass CallAttempt (the OneShotFuture of a call), "
            f"got {future_type!r}"
        )
    calls = local._actor.calls
    before, calls.attempt_type = calls.attempt_type, future_type
    return Installed(lambda: setattr(calls, "attempt_type", before))


@contextlib.contextmanager
def expect_restart(name: str) -> Iterator[None]:
    """While the block runs, registrar `name` dying is not a registrar gone for good.

    A supervisor says so for every child it will restart: the providers then keep the
    dead registrar's consumer ids for its restored catalog, and its consumers keep the
    ids they hold there without a `FATAL` (no death watch, rule 19). It holds for
    a registrar of this process and for the manager process of a `RemoteRegistrar`
    whose owner handle is in this process (`kill()` inside the block).
    """
    known = DIRECTORY.restart_expected(name)
    DIRECTORY.expect_restart(name)
    try:
        yield
    finally:
        if not known:
            DIRECTORY.expect_restart(name, expected=False)


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
    record = actor.shared
    provider, flights = record.provider, record.flights
    ids = [w.query_id for waiters in provider.loads.values() for w in waiters]
    ids += [load.query_id for loads in provider.after_unload.values() for load in loads]
    ids += [load.query_id for load in provider.matching.waiting()]
    reply.set_result(
        PendingWork(
            waiting_loads=collections.Counter(ids),
            held_loads=tuple(load.query_id for load in provider.held_loads),
            answers_due=record.due.ids(),
            parked_notices=flights.parked_ids(),
            open_requests=len(record.open_requests) - 1,  # (not this one)
            queued_callbacks=record.workers.queued,
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
        ref = registrar._actor.ref
    work: PendingWork = wait(_ask_actor(ref, _pending_work).future, timeout, "pending_work()")
    return work


# -- placement-independent helpers -------------------------------------------------------------


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
    registrar._actor.crash()
    registrar._actor.died.wait(timeout)  # the actor's death handling ran, death watch included


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
        there = functools.partial(catalog_snapshot, timeout=timeout)
        remote: CatalogView = registrar.run(there, timeout=timeout + FORWARD_MARGIN)
        return remote
    return snapshot(registrar, timeout=timeout, check=True)


def running_actors() -> list[Any]:
    """The pykka actors still running in this process."""
    return list(pykka.ActorRegistry.get_all())
