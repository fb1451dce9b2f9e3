"""Shared fixtures: leak checks, registrar creation, recording resource servers.

Every registrar a test starts goes through `make_registrar`, so that placement (threads
now, processes later) can be parametrised in one place, and every registrar is stopped
at teardown. The autouse `no_leftovers` fixture fails any test that leaves pykka actors
or child processes running.
"""

from __future__ import annotations

import collections
import dataclasses
import multiprocessing
import os
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pykka
import pytest

import rr_actors as rr
from rr_actors._registrar import _Request
from rr_actors._replies import FutureReply, wait

LEAK_GRACE = 5.0
"""Seconds a test's actors and child processes get to finish stopping after it ended."""


def _os_children() -> list[int]:
    """Pids of this process's living (non-zombie) children, read from /proc (Linux)."""
    pids: set[int] = set()
    for task in Path(f"/proc/{os.getpid()}/task").glob("*"):
        try:
            pids.update(int(p) for p in (task / "children").read_text().split())
        except (OSError, ValueError):
            continue
    living = []
    for pid in pids:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if state != "Z":
            living.append(pid)
    return living


@pytest.fixture(autouse=True)
def no_leftovers() -> Iterator[None]:
    """Fail the test if pykka actors or child processes outlive it (after a bounded wait)."""
    children_before = set(_os_children())
    yield
    deadline = time.monotonic() + LEAK_GRACE
    for ref in pykka.ActorRegistry.get_all():
        ref.actor_stopped.wait(max(0.0, deadline - time.monotonic()))
    actors = pykka.ActorRegistry.get_all()
    for child in multiprocessing.active_children():
        child.join(max(0.0, deadline - time.monotonic()))
    processes = multiprocessing.active_children()
    strays = set(_os_children()) - children_before - {p.pid for p in processes}
    if actors:
        pykka.ActorRegistry.stop_all(block=True, timeout=LEAK_GRACE)
    for child in processes:
        child.kill()
        child.join(LEAK_GRACE)
    problems = []
    if actors:
        problems.append(f"actors left running: {[a.actor_class.__name__ for a in actors]}")
    if processes:
        problems.append(f"child processes left running: {processes}")
    if strays:
        problems.append(f"child processes (by pid) left running: {sorted(strays)}")
    if problems:
        pytest.fail("; ".join(problems))


@pytest.fixture
def registrar_placement() -> str:
    """Where registrars started by `make_registrar` run ("thread": in this process).

    The single hook for running the registrar tests over both placements.
    """
    return "thread"


MakeRegistrar = Callable[..., rr.ResourceRegistrar]


@pytest.fixture
def make_registrar(registrar_placement: str) -> Iterator[MakeRegistrar]:
    """Start registrars with unique names (`<prefix>-<8 hex>`); stop them all at teardown.

    Call as `make_registrar("provider", call_timeout=5.0)`: keyword arguments are
    `RegistrarConfig` fields. Registrars are stopped newest first.
    """
    assert registrar_placement == "thread", f"placement {registrar_placement!r} is not built"
    started: list[rr.ResourceRegistrar] = []

    def make(prefix: str = "rr", **config: Any) -> rr.ResourceRegistrar:
        name = f"{prefix}-{uuid.uuid4().hex[:8]}"
        registrar = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name, **config))
        started.append(registrar)
        return registrar

    yield make
    errors: list[BaseException] = []
    for registrar in reversed(started):
        try:
            registrar.stop()
        except Exception as exc:
            errors.append(exc)
    if errors:
        pytest.fail(f"stopping the test's registrars failed: {errors!r}")


@dataclasses.dataclass
class ServerLog:
    """A recording resource server: what its callbacks were called with, in order.

    `journal` is shared by every server of one test, so orders across servers show.
    Entries are `(full server id, "load" | "unload", request)`.
    """

    full_id: str
    journal: list[tuple[str, str, Any]]
    respond: Callable[[Any], Any]
    loads: list[Any] = dataclasses.field(default_factory=list)
    unloads: list[tuple[Any, Any]] = dataclasses.field(default_factory=list)
    statuses: list[tuple[rr.Query, rr.StatusUpdate]] = dataclasses.field(default_factory=list)
    lock: threading.Lock = dataclasses.field(default_factory=threading.Lock)
    unloaded: threading.Event = dataclasses.field(default_factory=threading.Event)

    def load(self, request: Any) -> Any:
        with self.lock:
            self.loads.append(request)
            self.journal.append((self.full_id, "load", request))
        return self.respond(request)

    def unload(self, request: Any, response: Any) -> None:
        with self.lock:
            self.unloads.append((request, response))
            self.journal.append((self.full_id, "unload", request))
        self.unloaded.set()

    def on_status(self, query: rr.Query, update: rr.StatusUpdate) -> None:
        with self.lock:
            self.statuses.append((query, update))


