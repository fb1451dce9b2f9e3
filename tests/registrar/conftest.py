"""Fixtures of the registrar tests: every placement, the async API, recording servers.

Placement. Every registrar test starts its registrars through `make_registrar`, and every
test that (directly or through another fixture) uses it runs three times, through the one
parametrised fixture `registrar_placement`:

- "thread": `make_registrar` returns `ResourceRegistrar`s in this process (threads).
- "process": each registrar runs in its own manager process (forkserver context) on a
  per-test `System`; `make_registrar` returns `rr_actors.testing.RemoteRegistrar`
  handles, which have the same methods and forward each one into the registrar's process
  over the system's authenticated channel. Errors come back as the same rr_actors
  errors. Callbacks are cloudpickled into the manager process; a callback that captured a
  handle calls its registrar directly when it runs in that registrar's process (so
  dependency tracking through the context variable works inside `load`) and forwards
  otherwise. `rr_actors.testing.crash` SIGKILLs the manager process, and its owner handle
  then tells the other registrars the consumer is gone (what a supervisor does for a
  child it will not restart).
- "zenoh": as "process", but the system is a `ZenohNetwork` (tls=None, the default
  1 s lease, a unique system name per test): this process is its router and each
  manager process joins it as a Zenoh client over the router's Unix socket, so every
  message between two registrars crosses the Zenoh wire (`zenoh.wire` frames, puts
  routed through this process, liveliness tokens for presence). No TCP `listen`: on
  one host the carrier's own process model never uses TCP (managers always join over
  the Unix socket), and a listen port nobody connects to exercises nothing;
  `tests/multihost` covers TCP between routers. Loopback only, no root.

API. In the test classes of the semantic rules (marked `pytestmark =
pytest.mark.both_apis`), every test that starts its registrars through `make_registrar`
also runs against the async API: ids "thread-async" and "process-async" (the thread
placement and the AF_UNIX one; Zenoh adds nothing the async surface does differently).
There `make_registrar` returns handles whose blocking methods go through their awaitable
twins, with coroutine callbacks (`tests.support.awaited`): the same bodies, not copies.
Each twin is awaited in the registrar's own process, on a loop there: in
"process-async", a registrar of a manager process awaits its providers in the other
manager processes, as an application's consumer registrar awaits a supervised manager.

A test that cannot mean the same in every placement is marked
`@pytest.mark.thread_only("reason")` (thread placement only),
`@pytest.mark.not_zenoh("reason")` (not the zenoh one) or
`@pytest.mark.across_processes("reason")` (not the thread one: what it tests needs a
message to cross between processes); `pytest_generate_tests` reads them.

Why these choices:

- One `System` per test, not per module: creating one costs a temporary directory and
  32 random bytes, and a fresh one keeps the death-watch broadcast (which lists the
  system's sockets) and the directory resolver to the test's own registrars. What costs
  is a manager process (~35 ms to fork from the warm forkserver and be served), paid per
  registrar; the forkserver (with its preloaded rr_actors modules) and multiprocessing's
  resource tracker are started once per session, before any leak check counts children.
- State the test shares with callbacks (the recording servers' journals, status inboxes,
  gates, started-events, barriers) comes from the `shared` fixture: plain `threading`
  objects and lists in the thread placement (nothing changes there), and
  `rr_actors.testing.SharedObjects` proxies (a `SyncManager` helper process, one per
  session, excluded from the leak check by pid) in the process placement. Lists are
  `rr_actors.testing.Records`: they compare equal to a list, so assertions are unchanged.
  A callback that captured a bare `threading.Event` fails loudly in the process placement
  (it does not pickle), and one that captured a bare list would record into a copy, so
  tests use `shared` wherever a callback touches state the test reads.
- conftest and the test modules are registered with cloudpickle "by value", so their
  functions and classes (the recording server, `SensorError`, ...) reach the manager
  processes without those importing pytest or the test modules.
"""

from __future__ import annotations

import collections
import dataclasses
import sys
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import cloudpickle
import pytest

import rr_actors as rr
from rr_actors.testing import RemoteRegistrar, SharedObjects, System, pending_work
from tests.support import awaited as awaited_handles
from tests.support import gating
from tests.support.gating import GatedLoad, same
from tests.support.heard import Heard
from tests.support.waiting import wait_for

PLACEMENTS = ("thread", "process", "zenoh")
"""Where `make_registrar` starts registrars: in this process, or one manager process each
(joined over the AF_UNIX carrier, or over Zenoh)."""

