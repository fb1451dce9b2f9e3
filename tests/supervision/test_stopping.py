"""Stopping a supervisor's children (`rr_actors._supervision.stopping`): the shutdown timeout
and then the kill, the death watch at every provider, and what a child that will not come
back leaves behind.

A host's tree stopped for good is a clean stop at its consumers elsewhere, not a loss:
`rr-actors demo --hosts 2`'s end, reduced to two processes over Zenoh: a "robot host"
process (its own Zenoh router, a supervisor of one manager process) serves a provider;
the test process (the "station") holds an id there from a consumer registrar. The host
stops its tree and leaves the network: its consumer hears no `FATAL` and logs no
WARNING (rule 12: a stopped provider's served ids stay; its consumers release them).
Rule 19 still holds: a host killed with its supervisor (nobody restarts the provider)
is lost: `FATAL` to the id, and the WARNING.

The clean stop's check needs a bound on "nothing came": an unsupervised control
provider (`own_provider_main`) is killed after the host left; its loss is heard after
whatever the host's leaving caused.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing.connection
import multiprocessing.context
import os
import signal
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.replies import FutureReply, wait
from rr_actors._registrar.messages import Load
from rr_actors.testing import SharedObjects, actor_ref, start_forkserver
from tests.support.carriers import own_provider_main, setup_servers
from tests.support.supervising import (
    FakeClock,
    alive,
    process,
    sigkill,
)
from tests.support.waiting import wait_for


@pytest.fixture(scope="module", autouse=True)
def forkserver() -> None:
    """Start the forkserver before the leak check counts this process's children."""
    start_forkserver()


LOST = "is gone and nobody will restart it"
"""What the consumer's WARNING says of a provider lost for good (rule 19)."""


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def host_main(
    system: str,
    listen: str,
    connect: str,
    provider: str,
    control: multiprocessing.connection.Connection,
) -> None:
    """The robot's host: its router, a supervisor of manager process `provider`; on
    "stop", the tree stops, then the network closes (as `rr_actors.mission.hosts.main`)."""
    net = rr.ZenohNetwork(system=system, listen=[listen], connect=[connect], tls=None)
    sup = rr.Supervisor(
        [rr.ManagerSpec(provider, setup=setup_servers, isolation="process", restart="permanent")],
        network=net,
        name="robot",
    )
    with net:
        sup.start()
        try:
            control.send(("ready", os.getpid()))
            with contextlib.suppress(EOFError, OSError):
                control.recv()
        finally:
            sup.stop()


class Station:
    """The test process's side: its network, a consumer, what the consumer heard."""

    def __init__(self, context: multiprocessing.context.ForkServerContext) -> None:
        self.context = context
        self.system = f"quietend-{uuid.uuid4().hex[:8]}"
        self.endpoint = f"tcp/127.0.0.1:{_free_port()}"
        self.network = rr.ZenohNetwork(system=self.system, listen=[self.endpoint], tls=None)
        self.heard: list[tuple[str, rr.Status, str]] = []
        self.changed = threading.Condition()
        self.consumer = rr.ResourceRegistrar.start(
            rr.RegistrarConfig(name=f"cm-{uuid.uuid4().hex[:8]}", call_timeout=30.0),
            network=self.network,
        )
        self.processes: list[tuple[multiprocessing.process.BaseProcess, Any]] = []

    def on_status(self, query: rr.Query, update: rr.StatusUpdate) -> None:
        with self.changed:
            self.heard.append((query.id, update.status, update.source))
            self.changed.notify_all()

    def wait_heard(self, query_id: str, timeout: float = 15.0) -> bool:
        with self.changed:
            return self.changed.wait_for(
                lambda: any(q == query_id for q, _, _ in self.heard), timeout
            )

    def start(
        self, target: Any, *args: Any, daemon: bool = True
    ) -> tuple[multiprocessing.process.BaseProcess, Any]:
        parent_end, child_end = self.context.Pipe()
        process = self.context.Process(target=target, args=(*args, child_end), daemon=daemon)
        process.start()
        child_end.close()
        self.processes.append((process, parent_end))
        assert parent_end.poll(60), "the process did not get ready"
        return process, parent_end

    def host(self) -> tuple[str, multiprocessing.process.BaseProcess, Any]:
        """Start the robot's host; once the provider is served there and seen here."""
        provider = f"erm-{uuid.uuid4().hex[:8]}"
        listen = f"tcp/127.0.0.1:{_free_port()}"
        process, control = self.start(
            host_main, self.system, listen, self.endpoint, provider, daemon=False
        )  # (not daemonic: it starts manager processes)
        assert "ready" == control.recv()[0]
        self.network.wait_for(provider, timeout=30)
        return provider, process, control

    def control_provider(self) -> tuple[str, multiprocessing.process.BaseProcess]:
        """An unsupervised provider of its own (its loss is the control)."""
        name = f"control-{uuid.uuid4().hex[:8]}"
        join = ("router", self.system, self.endpoint)
        process, control = self.start(own_provider_main, join, name)
        assert "ready" == control.recv()
        self.network.wait_for(name, timeout=30)
        return name, process

    def close(self) -> None:
        with contextlib.suppress(rr.RrError):
            self.consumer.stop()
        for _, control in self.processes:
            with contextlib.suppress(OSError):
                control.send("stop")
        for child, control in self.processes:
            child.join(30)
            if child.is_alive():
                child.kill()
                child.join(10)
            control.close()
        self.network.close()