def default_response(request: Any) -> Any:
    """The response a recording server gives unless told otherwise."""
    return {"resource": request}


@pytest.fixture
def journal() -> list[tuple[str, str, Any]]:
    """The ordered load/unload record shared by the test's recording servers."""
    return []


@pytest.fixture
def serve(journal: list[tuple[str, str, Any]]) -> Callable[..., ServerLog]:
    """Register a recording server: `serve(registrar, "leaf", respond=fn)` -> `ServerLog`.

    `respond(request)` runs inside `load` (on a worker thread) and gives the response; it
    may raise, block or call other servers.
    """

    def register(
        registrar: rr.ResourceRegistrar,
        name: str,
        respond: Callable[[Any], Any] = default_response,
    ) -> ServerLog:
        log = ServerLog(f"{registrar.name}/{name}", journal, respond)
        registrar.register_server(name, load=log.load, unload=log.unload, on_status=log.on_status)
        return log

    return register


class StatusInbox:
    """A client status callback that records what it receives."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.updates: list[tuple[rr.Query, rr.StatusUpdate]] = []

    def __call__(self, query: rr.Query, update: rr.StatusUpdate) -> None:
        with self.lock:
            self.updates.append((query, update))


@pytest.fixture
def inbox() -> Callable[[], StatusInbox]:
    """Make client status callbacks that record their updates: `cb = inbox()`."""
    return StatusInbox


def wait_for(predicate: Callable[[], bool], timeout: float = 5.0) -> bool:
    """Poll `predicate` (each check is a round trip to an actor) until true or `timeout` s."""
    deadline = time.monotonic() + timeout
    pause = threading.Event()
    while not predicate():
        if time.monotonic() > deadline:
            return False
        pause.wait(0.005)
    return True


@pytest.fixture
def eventually() -> Callable[..., bool]:
    """`eventually(predicate, timeout=5.0)`: bounded wait for a condition other actors make true."""
    return wait_for


@pytest.fixture
def gates(make_registrar: MakeRegistrar) -> Iterator[Callable[[], threading.Event]]:
    """Make events that block callbacks; all are set at teardown so no worker stays stuck.

    Depends on `make_registrar` so that the gates open before the registrars stop.
    """
    made: list[threading.Event] = []

    def make() -> threading.Event:
        event = threading.Event()
        made.append(event)
        return event

    yield make
    for event in made:
        event.set()


def waiting_query_ids(
    provider: rr.ResourceRegistrar, timeout: float = 5.0
) -> collections.Counter[str]:
    """Consumer ids whose load the provider has taken but not answered yet (with repeats).

    Reads the registrar actor's private state in its own thread (like
    `rr_actors.testing.catalog_snapshot`): the ids waiting for a load that runs, and the
    ids parked until an equal resource finished unloading.
    """

    def op(actor: Any, reply: Any) -> None:
        ids = [w.query_id for waiters in actor.loads.values() for w in waiters]
        ids += [load.query_id for loads in actor.after_unload.values() for load in loads]
        reply.set_result(collections.Counter(ids))

    reply = FutureReply()
    provider._ref.tell(_Request(op, reply))  # test-only introspection
    ids: collections.Counter[str] = wait(reply.future, timeout, "waiting_query_ids()")
    return ids


@pytest.fixture
def arrived() -> Callable[..., bool]:
    """`arrived(provider, ids)`: wait (bounded) until the provider holds those calls waiting.

    An id listed twice must be waiting twice (a retry with the same query id).
    """

    def check(provider: rr.ResourceRegistrar, query_ids: list[str], timeout: float = 5.0) -> bool:
        wanted = collections.Counter(query_ids)
        return wait_for(lambda: wanted <= waiting_query_ids(provider), timeout)

    return check
