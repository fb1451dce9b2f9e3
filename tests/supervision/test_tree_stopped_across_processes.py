"""A host's tree stopped for good is a clean stop at its consumers elsewhere, not a loss.

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
import uuid
from collections.abc import Iterator
from typing import Any

import pytest

import rr_actors as rr
from tests.support.carriers import own_provider_main, setup_servers
from tests.support.waiting import wait_for

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
        for process, control in self.processes:
            process.join(30)
            if process.is_alive():
                process.kill()
                process.join(10)
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