@pytest.fixture
def station(context: multiprocessing.context.ForkServerContext) -> Iterator[Station]:
    made = Station(context)
    yield made
    made.close()


def _lost_warnings(caplog: pytest.LogCaptureFixture, name: str) -> list[str]:
    return [
        r.getMessage()
        for r in caplog.records
        if r.levelno >= logging.WARNING and f"{name} {LOST}" in r.getMessage()
    ]


@pytest.mark.timeout(180)
def test_a_host_that_stops_its_tree_for_good_is_no_loss_at_its_consumer_on_another_host(
    station: Station, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="rr_actors")
    provider, host, control = station.host()
    query = station.consumer.call(provider, "echo", "r", on_status=station.on_status)
    control_name, control_process = station.control_provider()
    control_query = station.consumer.call(control_name, "echo", "c", on_status=station.on_status)

    control.send("stop")  # the tree stops (the provider for good), then its network closes
    host.join(60)
    assert 0 == host.exitcode
    assert wait_for(lambda: provider not in station.network.names(), 15.0)
    assert control_process.pid
    os.kill(control_process.pid, signal.SIGKILL)  # heard after what the host's end caused
    assert station.wait_heard(control_query.id), "the control was never heard lost"

    assert [(control_query.id, rr.Status.FATAL, f"{control_name}/echo")] == station.heard
    assert [] == _lost_warnings(caplog, provider)
    assert [query.id] == [
        q.id for q in station.consumer.client_queries() if q.serving_rr == provider
    ]  # kept, as a stop leaves it (rule 12)


@pytest.mark.timeout(180)
def test_a_host_killed_with_its_supervisor_is_a_loss_fatal_at_its_consumer_on_another_host(
    station: Station, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="rr_actors")
    provider, host, _ = station.host()
    query = station.consumer.call(provider, "echo", "r", on_status=station.on_status)

    assert host.pid
    os.kill(host.pid, signal.SIGKILL)  # the supervisor too: nobody restarts the provider

    assert station.wait_heard(query.id), "the provider was never heard lost"
    assert [(query.id, rr.Status.FATAL, f"{provider}/echo")] == station.heard
    assert 1 == len(_lost_warnings(caplog, provider))
    assert [] == [q for q in station.consumer.client_queries() if q.serving_rr == provider]