ASYNC_PLACEMENTS = ("thread", "process")
"""The placements a `both_apis` class's tests also run in against the async API."""


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    """Run every test that uses `registrar_placement` once per placement."""
    if "registrar_placement" not in metafunc.fixturenames:
        return
    placements = list(PLACEMENTS)
    marker = metafunc.definition.get_closest_marker("thread_only")
    if marker is not None:
        assert marker.args or marker.kwargs.get("reason"), "thread_only needs a reason"
        placements = ["thread"]
    marker = metafunc.definition.get_closest_marker("not_zenoh")
    if marker is not None:
        assert marker.args or marker.kwargs.get("reason"), "not_zenoh needs a reason"
        placements = [p for p in placements if p != "zenoh"]
    marker = metafunc.definition.get_closest_marker("across_processes")
    if marker is not None:
        assert marker.args or marker.kwargs.get("reason"), "across_processes needs a reason"
        placements = [p for p in placements if p != "thread"]
    both = metafunc.definition.get_closest_marker("both_apis") is not None
    marker = metafunc.definition.get_closest_marker("blocking_api_only")
    if marker is not None:
        assert marker.args or marker.kwargs.get("reason"), "blocking_api_only needs a reason"
        both = False
    if not both or "registrar_api" not in metafunc.fixturenames:
        metafunc.parametrize("registrar_placement", placements, indirect=True, ids=placements)
        return
    cases = [(p, "blocking") for p in placements]
    cases += [(p, "async") for p in ASYNC_PLACEMENTS if p in placements]
    ids = [p if api == "blocking" else f"{p}-async" for p, api in cases]
    metafunc.parametrize(("registrar_placement", "registrar_api"), cases, indirect=True, ids=ids)


# -- placement ------------------------------------------------------------------------------


@pytest.fixture
def registrar_placement(request: pytest.FixtureRequest) -> str:
    """Where registrars started by `make_registrar` run: "thread", "process" or "zenoh".

    Parametrised by `pytest_generate_tests` (ids "thread" / "process" / "zenoh"); a test
    marked `thread_only` gets "thread" only, one marked `not_zenoh` not "zenoh".
    """
    placement: str = request.param
    return placement


@pytest.fixture
def registrar_api(request: pytest.FixtureRequest) -> str:
    """Which API `make_registrar`'s handles are driven through: "blocking" or "async".

    "async" only in `both_apis` classes (`pytest_generate_tests`): the handles' blocking
    methods then go through their awaitable twins (`tests.support.awaited`).
    """
    api: str = getattr(request, "param", "blocking")
    return api


class _LocalObjects:
    """The thread placement's shared state: ordinary objects of this process."""

    def event(self) -> threading.Event:
        return threading.Event()

    def lock(self) -> threading.Lock:
        return threading.Lock()

    def barrier(self, parties: int, *, timeout: float | None = None) -> threading.Barrier:
        return threading.Barrier(parties, timeout=timeout)

    def list(self) -> list[Any]:
        return []


Shared = _LocalObjects | SharedObjects


@pytest.fixture
def shared(registrar_placement: str, process_helpers: SharedObjects) -> Shared:
    """Events, locks, barriers and lists a test shares with its callbacks.

    `shared.event()`, `shared.lock()`, `shared.barrier(n, timeout=5)`, `shared.list()`:
    `threading` objects and a list in the thread placement, `SharedObjects` proxies (that
    work from manager processes) in the process placement.
    """
    if registrar_placement == "thread":
        return _LocalObjects()
    return process_helpers


Registrar = rr.ResourceRegistrar | RemoteRegistrar
MakeRegistrar = Callable[..., Registrar]
Starter = Callable[..., rr.ResourceRegistrar]
"""`named_registrars`: start a registrar of this process by a prefix of its name."""


def placement_network(placement: str) -> System | rr.ZenohNetwork:
    """A fresh system (any carrier's `Transport`) for a placement's manager processes."""
    if placement == "process":
        return System.create()
    if placement == "zenoh":
        return rr.ZenohNetwork(system=f"test-{uuid.uuid4().hex[:8]}", tls=None)
    raise AssertionError(f"no carrier for placement {placement!r}")


