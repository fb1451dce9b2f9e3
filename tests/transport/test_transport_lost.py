"""The carrier contract's rule 19, for every carrier: a provider gone for good is lost.

A registrar of another process that is gone and that nobody will restart is *lost*: the
carrier calls `Endpoint.peer_lost(name)` on every endpoint it serves in this process, and
a real consumer registrar reports `FATAL` for the ids it held there (once) and forgets
them. A provider whose supervisor lives on is not lost; nor is one stopped cleanly.

Each test also kills an unsupervised provider as a control, so that "not lost" is not
merely "the carrier never says lost". Real processes, real SIGKILLs; each test runs once
per carrier (`CARRIERS`). An unsupervised provider is a process that joins the system
by itself: on AF_UNIX it attaches the system's address; on Zenoh it is a router of its
own that connects to the test's, or (`zenoh-attached`) a process that attaches through the
test's router: only a manager process that router started counts as supervised by it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import multiprocessing.connection
import multiprocessing.context
import os
import signal
import socket
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._transport import Transport
from rr_actors.testing.carrier import Served
from tests.support.carriers import CARRIERS, setup_servers
from tests.support.waiting import wait_for

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")

LOST_WITHIN = 1.0
"""Seconds from a SIGKILL to `peer_lost` (the issue's bound)."""


class Recorder:
    """An `Endpoint` that records the `peer_lost` calls it gets (no registrar behind it)."""

    def __init__(self) -> None:
        self.name = f"recorder-{uuid.uuid4().hex[:8]}"
        self.max_message_bytes = 1024 * 1024
        self.lost: list[tuple[str, float]] = []
        self.changed = threading.Condition()
        self._ended = threading.Event()

    def run(self, fn: Callable[[Any], Any]) -> Any:
        return fn(None)

    def wait_ended(self, timeout: float | None = None) -> bool:
        return self._ended.wait(timeout)

    def stopped_cleanly(self) -> bool:
        return self._ended.is_set()

    def listening(self) -> None:
        pass

    def peer_lost(self, name: str) -> None:
        with self.changed:
            self.lost.append((name, time.monotonic()))
            self.changed.notify_all()

    def peer_reachable(self, name: str) -> None:
        pass

    def lost_names(self) -> list[str]:
        with self.changed:
            return [name for name, _ in self.lost]

    def wait_lost(self, name: str, timeout: float = 5.0) -> float | None:
        """When `name` was first reported lost (monotonic), waiting up to `timeout` s."""
        with self.changed:
            self.changed.wait_for(lambda: name in [n for n, _ in self.lost], timeout)
            return next((at for n, at in self.lost if n == name), None)

    def end(self) -> None:
        self._ended.set()


# -- the provider's process ----------------------------------------------------------------------


def own_provider_main(
    join: tuple[Any, ...], name: str, control: multiprocessing.connection.Connection
) -> None:
    """An unsupervised provider process: joins the system by itself (`join`: `("attach",
    address)`, or `("router", system, endpoint)` for a Zenoh router of its own), serves
    registrar `name` with the `carriers` servers until told to stop, then stops cleanly."""
    if join[0] == "attach":
        transport = join[1].attach()
    else:
        transport = rr.ZenohNetwork(system=join[1], connect=[join[2]], tls=None)
    registrar = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name, call_timeout=10.0))
    try:
        setup_servers(registrar)
        transport.serve(Served(registrar))
        control.send("ready")
        with contextlib.suppress(EOFError, OSError):
            control.recv()
    finally:
        registrar.stop()
        transport.close()


# -- per carrier ----------------------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


@dataclasses.dataclass
class Lab:
    """The test process's system on one carrier, and its provider processes."""

    carrier: str
    system: Transport
    join: tuple[Any, ...]
    context: multiprocessing.context.ForkServerContext
    started: list[tuple[multiprocessing.process.BaseProcess, Any]] = dataclasses.field(
        default_factory=list
    )
    endpoints: list[Recorder] = dataclasses.field(default_factory=list)

    def provider(self) -> tuple[str, multiprocessing.process.BaseProcess, Any]:
        """Start an unsupervised provider process; once other processes see it."""
        name = f"provider-{uuid.uuid4().hex[:8]}"
        parent_end, child_end = self.context.Pipe()
        process = self.context.Process(
            target=own_provider_main, args=(self.join, name, child_end), daemon=True
        )
        process.start()
        child_end.close()
        self.started.append((process, parent_end))
        assert parent_end.poll(30), "the provider process did not get ready"
        assert "ready" == parent_end.recv()
        assert wait_for(lambda: name in self.system.names(), 10.0), f"{name} not seen"
        self.connect(name)
        return name, process, parent_end

    def connect(self, name: str) -> None:
        """Reach registrar `name` once from this process (AF_UNIX: opens its connection)."""
        assert isinstance(self.system.run(name, id, timeout=10), int)

    def recorder(self) -> Recorder:
        """An endpoint served on the system in this process."""
        recorder = Recorder()
        self.system.serve(recorder)
        self.endpoints.append(recorder)
        return recorder

    def close(self) -> None:
        for _, control in self.started:
            with contextlib.suppress(OSError):
                control.send("stop")
        for process, control in self.started:
            process.join(10)
            if process.is_alive():
                process.kill()
                process.join(5)
            control.close()
            with contextlib.suppress(ValueError):  # its sentinel now, not at a later GC
                process.close()
        for recorder in self.endpoints:
            recorder.end()
        self.system.close()