class TestStoppedForGood:
    """A manager its supervisor stops for good is a mark: what a provider still holds of it goes.

    Issue 32 (the kill-heavy plan's `end` findings): consumer `edge` stopped for good (the
    tree's stop) while provider `api` still held ids `edge` had given up while `api` was
    down; `api`'s reconcile came too late to name them, and `api` ended the run holding
    them. A stopped registrar holds nothing (rule 12), so its supervisor's "it will not be
    started again" is a mark as a death for good is (`_core/membership.py`): the provider
    releases what it still holds of it. Here the stale id is a `Load` sent in the consumer's
    name, which the consumer never knew of (it used to come from a consumer without a
    backup, killed and restarted: issue 42 had its supervisor's `lost_everything` make it
    reconcile, and such ids are released at its restart now).
    """

    def test_a_consumer_stopped_for_good_by_its_supervisor_has_its_stale_ids_released(
        self, tmp_path: Path, uid: str
    ) -> None:
        provider, consumer = f"api-{uid}", f"edge-{uid}"
        unloads: list[Any] = []
        unloaded = threading.Event()

        def unload(request: Any, _response: Any) -> None:
            unloads.append(request)
            unloaded.set()

        def setup(registrar: rr.ResourceRegistrar) -> None:
            registrar.register_server("leaf", load=lambda r: r, unload=unload)

        sup = rr.Supervisor(
            [
                rr.ManagerSpec(provider, setup, isolation="thread"),
                rr.ManagerSpec(consumer, None, isolation="thread"),
            ],
            backoff=rr.Backoff(initial=0.0, jitter=0.0),
        )
        with sup:
            stale = FutureReply()
            DIRECTORY.lookup(provider).tell(
                Load(str(uuid.uuid4()), "leaf", "x", consumer, (), stale)
            )
            assert "x" == wait(stale.future, 10, "the load in the consumer's name")
            assert [] == sup.run_in(consumer, lambda r: r.client_queries())  # it knows no id
            assert 1 == len(sup.run_in(provider, lambda r: r.server_queries("leaf")))  # held
            # the tree stops: the consumer first, for good; then the provider

        assert unloaded.wait(10)
        assert ["x"] == unloads  # released when the consumer stopped for good, unloaded once


class TestShutdownThenKill:
    """A child's `shutdown`: the time its own stop gets, then it is killed (a process) or
    told to crash (a thread)."""

    def test_a_process_manager_is_killed_once_its_own_shutdown_ran_out(
        self, supervisors: Callable[..., rr.Supervisor], uid: str
    ) -> None:
        name = f"erm-{uid}"
        sup = supervisors([process(name, heartbeat=None, shutdown=0.5)]).start()
        pid = sup.child(name).pid
        assert pid is not None  # never os.kill(0, ...): that signals this test's process group
        os.kill(pid, signal.SIGSTOP)  # it cannot stop cleanly
        started = time.monotonic()
        sup.stop()
        took = time.monotonic() - started

        assert ("killed", False) == ((sup.child(name).last_exit or "")[:6], alive(pid))
        assert took < 4.0, f"stop took {took:.2f} s with shutdown=0.5"

    def test_a_thread_manager_stuck_past_its_shutdown_is_told_to_crash(
        self, supervisors: Callable[..., rr.Supervisor], uid: str
    ) -> None:
        name = f"a-{uid}"
        release = threading.Event()

        def setup(reg: rr.ResourceRegistrar) -> None:
            reg.register_server("res", load=lambda r: r, unload=lambda r, _: release.wait(30.0))

        sup = supervisors([rr.ManagerSpec(name, setup, shutdown=0.5)], clock=FakeClock()).start()
        registrar = sup.run_in(name, lambda r: r)
        sup.run_in(name, lambda reg: reg.call(name, "res", "x"))  # its clean stop must unload it
        try:
            sup.stop()
        finally:
            release.set()
        assert actor_ref(registrar).actor_stopped.wait(10.0)

        assert "killed" == (sup.child(name).last_exit or "")[:6]
        with pytest.raises(rr.RegistrarUnavailableError):  # it died; a clean stop would say so
            registrar.call(name, "res", "y", timeout=5.0)


def unload_flag(unloaded: Any) -> Callable[[rr.ResourceRegistrar], None]:
    def setup(registrar: rr.ResourceRegistrar) -> None:
        registrar.register_server("res", load=lambda r: r, unload=lambda r, s: unloaded.set())

    return setup


