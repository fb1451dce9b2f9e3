"""Rule 19 on the AF_UNIX carrier: who speaks for a registrar, and when a process hears it.

A listener publishes `<name>.restart`: nobody (`0`), or the process that speaks for it
when its process dies (a manager's supervisor, `AttachedSystem.supervised_by`). A process
judges a registrar when its connection to it ends or a connect to it fails: lost when
nobody holds its lock and its speaker is gone too; awaited while the speaker lives.
"""

from __future__ import annotations

import contextlib
import fcntl
import multiprocessing
import multiprocessing.connection
import multiprocessing.context
import os
import signal
import sys
import threading
from collections.abc import Iterator
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._transport import System, SystemAddress
from rr_actors.testing import expect_restart
from rr_actors.testing.carrier import Served
from tests.support.names import named
from tests.support.waiting import wait_for
from tests.transport.test_transport_lost import Recorder

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")


def speaker_main(control: multiprocessing.connection.Connection) -> None:
    """A process that only lives (it stands for a supervisor) until told to stop."""
    control.send("ready")
    with contextlib.suppress(EOFError, OSError):
        control.recv()


def provider_main(
    address: SystemAddress,
    name: str,
    speaker: int | None,
    control: multiprocessing.connection.Connection,
) -> None:
    """Serve registrar `name`, spoken for by process `speaker` (or nobody)."""
    attached = address.attach()
    attached.supervised_by(speaker)
    registrar = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name, call_timeout=10.0))
    try:
        attached.serve(Served(registrar))
        control.send("ready")
        with contextlib.suppress(EOFError, OSError):
            control.recv()
    finally:
        registrar.stop()
        attached.close()


class Processes:
    """Child processes of a test; all are stopped and reaped at its end."""

    def __init__(self, context: multiprocessing.context.ForkServerContext) -> None:
        self.context = context
        self.started: list[tuple[multiprocessing.process.BaseProcess, Any]] = []

    def start(
        self, target: Any, *args: Any, daemon: bool = True
    ) -> multiprocessing.process.BaseProcess:
        parent_end, child_end = self.context.Pipe()
        process = self.context.Process(target=target, args=(*args, child_end), daemon=daemon)
        process.start()
        child_end.close()
        self.started.append((process, parent_end))
        assert parent_end.poll(30), "the child did not get ready"
        assert "ready" == parent_end.recv()
        return process

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


@pytest.fixture
def processes(context: multiprocessing.context.ForkServerContext) -> Iterator[Processes]:
    started = Processes(context)
    yield started
    started.close()


@pytest.fixture
def unix() -> Iterator[System]:
    made = System.create()
    yield made
    made.close()


@pytest.fixture
def recorder(unix: System) -> Iterator[Recorder]:
    made = Recorder()
    unix.serve(made)
    yield made
    made.end()


def kill(process: multiprocessing.process.BaseProcess) -> None:
    assert process.pid
    os.kill(process.pid, signal.SIGKILL)
    process.join(10)


def test_the_restart_file_names_the_speaker_or_nobody(
    unix: System, processes: Processes, recorder: Recorder
) -> None:
    speaker = processes.start(speaker_main)
    spoken_for, alone = named("spoken"), named("alone")
    processes.start(provider_main, unix.address, spoken_for, speaker.pid)
    processes.start(provider_main, unix.address, alone, None)

    def published(name: str) -> str:
        with open(unix.address.restart_path(name), encoding="ascii") as restart:
            return restart.read()

    assert str(speaker.pid) == published(spoken_for).split()[0]
    assert "0" == published(alone)
    assert "0" == published(recorder.name)  # nobody restarts it
    restarted = Recorder()
    restarted.name = named("thread-manager")
    with expect_restart(restarted.name):  # a thread manager: its own process restarts it
        unix.serve(restarted)
    try:
        assert str(os.getpid()) == published(restarted.name).split()[0]
    finally:
        restarted.end()


def test_a_killed_provider_is_awaited_while_its_speaker_lives_and_lost_once_it_is_gone(
    unix: System, processes: Processes, recorder: Recorder
) -> None:
    speaker = processes.start(speaker_main)
    spoken_for, alone = named("spoken"), named("alone")
    spoken_process = processes.start(provider_main, unix.address, spoken_for, speaker.pid)
    alone_process = processes.start(provider_main, unix.address, alone, None)
    for name in (spoken_for, alone):
        unix.run(name, id, timeout=10)  # connected

    kill(spoken_process)
    kill(alone_process)
    assert recorder.wait_lost(alone) is not None  # (the control: judged after it)
    assert [alone] == recorder.lost_names()

    kill(speaker)  # nobody speaks for it any more

    assert recorder.wait_lost(spoken_for, timeout=1.0) is not None
    assert [alone, spoken_for] == recorder.lost_names()