@pytest.fixture(params=[*sorted(CARRIERS), "zenoh-attached"])
def lab(
    request: pytest.FixtureRequest, context: multiprocessing.context.ForkServerContext
) -> Iterator[Lab]:
    carrier = request.param
    if carrier == "unix":
        system = CARRIERS["unix"]()
        join: tuple[Any, ...] = ("attach", system.address)
    elif carrier == "zenoh":
        endpoint = f"tcp/127.0.0.1:{_free_port()}"
        name = f"lost-{uuid.uuid4().hex[:8]}"
        system = rr.ZenohNetwork(system=name, listen=[endpoint], tls=None)
        join = ("router", name, endpoint)
    elif carrier == "zenoh-attached":  # joins through the test's router, unsupervised
        system = CARRIERS["zenoh"]()
        join = ("attach", system.address)
    else:
        raise AssertionError(f"no unsupervised provider for carrier {carrier!r} yet")
    made = Lab(carrier, system, join, context)
    yield made
    made.close()


def kill(process: multiprocessing.process.BaseProcess) -> float:
    """SIGKILL `process` (not reaped yet: its parent does that later); when it was sent."""
    assert process.pid
    killed_at = time.monotonic()
    os.kill(process.pid, signal.SIGKILL)
    return killed_at


# -- the tests ------------------------------------------------------------------------------------


def test_a_killed_unsupervised_provider_is_lost_its_consumer_hears_fatal_once_and_forgets(
    lab: Lab,
) -> None:
    name, process, _ = lab.provider()
    recorder = lab.recorder()
    heard: list[tuple[str, rr.Status, str]] = []
    consumer = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=f"consumer-{uuid.uuid4().hex[:8]}", call_timeout=30.0),
        network=lab.system,
    )
    try:
        query = consumer.call(
            name,
            "echo",
            {"cam": 1},
            on_status=lambda q, u: heard.append((q.id, u.status, u.source)),
        )

        killed_at = kill(process)
        lost_at = recorder.wait_lost(name)

        assert lost_at is not None, f"{name} was never reported lost"
        assert lost_at - killed_at < LOST_WITHIN
        assert wait_for(lambda: bool(heard), 5.0)
        assert [] == [q for q in consumer.client_queries() if q.serving_rr == name]
        assert [(query.id, rr.Status.FATAL, f"{name}/echo")] == heard  # once
        with pytest.raises(rr.UnknownQueryError):
            consumer.unload(query.id, timeout=5)
        assert [name] == recorder.lost_names()
    finally:
        consumer.stop()


def test_a_killed_manager_whose_supervisor_lives_is_not_lost(lab: Lab) -> None:
    manager = f"manager-{uuid.uuid4().hex[:8]}"
    sup = rr.Supervisor(
        [rr.ManagerSpec(manager, setup=None, isolation="process")], network=lab.system
    ).start()
    try:
        control, control_process, _ = lab.provider()
        recorder = lab.recorder()
        assert wait_for(lambda: manager in lab.system.names(), 10.0)
        lab.connect(manager)
        pid = sup.child(manager).pid
        assert pid

        os.kill(pid, signal.SIGKILL)
        kill(control_process)
        sup.wait_restarted(manager, timeout=15)
        assert recorder.wait_lost(control) is not None  # the carrier does say "lost"
        assert wait_for(lambda: manager in lab.system.names(), 10.0)
        os.kill(sup.child(manager).pid or 0, 0)  # (the restarted one runs)

        assert [control] == recorder.lost_names()
    finally:
        sup.stop()


def test_a_provider_stopped_cleanly_is_not_lost(lab: Lab) -> None:
    stopped, stopped_process, stopped_control = lab.provider()
    control, control_process, _ = lab.provider()
    recorder = lab.recorder()
    consumer = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=f"consumer-{uuid.uuid4().hex[:8]}", call_timeout=30.0),
        network=lab.system,
    )
    try:
        consumer.call(stopped, "echo", "r")  # connected, and holds an id there

        stopped_control.send("stop")
        stopped_process.join(10)
        assert 0 == stopped_process.exitcode
        kill(control_process)  # after the stop: its loss is reported after the stop's
        assert recorder.wait_lost(control) is not None

        assert [control] == recorder.lost_names()
    finally:
        consumer.stop()