def consumer_of(*providers: str) -> Callable[[rr.ResourceRegistrar], None]:
    def setup(registrar: rr.ResourceRegistrar) -> None:
        if not registrar.client_queries():
            for provider in providers:
                registrar.call(provider, "res", "camera", timeout=10.0)

    return setup


class TestDeathWatchAtEveryProvider:
    """A consumer that dies for good has its ids released at every provider it held them at,
    nested or not."""

    def test_a_temporary_consumer_that_dies_has_its_ids_released_at_every_provider(
        self, supervisors: Callable[..., rr.Supervisor], uid: str, process_helpers: SharedObjects
    ) -> None:
        p1, p2, c = f"p1-{uid}", f"p2-{uid}", f"c-{uid}"
        unloaded1, unloaded2 = process_helpers.event(), process_helpers.event()
        sup = supervisors(
            [
                process(p1, unload_flag(unloaded1)),
                process(p2, unload_flag(unloaded2)),
                process(c, consumer_of(p1, p2), restart="temporary"),
            ]
        ).start()
        sigkill(sup, c)

        assert [True, True] == [unloaded1.wait(10.0), unloaded2.wait(10.0)]
        held = [sup.run_in(p, lambda r: r.server_queries("res"), timeout=10.0) for p in (p1, p2)]
        assert [[], []] == held

    def test_a_temporary_consumer_that_dies_is_released_at_a_provider_in_a_nested_supervisor(
        self, supervisors: Callable[..., rr.Supervisor], uid: str, process_helpers: SharedObjects
    ) -> None:
        p, c = f"p-{uid}", f"c-{uid}"
        unloaded = process_helpers.event()
        inner = rr.SupervisorSpec(f"inner-{uid}", (process(p, unload_flag(unloaded)),))
        sup = supervisors([inner, process(c, consumer_of(p), restart="temporary")]).start()
        sigkill(sup, c)

        assert unloaded.wait(10.0)
        assert [] == sup.run_in(p, lambda r: r.server_queries("res"), timeout=10.0)

    def test_a_consumer_process_whose_supervisor_gave_up_for_good_is_released_at_its_provider(
        self, supervisors: Callable[..., rr.Supervisor], uid: str, process_helpers: SharedObjects
    ) -> None:
        p, c = f"p-{uid}", f"c-{uid}"
        unloaded = process_helpers.event()
        inner = rr.SupervisorSpec(
            f"inner-{uid}", (process(c, consumer_of(p)),), max_restarts=0, restart="temporary"
        )
        sup = supervisors([process(p, unload_flag(unloaded)), inner]).start()
        sigkill(sup, c)  # c is permanent, but its supervisor gives up for good

        assert unloaded.wait(10.0)
        assert [] == sup.run_in(p, lambda r: r.server_queries("res"), timeout=10.0)


def test_a_childs_exit_carries_its_supervisors_strategy_and_children_in_start_order(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    # (what the checker's `strategy` rule judges a decision against: one_for_all here)
    first, second = f"a-{uid}", f"b-{uid}"
    sup = supervisors(
        [rr.ManagerSpec(first), rr.ManagerSpec(second, restart="transient")],
        strategy="one_for_all",
    )
    heard: list[rr.events.Event] = []
    subscription = sup.subscribe(heard.append)
    sup.start()
    rr.testing.crash(sup.run_in(first, lambda r: r))
    sup.wait_restarted(first, timeout=10)
    sup.stop()
    assert subscription.wait_delivered(timeout=5)
    subscription.close()

    exits = [e for e in heard if isinstance(e, rr.events.ChildExited)]
    assert [(first, False), (second, True), (second, True), (first, True)] == [
        (e.child, e.stopped) for e in exits
    ]  # the crash, its sibling taken down, then the shutdown (reverse start order)
    assert {("one_for_all", (first, second))} == {(e.strategy, e.children) for e in exits}
    assert ["permanent", "transient"] == [e.restart for e in exits[:2]]