@pytest.fixture
def make_registrar(
    registrar_placement: str,
    registrar_api: str,
    request: pytest.FixtureRequest,
    process_helpers: SharedObjects,
) -> Iterator[MakeRegistrar]:
    """Start registrars with unique names (`<prefix>-<8 hex>`); stop them all at teardown.

    Call as `make_registrar("provider", call_timeout=5.0)`: keyword arguments are
    `RegistrarConfig` fields. In the "process" placement each registrar gets its own
    manager process (of an AF_UNIX `System`, or of a `ZenohNetwork` in "zenoh") and the
    result is a `RemoteRegistrar`. Registrars are stopped newest first.
    """
    started: list[Registrar] = []
    system: System | rr.ZenohNetwork | None = None
    if registrar_placement != "thread":
        cloudpickle.register_pickle_by_value(sys.modules[__name__])
        cloudpickle.register_pickle_by_value(gating)
        # (not `awaited_handles`: by reference, its thread pool stays in each process)
        cloudpickle.register_pickle_by_value(request.module)
        system = placement_network(registrar_placement)

    def make(prefix: str = "rr", **config: Any) -> Registrar:
        settings = rr.RegistrarConfig(name=f"{prefix}-{uuid.uuid4().hex[:8]}", **config)
        registrar: Registrar
        if system is None:
            registrar = rr.ResourceRegistrar.start(settings)
        else:
            registrar = RemoteRegistrar.start(settings, system)
        if registrar_api == "async":
            registrar = awaited_handles.awaited(registrar)
        started.append(registrar)
        return registrar

    yield make
    errors: list[BaseException] = []
    for registrar in reversed(started):
        try:
            registrar.stop()
        except Exception as exc:
            errors.append(exc)
    if system is not None:
        system.close()
    if errors:
        pytest.fail(f"stopping the test's registrars failed: {errors!r}")


@pytest.fixture
def named_registrars() -> Iterator[Starter]:
    """Start registrars in this process, named `<prefix>-<8 hex>` (keyword arguments are
    `RegistrarConfig` fields): `named_registrars("erm", call_timeout=5.0)`. Stopped newest
    first at teardown."""
    registrars: list[rr.ResourceRegistrar] = []

    def start(prefix: str, **config: Any) -> rr.ResourceRegistrar:
        name = f"{prefix}-{uuid.uuid4().hex[:8]}"
        registrar = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name, **config))
        registrars.append(registrar)
        return registrar

    yield start
    for registrar in reversed(registrars):
        registrar.stop()


# -- recording servers and status inboxes ------------------------------------------------------


class ServerLog:
    """A recording resource server: what its callbacks were called with, in order.

    `journal` is shared by every server of one test, so orders across servers show.
    Entries are `(full server id, "load" | "unload", request)`. The lists and the
    `unloaded` event come from the `shared` fixture, so the callbacks may run in a manager
    process; each append is atomic (no lock needed around one).
    """

    def __init__(
        self, full_id: str, journal: Any, respond: Callable[[Any], Any], shared: Shared
    ) -> None:
        self.full_id = full_id
        self.journal = journal
        self.respond = respond
        self.loads = shared.list()
        self.unloads = shared.list()
        self.statuses = shared.list()
        self.unloaded = shared.event()

    def load(self, request: Any) -> Any:
        self.loads.append(request)
        self.journal.append((self.full_id, "load", request))
        return self.respond(request)

    def unload(self, request: Any, response: Any) -> None:
        self.unloads.append((request, response))
        self.journal.append((self.full_id, "unload", request))
        self.unloaded.set()

    def on_status(self, query: rr.Query, update: rr.StatusUpdate) -> None:
        self.statuses.append((query, update))


def default_response(request: Any) -> Any:
    """The response a recording server gives unless told otherwise."""
    return {"resource": request}


@pytest.fixture
def journal(shared: Shared) -> Any:
    """The ordered load/unload record shared by the test's recording servers."""
    return shared.list()


@pytest.fixture
def serve(journal: Any, shared: Shared) -> Callable[..., ServerLog]:
    """Register a recording server: `serve(registrar, "leaf", respond=fn)` -> `ServerLog`.

    `respond(request)` runs inside `load` (on a worker thread of the registrar's process)
    and gives the response; it may raise, block or call other servers.
    """

    def register(
        registrar: Registrar,
        name: str,
        respond: Callable[[Any], Any] = default_response,
    ) -> ServerLog:
        log = ServerLog(f"{registrar.name}/{name}", journal, respond, shared)
        registrar.register_server(name, load=log.load, unload=log.unload, on_status=log.on_status)
        return log

    return register


class ServedPair(NamedTuple):
    """A provider and a consumer, the provider serving a recording server "leaf"."""

    provider: Registrar
    consumer: Registrar
    leaf: ServerLog


@pytest.fixture
def served_pair(make_registrar: MakeRegistrar, serve: Callable[..., ServerLog]) -> ServedPair:
    """`provider, consumer, leaf = served_pair`: registrars "provider" then "consumer" (so
    stopped in the other order), and `serve(provider, "leaf")`'s log."""
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    return ServedPair(provider, consumer, serve(provider, "leaf"))


