"""The AF_UNIX carrier's system (`rr_actors._transport.unix.system`): its runtime
directory, its address, one owner per name; `TestLostForGood`: rule 19 from the
directory's files.
"""

from __future__ import annotations

import contextlib
import fcntl
import multiprocessing
import multiprocessing.connection
import multiprocessing.context
import multiprocessing.forkserver
import multiprocessing.synchronize
import os
import pickle
import signal
import socket
import stat
import sys
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._core.directory import DIRECTORY
from rr_actors._registrar.life import Served
from rr_actors._transport import System, SystemAddress, attach
from rr_actors._transport.messenger import Remote
from rr_actors.testing import expect_restart
from tests.support.carriers import (
    Children,
    ProviderFactory,
    Recorder,
    record_warnings,
    warnings_logged,
)
from tests.support.names import named
from tests.support.waiting import wait_for


@pytest.fixture
def system() -> Iterator[System]:  # type: ignore[no-redef]
    """A fresh AF_UNIX system (runtime directory + authkey), closed after the test."""
    created = System.create()
    yield created
    created.close()


# -- one owner per name ---------------------------------------------------------------------------


def contender_main(
    address: Any,
    names: list[str],
    barrier: multiprocessing.synchronize.Barrier,
    control: multiprocessing.connection.Connection,
) -> None:
    """For each name: serve it when all contenders are ready, report, unserve on "next"."""
    attached = attach(address)
    try:
        for name in names:
            with rr.ResourceRegistrar.start(name) as registrar:
                outcome = "served"
                barrier.wait(30)
                try:
                    attached.serve(Served(registrar))
                except rr.RrError as exc:
                    outcome = type(exc).__name__
                control.send(outcome)
                if control.recv() != "next":
                    return
    except (EOFError, OSError, threading.BrokenBarrierError):
        return
    finally:
        attached.close()


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


def kill(process: multiprocessing.process.BaseProcess) -> None:
    assert process.pid
    os.kill(process.pid, signal.SIGKILL)
    process.join(10)


def _connected(system: System, name: str) -> bool:
    dial = system._unix._dials.get(name)
    channel = None if dial is None else dial._channel
    return channel is not None and not channel.writer.closed


def _published(system: System, name: str) -> str:
    with open(system.address.restart_path(name), encoding="ascii") as restart:
        return restart.read()


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


# -- the runtime directory --------------------------------------------------------------------


def test_the_runtime_directory_is_private_to_its_user(system: System) -> None:
    assert 0o700 == stat.S_IMODE(os.stat(system.address.runtime_dir).st_mode)


def test_a_given_runtime_directory_is_made_private(tmp_path: Path) -> None:
    wanted = tmp_path / "run"
    wanted.mkdir(mode=0o755)
    created = System.create(str(wanted))
    try:
        assert 0o700 == stat.S_IMODE(os.stat(wanted).st_mode)
    finally:
        created.close()


def test_closing_a_system_keeps_a_given_directory_and_the_files_it_did_not_make(
    tmp_path: Path,
) -> None:
    wanted = tmp_path / "run"
    wanted.mkdir()
    (wanted / "notes.txt").write_text("mine")
    created = System.create(str(wanted))
    registrar = rr.ResourceRegistrar.start(f"kept-{uuid.uuid4().hex[:8]}")
    try:
        created.serve(Served(registrar))
    finally:
        registrar.stop()
        created.close()

    assert ["notes.txt"] == sorted(os.listdir(wanted))


def test_closing_a_system_removes_the_runtime_directory_it_made(tmp_path: Path) -> None:
    wanted = tmp_path / "made" / "run"
    created = System.create(str(wanted))
    registrar = rr.ResourceRegistrar.start(f"made-{uuid.uuid4().hex[:8]}")
    try:
        created.serve(Served(registrar))
    finally:
        registrar.stop()
        created.close()

    assert not wanted.exists()


def test_the_system_address_pickles_and_hides_its_key_in_its_repr(system: System) -> None:
    address = pickle.loads(pickle.dumps(system.address))

    assert system.address == address
    assert system.address.authkey.hex() not in repr(address)