def test_a_registrar_served_again_is_connected_at_once_so_its_next_death_is_heard(
    unix: System, processes: Processes, recorder: Recorder
) -> None:
    speaker = processes.start(speaker_main)
    name = named("restarted")
    first = processes.start(provider_main, unix.address, name, speaker.pid)
    unix.run(name, id, timeout=10)
    kill(first)
    second = processes.start(provider_main, unix.address, name, None)  # "restarted"
    # awaited, then served again: this process connects to it by itself
    assert wait_for(lambda: _connected(unix, name), 5.0)

    kill(second)  # nobody speaks for this one, and this process sent it nothing

    assert recorder.wait_lost(name) is not None
    assert [name] == recorder.lost_names()


def _connected(system: System, name: str) -> bool:
    peer = system._peers.get(name)
    channel = None if peer is None else peer._channel
    return channel is not None and not channel.writer.closed


def test_a_process_not_connected_when_the_provider_died_hears_at_its_next_connect(
    unix: System, processes: Processes, recorder: Recorder
) -> None:
    name = named("unconnected")
    kill(processes.start(provider_main, unix.address, name, None))
    assert [] == recorder.lost_names()  # (it never had a connection to see end)

    with pytest.raises(rr.RegistrarUnavailableError):
        unix.run(name, id, timeout=10)

    assert recorder.wait_lost(name) is not None
    assert [name] == recorder.lost_names()


def test_a_listener_waits_out_a_probe_of_its_lock_but_not_an_owner(unix: System) -> None:
    name = named("probed")
    registrar = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name))
    try:
        owner = os.open(unix.address.lock_path(name), os.O_RDONLY | os.O_CREAT, 0o600)
        fcntl.flock(owner, fcntl.LOCK_SH | fcntl.LOCK_NB)  # held for good
        try:
            with pytest.raises(rr.DuplicateNameError):
                unix.serve(Served(registrar))
        finally:
            os.close(owner)

        probe = os.open(unix.address.lock_path(name), os.O_RDONLY)
        fcntl.flock(probe, fcntl.LOCK_SH | fcntl.LOCK_NB)  # a probe: let go of soon
        threading.Timer(0.02, os.close, (probe,)).start()
        unix.serve(Served(registrar))

        assert name in unix.served()
    finally:
        registrar.stop()


def _published(system: System, name: str) -> str:
    with open(system.address.restart_path(name), encoding="ascii") as restart:
        return restart.read()


@pytest.mark.usefixtures("process_helpers")  # the forkserver, before the leak check counts
def test_a_manager_process_is_spoken_for_by_its_supervisors_process(unix: System) -> None:
    manager = named("manager")
    sup = rr.Supervisor(
        [rr.ManagerSpec(manager, setup=None, isolation="process")], network=unix
    ).start()
    try:
        assert str(os.getpid()) == _published(unix, manager).split()[0]
    finally:
        sup.stop()


def supervisor_main(
    address: SystemAddress, manager: str, control: multiprocessing.connection.Connection
) -> None:
    """A process that supervises manager process `manager` on the system."""
    attached = address.attach()
    sup = rr.Supervisor(
        [rr.ManagerSpec(manager, setup=None, isolation="process")], network=attached
    ).start()
    try:
        control.send("ready")
        with contextlib.suppress(EOFError, OSError):
            control.recv()
    finally:
        sup.stop()


def test_a_manager_whose_supervisors_process_is_killed_is_lost(
    unix: System, processes: Processes, recorder: Recorder
) -> None:
    manager = named("manager")
    supervisor = processes.start(supervisor_main, unix.address, manager, daemon=False)
    assert wait_for(lambda: manager in unix.names(), 10.0)
    unix.run(manager, id, timeout=10)  # connected
    assert str(supervisor.pid) == _published(unix, manager).split()[0]

    kill(supervisor)  # its manager process exits too (its control pipe ends)

    assert recorder.wait_lost(manager) is not None
    assert [manager] == recorder.lost_names()