class StatusInbox:
    """A client status callback that records what it receives (in `updates`)."""

    def __init__(self, updates: Any) -> None:
        self.updates = updates

    def __call__(self, query: rr.Query, update: rr.StatusUpdate) -> None:
        self.updates.append((query, update))


@pytest.fixture
def inbox(shared: Shared) -> Callable[[], StatusInbox]:
    """Make client status callbacks that record their updates: `cb = inbox()`."""
    return lambda: StatusInbox(shared.list())


@pytest.fixture
def gates(make_registrar: MakeRegistrar, shared: Shared) -> Iterator[Callable[[], Any]]:
    """Make events that block callbacks; all are set at teardown so no worker stays stuck.

    Depends on `make_registrar` so that the gates open before the registrars stop.
    """
    made: list[Any] = []

    def make() -> Any:
        event = shared.event()
        made.append(event)
        return event

    yield make
    for event in made:
        event.set()


@pytest.fixture
def gated_load(gates: Callable[[], Any], shared: Shared) -> Callable[..., GatedLoad]:
    """Make gated slow loads: `slow = gated_load(respond)`; `serve(provider, "leaf", slow)`.

    Then `slow.started.wait(5)` (the load runs) and `slow.gate.set()` (let it answer). The
    gate comes from `gates` (opened at teardown), the event and the request list from
    `shared` (so the load may run in a manager process). `wait=20` for a longer bound.
    """

    def make(respond: Callable[[Any], Any] = same, *, wait: float = 10.0) -> GatedLoad:
        return GatedLoad(gates(), shared.event(), respond, wait=wait, requests=shared.list())

    return make


def waiting_query_ids(provider: Registrar, timeout: float = 5.0) -> collections.Counter[str]:
    """Consumer ids whose load the provider has taken but not answered yet (with repeats).

    The ids waiting for a load that runs, and the ids parked until an equal resource
    finished unloading (`rr_actors.testing.pending_work`, asked in the registrar's
    process for a `RemoteRegistrar`).
    """
    return pending_work(provider, timeout=timeout).waiting_loads


@pytest.fixture
def arrived() -> Callable[..., bool]:
    """`arrived(provider, ids)`: wait (bounded) until the provider holds those calls waiting.

    An id listed twice must be waiting twice (a retry with the same query id).
    """

    def check(provider: Registrar, query_ids: list[str], timeout: float = 30.0) -> bool:
        wanted = collections.Counter(query_ids)
        return wait_for(lambda: wanted <= waiting_query_ids(provider), timeout)

    return check


@pytest.fixture
def system() -> Iterator[System]:
    """A fresh AF_UNIX system (runtime directory + authkey) for manager processes; closed after."""
    made = System.create()
    yield made
    made.close()


def leaf_setup(registrar: rr.ResourceRegistrar) -> None:
    """A manager's setup: it serves `leaf`, whose load answers `loaded <request>`."""
    registrar.register_server("leaf", load=lambda r: f"loaded {r}", unload=lambda _q, _r: None)


@dataclasses.dataclass
class ManagerProvider:
    """A durable provider `name` serving `leaf` in a manager process of `sup` (no heartbeat:
    a test may hold it), `app`, a registrar of this process, and `heard`, the tree's events."""

    name: str
    sup: rr.Supervisor
    app: rr.ResourceRegistrar
    heard: Heard
    subscription: Any

    def events(self) -> Heard:
        """Every event of the tree so far (its managers' flushed), then no more heard."""
        assert self.sup.flush_events(timeout=10)
        assert self.subscription.wait_delivered(timeout=10)
        self.subscription.close()
        return self.heard


@pytest.fixture
def manager_provider(
    supervisors: Callable[..., rr.Supervisor], tmp_path: Path
) -> Callable[..., ManagerProvider]:
    """`manager_provider(**app_config)`: a started `ManagerProvider` (the test's SIGKILLs are
    real; its backup is under `tmp_path`), `app` configured with `app_config`."""
    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # (`leaf_setup`)

    def make(**app_config: Any) -> ManagerProvider:
        uid = uuid.uuid4().hex[:8]
        spec = rr.ManagerSpec(f"p-{uid}", leaf_setup, isolation="process", heartbeat=None)
        sup = supervisors([spec], state_dir=tmp_path / "state")
        heard = Heard()
        subscription = sup.subscribe(heard)
        sup.start()
        app = sup.registrar(rr.RegistrarConfig(name=f"app-{uid}", **app_config))
        return ManagerProvider(spec.name, sup, app, heard, subscription)

    return make