def test_a_remote_peer_is_what_the_directory_hands_out_for_another_process(
    consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider()

    assert isinstance(DIRECTORY.lookup(provider.name), Remote)
    assert not isinstance(DIRECTORY.lookup(consumer.name), Remote)


def test_of_processes_racing_to_serve_one_name_exactly_one_serves_it(
    system: System, context: multiprocessing.context.ForkServerContext
) -> None:
    rounds, parties = 10, 4
    names = [f"contested-{number}-{uuid.uuid4().hex[:8]}" for number in range(rounds)]
    for name in names:  # each name starts with a socket left behind by a dead process
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as stale:
            stale.bind(system.address.socket_path(name))
    barrier = context.Barrier(parties)
    contenders = []
    for _ in range(parties):
        parent_end, child_end = context.Pipe()
        process = context.Process(
            target=contender_main, args=(system.address, names, barrier, child_end), daemon=True
        )
        process.start()
        child_end.close()
        contenders.append((process, parent_end))
    outcomes = []
    try:
        for _ in names:
            outcome = []
            for _process, control in contenders:
                assert control.poll(30), "a contender did not report"
                outcome.append(control.recv())
            outcomes.append(sorted(outcome))
            for _process, control in contenders:
                control.send("next")
    finally:
        for process, control in contenders:
            control.close()
            process.join(10)

    assert [["DuplicateNameError"] * (parties - 1) + ["served"]] * rounds == outcomes


def test_a_refused_duplicate_does_not_make_the_owner_log_a_warning(
    system: System, start_provider: ProviderFactory
) -> None:
    provider = start_provider()
    system.run(provider.name, record_warnings, timeout=10)
    with (
        rr.ResourceRegistrar.start(provider.name) as duplicate,
        pytest.raises(rr.DuplicateNameError),
    ):
        system.serve(Served(duplicate))

    assert [] == system.run(provider.name, warnings_logged, timeout=10)


class TestLostForGood:
    """Rule 19 on the AF_UNIX carrier: who speaks for a registrar, and when a process hears it.

    A listener publishes `<name>.restart`: nobody (`0`), or the process that speaks for it
    when its process dies (a manager's supervisor, `AttachedSystem.supervised_by`). A process
    judges a registrar when its connection to it ends or a connect to it fails: lost when
    nobody holds its lock and its speaker is gone too; awaited while the speaker lives.
    """

    pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")

    @pytest.fixture
    def unix(self) -> Iterator[System]:
        made = System.create()
        yield made
        made.close()

    @pytest.fixture
    def recorder(self, unix: System) -> Iterator[Recorder]:
        made = Recorder()
        unix.serve(made)
        yield made
        made.end()

    def test_the_restart_file_names_the_speaker_or_nobody(
        self, unix: System, children: Children, recorder: Recorder
    ) -> None:
        speaker, _ = children.start(speaker_main)
        spoken_for, alone = named("spoken"), named("alone")
        children.start(provider_main, unix.address, spoken_for, speaker.pid)
        children.start(provider_main, unix.address, alone, None)

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
        self, unix: System, children: Children, recorder: Recorder
    ) -> None:
        speaker, _ = children.start(speaker_main)
        spoken_for, alone = named("spoken"), named("alone")
        spoken_process, _ = children.start(provider_main, unix.address, spoken_for, speaker.pid)
        alone_process, _ = children.start(provider_main, unix.address, alone, None)
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
        self, unix: System, children: Children, recorder: Recorder
    ) -> None:
        speaker, _ = children.start(speaker_main)
        name = named("restarted")
        first, _ = children.start(provider_main, unix.address, name, speaker.pid)
        unix.run(name, id, timeout=10)
        kill(first)
        second, _ = children.start(provider_main, unix.address, name, None)  # "restarted"
        # awaited, then served again: this process connects to it by itself
        assert wait_for(lambda: _connected(unix, name), 5.0)

        kill(second)  # nobody speaks for this one, and this process sent it nothing

        assert recorder.wait_lost(name) is not None
        assert [name] == recorder.lost_names()

    def test_a_process_not_connected_when_the_provider_died_hears_at_its_next_connect(
        self, unix: System, children: Children, recorder: Recorder
    ) -> None:
        name = named("unconnected")
        kill(children.start(provider_main, unix.address, name, None)[0])
        assert [] == recorder.lost_names()  # (it never had a connection to see end)

        with pytest.raises(rr.RegistrarUnavailableError):
            unix.run(name, id, timeout=10)

        assert recorder.wait_lost(name) is not None
        assert [name] == recorder.lost_names()

    def test_a_listener_waits_out_a_probe_of_its_lock_but_not_an_owner(self, unix: System) -> None:
        name = named("probed")
        with rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name)) as registrar:
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

    @pytest.mark.usefixtures("process_helpers")  # the forkserver, before the leak check counts
    def test_a_manager_process_is_spoken_for_by_its_supervisors_process(self, unix: System) -> None:
        manager = named("manager")
        sup = rr.Supervisor(
            [rr.ManagerSpec(manager, setup=None, isolation="process")], network=unix
        ).start()
        try:
            assert str(os.getpid()) == _published(unix, manager).split()[0]
        finally:
            sup.stop()

    def test_a_manager_whose_supervisors_process_is_killed_is_lost(
        self, unix: System, children: Children, recorder: Recorder
    ) -> None:
        manager = named("manager")
        supervisor, _ = children.start(supervisor_main, unix.address, manager, daemon=False)
        assert wait_for(lambda: manager in unix.names(), 10.0)
        unix.run(manager, id, timeout=10)  # connected
        assert str(supervisor.pid) == _published(unix, manager).split()[0]

        kill(supervisor)  # its manager process exits too (its control pipe ends)

        assert recorder.wait_lost(manager) is not None
        assert [manager] == recorder.lost_names()
