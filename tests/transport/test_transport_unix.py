"""The AF_UNIX carrier's own guarantees: its runtime directory, the authkey handshake,
one owner per name, malformed frames, and the pieces (codec, writer, framing)."""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import multiprocessing.connection
import multiprocessing.context
import multiprocessing.forkserver
import multiprocessing.synchronize
import os
import pickle
import resource
import select
import signal
import socket
import stat
import struct
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr
from rr_actors._core.directory import DIRECTORY
from rr_actors._transport import RemotePeer, System, attach
from rr_actors._transport.codec import frame, frames, plain, unframe
from rr_actors._transport.unix.link import HANDSHAKE_TIMEOUT, Listener, Writer, _Channel, connect
from rr_actors.testing.carrier import Fetch, Load, Revoke, Served
from tests.support.carriers import (
    ProviderFactory,
    load_count,
    record_warnings,
    setup_servers,
    warnings_logged,
)


@pytest.fixture
def system() -> Iterator[System]:  # type: ignore[no-redef]
    """A fresh AF_UNIX system (runtime directory + authkey), closed after the test."""
    created = System.create()
    yield created
    created.close()


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


class _SlowShutdown:
    """A listening socket whose `shutdown` waits for `release` (to hold a close mid-way)."""

    def __init__(self, sock: socket.socket, entered: threading.Event, release: threading.Event):
        self.sock, self.entered, self.release = sock, entered, release

    def shutdown(self, how: int) -> None:
        self.entered.set()
        self.release.wait(10)
        self.sock.shutdown(how)

    def close(self) -> None:
        self.sock.close()


def test_a_second_close_of_a_listener_returns_only_once_the_first_finished(
    system: System, consumer: rr.ResourceRegistrar
) -> None:
    # The registrar's watcher and the system's close() may both close its listener; a
    # process that exits after its own close() must not leave the socket half closed
    # (the watcher is a daemon thread: the exit cuts it short).
    listener = system.serving(consumer.name)
    assert isinstance(listener, Listener)
    entered, release, second_done = threading.Event(), threading.Event(), threading.Event()
    listener._sock = _SlowShutdown(listener._sock, entered, release)  # type: ignore[assignment]

    def second() -> None:
        system._unserve(listener, stopped=True)  # (the system's close)
        second_done.set()

    first_thread = threading.Thread(  # (the registrar's watcher)
        target=system._unserve, args=(listener,), kwargs={"stopped": True}
    )
    second_thread = threading.Thread(target=second)
    try:
        first_thread.start()
        assert entered.wait(10)
        second_thread.start()
        assert not second_done.wait(0.3), "returned while the first close was half way"
    finally:
        release.set()
        first_thread.join(10)
        second_thread.join(10)

    assert second_done.is_set()
    assert (True, False) == (os.path.exists(listener.tombstone), os.path.exists(listener.path))


def test_closing_the_system_waits_for_a_stopped_registrar_s_listener_to_close(
    system: System,
) -> None:
    # The registrar's watcher thread closes its listener when the registrar stops, while
    # the process may already be in `close()` of its system, on its way out.
    registrar = rr.ResourceRegistrar.start(f"closing-{uuid.uuid4().hex[:8]}")
    system.serve(Served(registrar))
    listener = system.serving(registrar.name)
    assert isinstance(listener, Listener)
    entered, release, closed = threading.Event(), threading.Event(), threading.Event()
    listener._sock = _SlowShutdown(listener._sock, entered, release)  # type: ignore[assignment]

    def close_system() -> None:
        system.close()
        closed.set()

    closing = threading.Thread(target=close_system)
    try:
        registrar.stop()  # the watcher starts closing the listener, and is held half way
        assert entered.wait(10)
        closing.start()
        assert not closed.wait(0.3), "the system closed while the listener was half closed"
    finally:
        release.set()
        closing.join(10)

    assert closed.is_set()
    assert not os.path.exists(listener.path)  # (the system's close removed the tombstone)


# -- authentication --------------------------------------------------------------------------------


class _Marker:
    """A payload whose unpickling would create a file (to show nothing was unpickled)."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, ...]:
        return (Path.touch, (Path(self.path),))


def _drain_until_closed(conn: multiprocessing.connection.Connection) -> bool:
    """Read until the other side closes the connection; False if it stays open for 10 s."""
    while True:
        try:
            if not conn.poll(10):
                return False
            conn.recv_bytes()
        except (EOFError, OSError):
            return True


def _evil_load(name: str, marker: str) -> bytes:
    message = Load("q-1", "echo", _Marker(marker), "intruder", (), None)  # type: ignore[arg-type]
    payload: bytes = cloudpickle.dumps(message)
    return b"\x00" * 8 + payload


def test_a_client_with_the_wrong_authkey_is_refused_and_nothing_runs(
    system: System,
    consumer: rr.ResourceRegistrar,
    start_provider: ProviderFactory,
) -> None:
    provider = start_provider()
    path = system.address.socket_path(provider.name)

    with pytest.raises(multiprocessing.AuthenticationError):
        multiprocessing.connection.Client(path, family="AF_UNIX", authkey=os.urandom(32))

    assert 0 == system.run(provider.name, load_count, timeout=10)
    assert {"resource": "ok"} == consumer.call(provider.name, "echo", "ok").response


def test_a_client_without_an_authkey_is_refused_before_its_payload_is_unpickled(
    system: System,
    consumer: rr.ResourceRegistrar,
    start_provider: ProviderFactory,
    tmp_path: Path,
) -> None:
    provider = start_provider()
    marker = tmp_path / "unpickled"
    conn = multiprocessing.connection.Client(
        system.address.socket_path(provider.name), family="AF_UNIX"
    )
    try:
        for _ in range(3):
            conn.send_bytes(_evil_load(provider.name, str(marker)))
        assert _drain_until_closed(conn), "the listener kept an unauthenticated connection"
    finally:
        conn.close()

    assert not marker.exists()
    assert 0 == system.run(provider.name, load_count, timeout=10)
    assert {"resource": "ok"} == consumer.call(provider.name, "echo", "ok").response


def test_a_stalled_unauthenticated_client_does_not_block_others(
    consumer: rr.ResourceRegistrar, start_provider: ProviderFactory, system: System
) -> None:
    provider = start_provider()
    silent = multiprocessing.connection.Client(
        system.address.socket_path(provider.name), family="AF_UNIX"
    )
    try:
        query = consumer.call(provider.name, "echo", "ok", timeout=10)
    finally:
        silent.close()

    assert {"resource": "ok"} == query.response


def test_a_remote_peer_is_what_the_directory_hands_out_for_another_process(
    consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider()

    assert isinstance(DIRECTORY.lookup(provider.name), RemotePeer)
    assert not isinstance(DIRECTORY.lookup(consumer.name), RemotePeer)


# -- crowds, slow handshakes and a full descriptor table -----------------------------------------


def _raw_connections(path: str, count: int) -> list[socket.socket]:
    """`count` connections to `path` that never say a word (no handshake)."""
    made = []
    for _ in range(count):
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.settimeout(10)
        sock.connect(path)
        made.append(sock)
    return made


def few_descriptors(registrar: rr.ResourceRegistrar) -> None:
    """The provider's servers, in a process allowed 64 open files."""
    _soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (64, hard))
    setup_servers(registrar)


def test_a_listener_out_of_file_descriptors_accepts_again_once_some_are_free(
    system: System, start_provider: ProviderFactory, eventually: Callable[..., bool]
) -> None:
    provider = start_provider(few_descriptors)
    system.run(provider.name, record_warnings, timeout=10)  # (over a connection made now)
    raw = _raw_connections(system.address.socket_path(provider.name), 60)
    try:
        assert eventually(
            lambda: any(
                "cannot accept" in warning
                for warning in system.run(provider.name, warnings_logged, timeout=10)
            ),
            timeout=10,
        ), "the listener did not report that it cannot accept"
    finally:
        for sock in raw:
            sock.close()
    newcomer = system.link().peer(provider.name)  # a peer with a connection of its own
    try:
        assert 0 == newcomer.run(load_count, timeout=10)
    finally:
        newcomer.close(rr.RegistrarStoppedError("the test is over"))


def _handshake_as_listener(listening: socket.socket, authkey: bytes, count: int) -> None:
    """Accept `count` connections, one after the other, and pass the handshake with each."""
    for _ in range(count):
        accepted, _ = listening.accept()
        accepted.settimeout(None)  # (each client gives up after its own deadline)
        conn = multiprocessing.connection.Connection(accepted.detach())
        with conn, contextlib.suppress(EOFError, OSError):
            multiprocessing.connection.deliver_challenge(conn, authkey)
            multiprocessing.connection.answer_challenge(conn, authkey)


def _pending_connections(path: str) -> int:
    """How many connections to the listener at `path` it has not accepted yet (Linux).

    Each one is a socket listed in `/proc/net/unix` with the listener's path and the
    state "connecting" (02); the listener is "unconnected" (01), accepted ones "connected".
    """
    with open("/proc/net/unix", encoding="ascii") as table:
        rows = [line.split() for line in table.readlines()[1:]]
    return sum(1 for row in rows if len(row) == 8 and row[7] == path and row[5] == "02")


def _stopped(pid: int) -> bool:
    """Whether every thread of process `pid` is stopped (SIGSTOP takes effect a bit later)."""
    states = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            states.append((task / "stat").read_text().rsplit(")", 1)[1].split()[0])
    return bool(states) and all(state in ("T", "t") for state in states)


def test_a_connect_to_a_full_backlog_waits_for_room_instead_of_failing(
    system: System, eventually: Callable[..., bool]
) -> None:
    path = system.address.socket_path(f"crowded-{uuid.uuid4().hex[:8]}")
    peers = 5
    entered: list[int] = []
    outcomes: list[Any] = []

    def connect_once() -> None:
        entered.append(1)
        try:
            sock, conn = connect(path, system.address.authkey)
        except Exception as exc:
            outcomes.append(exc)
            return
        conn.close()
        sock.close()
        outcomes.append("connected")

    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as listening:
        listening.bind(path)
        listening.listen(1)  # room for one: the others find the backlog full
        listening.settimeout(10)
        threads = [threading.Thread(target=connect_once) for _ in range(peers)]
        for thread in threads:
            thread.start()
        # the backlog is full (two queued: Linux counts one more than asked) and every peer
        # is trying to connect before the listener accepts anyone
        assert eventually(lambda: len(entered) == peers and _pending_connections(path) >= 2)
        _handshake_as_listener(listening, system.address.authkey, peers)
        for thread in threads:
            thread.join(10)

    assert ["connected"] * peers == outcomes


def test_two_hundred_peers_connecting_at_once_to_a_busy_listener_all_get_through(
    system: System, start_provider: ProviderFactory, eventually: Callable[..., bool]
) -> None:
    provider = start_provider()
    path = system.address.socket_path(provider.name)
    peers = [system.link().peer(provider.name) for _ in range(200)]
    outcomes: list[Any] = []

    def run(peer: RemotePeer) -> None:
        try:
            outcomes.append(peer.run(load_count, timeout=30))
        except Exception as exc:
            outcomes.append(exc)

    threads = [threading.Thread(target=run, args=(peer,)) for peer in peers]
    os.kill(provider.pid, signal.SIGSTOP)  # it accepts nobody until every peer has tried
    try:
        assert eventually(lambda: _stopped(provider.pid))
        for thread in threads:
            thread.start()
        eventually(lambda: _pending_connections(path) + len(outcomes) >= len(peers), timeout=20)
    finally:
        os.kill(provider.pid, signal.SIGCONT)
    for thread in threads:
        thread.join(40)
    for peer in peers:
        peer.close(rr.RegistrarStoppedError("the test is over"))

    assert [0] * len(peers) == outcomes


def test_a_handshake_trickled_byte_by_byte_is_cut_off_at_its_deadline(
    system: System, consumer: rr.ResourceRegistrar
) -> None:
    # Each byte comes well within the time one read may take; the whole handshake does not.
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as slow:
        slow.connect(system.address.socket_path(consumer.name))
        started = time.monotonic()
        slow.settimeout(10)
        challenge = slow.recv(4096)  # the listener's challenge
        assert challenge
        slow.sendall(struct.pack("!i", 200))  # an answer of 200 bytes is coming ...
        closed = False
        while not closed and time.monotonic() - started < HANDSHAKE_TIMEOUT + 5:
            readable, _, _ = select.select([slow], [], [], 0.5)  # ... one byte per 0.5 s
            if readable:
                closed = slow.recv(4096) == b""
            else:
                slow.sendall(b"\x00")
        took = time.monotonic() - started

    assert (True, True) == (closed, took < HANDSHAKE_TIMEOUT + 1.5), f"took {took:.1f} s"


# -- malformed frames from an authenticated peer -------------------------------------------------


def _raw_client(system: System, name: str) -> multiprocessing.connection.Connection:
    """A connection to registrar `name` that passed the handshake (it knows the authkey)."""
    return multiprocessing.connection.Client(
        system.address.socket_path(name), family="AF_UNIX", authkey=system.address.authkey
    )


def _answer_to(conn: multiprocessing.connection.Connection, token: int) -> Any:
    """The next answer on `conn` (bounded wait), which must carry `token`."""
    assert conn.poll(10), "no answer came"
    data = conn.recv_bytes()
    assert token == struct.unpack_from("<Q", data)[0]
    return pickle.loads(data[8:])


def test_a_short_frame_from_an_authenticated_peer_leaves_its_connection_serving(
    system: System, start_provider: ProviderFactory
) -> None:
    provider = start_provider()
    conn = _raw_client(system, provider.name)
    try:
        conn.send_bytes(b"\x01\x02")
        fetch = Fetch("echo", "intruder", None)  # type: ignore[arg-type]
        conn.send_bytes(struct.pack("<Q", 7) + cloudpickle.dumps(fetch))
        answer = _answer_to(conn, 7)
    finally:
        conn.close()

    assert ([], None) == answer


def test_a_message_without_a_reply_field_is_answered_with_an_error(
    system: System, start_provider: ProviderFactory
) -> None:
    provider = start_provider()
    conn = _raw_client(system, provider.name)
    try:
        conn.send_bytes(struct.pack("<Q", 9) + pickle.dumps(42))
        _value, error = _answer_to(conn, 9)
    finally:
        conn.close()

    assert isinstance(error, rr.RrError)


def test_a_frame_over_the_limit_is_refused_before_its_body_arrives_and_the_link_keeps_serving(
    system: System, start_provider: ProviderFactory
) -> None:
    limit = 1024 * 1024
    provider = start_provider(max_message_bytes=limit)
    conn = _raw_client(system, provider.name)
    body = b"\x00" * (2 * limit)
    try:
        with socket.socket(fileno=os.dup(conn.fileno())) as raw:
            raw.sendall(struct.pack("!i", 8 + len(body)) + struct.pack("<Q", 5))
            _value, error = _answer_to(conn, 5)  # answered before the body was sent
            raw.sendall(body)
        fetch = Fetch("echo", "intruder", None)  # type: ignore[arg-type]
        conn.send_bytes(struct.pack("<Q", 7) + cloudpickle.dumps(fetch))
        answer = _answer_to(conn, 7)
    finally:
        conn.close()

    assert (True, len(body), limit) == (
        isinstance(error, rr.MessageTooLargeError),
        error.size,
        error.limit,
    )
    assert ([], None) == answer


def _fake_provider(listening: socket.socket, authkey: bytes) -> None:
    """Accept one connection; before the first answer send a short frame, answer the rest."""
    try:
        accepted, _ = listening.accept()
    except OSError:
        return
    accepted.settimeout(None)
    conn = multiprocessing.connection.Connection(accepted.detach())
    with contextlib.suppress(EOFError, OSError):
        multiprocessing.connection.deliver_challenge(conn, authkey)
        multiprocessing.connection.answer_challenge(conn, authkey)
        value: Any = "from the fake"
        while True:
            (token,) = struct.unpack_from("<Q", conn.recv_bytes())
            if value is not None:
                conn.send_bytes(b"\x01")
            if token:
                conn.send_bytes(struct.pack("<Q", token) + pickle.dumps((value, None)))
            value = None
    conn.close()


def test_a_malformed_answer_does_not_stop_the_reader_of_its_connection(
    system: System, consumer: rr.ResourceRegistrar
) -> None:
    name = f"fake-{uuid.uuid4().hex[:8]}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as listening:
        listening.bind(system.address.socket_path(name))
        listening.listen(1)
        listening.settimeout(10)
        threading.Thread(
            target=_fake_provider, args=(listening, system.address.authkey), daemon=True
        ).start()
        query = consumer.call(name, "echo", "r", timeout=10)

    assert "from the fake" == query.response


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
            registrar = rr.ResourceRegistrar.start(name)
            try:
                outcome = "served"
                barrier.wait(30)
                try:
                    attached.serve(Served(registrar))
                except rr.RrError as exc:
                    outcome = type(exc).__name__
                control.send(outcome)
                if control.recv() != "next":
                    return
            finally:
                registrar.stop()
    except (EOFError, OSError, threading.BrokenBarrierError):
        return
    finally:
        attached.close()


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
    duplicate = rr.ResourceRegistrar.start(provider.name)
    try:
        with pytest.raises(rr.DuplicateNameError):
            system.serve(Served(duplicate))
    finally:
        duplicate.stop()

    assert [] == system.run(provider.name, warnings_logged, timeout=10)


# -- internals -----------------------------------------------------------------------------------


class _CountingReply:
    """A reply that counts how often it was answered."""

    __slots__ = ("answers",)

    def __init__(self) -> None:
        self.answers = 0

    def set_result(self, _value: Any) -> None:
        self.answers += 1

    def set_error(self, _error: BaseException) -> None:
        self.answers += 1


def _lose_while_reading(system: System, answers: int) -> list[int]:
    """Close a peer's channel while a thread pops its answers; tokens not answered once."""
    peer = system.link().peer(f"nobody-{uuid.uuid4().hex[:8]}")
    assert isinstance(peer, RemotePeer)
    channel = _Channel(Writer(None, lambda _exc: None))
    peer._channel = channel
    replies = {token: _CountingReply() for token in range(1, answers + 1)}
    channel.pending.update((token, (reply, None)) for token, reply in replies.items())
    go = threading.Event()

    def reader() -> None:  # what the reader thread does with each answer
        go.wait(10)
        for token in reversed(replies):
            entry = channel.pending.pop(token, None)
            if entry is not None:
                entry[0].set_result(None)

    thread = threading.Thread(target=reader)
    thread.start()
    go.set()
    try:
        peer.close(rr.RegistrarStoppedError("closing"))
    finally:
        thread.join(10)
    return [token for token, reply in replies.items() if reply.answers != 1]


def test_losing_a_connection_while_its_reader_resolves_answers_answers_each_reply_once(
    system: System,
) -> None:
    switch_interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads as often as possible
    try:
        trials = [_lose_while_reading(system, 100_000) for _ in range(5)]
    finally:
        sys.setswitchinterval(switch_interval)

    assert [[]] * 5 == trials


# -- encoding: the C pickler's fast path ----------------------------------------------------


class _MyStr(str):
    """A subclass of a builtin: not plain."""


def _nested(depth: int) -> list[Any]:
    value: list[Any] = []
    for _ in range(depth):
        value = [value]
    return value


@pytest.mark.parametrize(
    "value",
    [
        Load("q1", "leaf", {"cmd": ["driver", "--id", 7], "rate": 2.5}, "C", ("C",), None),  # type: ignore[arg-type]
        Fetch("leaf", "C", None),  # type: ignore[arg-type]
        rr.Query("q2", "leaf", "P", "C", ("a", 1), {"pid": 4}),
        ("answer", 3, None, b"x", frozenset({1}), {2, 3}),
        rr.Status.FATAL,
    ],
)
def test_small_builtin_data_is_pickled_by_the_c_pickler_as_cloudpickle_would(value: Any) -> None:
    assert plain(value)
    data = frame(9, value)
    token, payload = unframe(data[4:])
    assert token == 9
    assert pickle.loads(payload) == value
    assert bytes(payload) == cloudpickle.dumps(value, pickle.HIGHEST_PROTOCOL)


@pytest.mark.parametrize(
    "value",
    [
        {"f": lambda: 1},  # needs cloudpickle
        [_MyStr("x")],  # a subclass
        Load("q1", "leaf", {"at": uuid.UUID(int=1)}, "C", (), None),  # not builtin data
        list(range(300)),  # too wide
        _nested(70),  # too deep
    ],
)
def test_anything_else_goes_through_cloudpickle(value: Any) -> None:
    assert not plain(value)
    token, payload = unframe(frame(1, value)[4:])
    assert token == 1
    decoded = cloudpickle.loads(payload)
    if not isinstance(value, dict):
        assert decoded == value


def test_a_writer_closed_while_a_sender_writes_closes_its_socket_after_that_write() -> None:
    # close() comes while a sender writes inline (under the writer's lock): the socket is
    # closed once that write returned, by the closing thread, not under it, not never
    entered, release, shut = (threading.Event() for _ in range(3))
    seen: list[str] = []

    class Socket:  # holds the sender inside its send() until told
        def send(self, data: bytes, flags: int) -> int:
            entered.set()
            release.wait(10)
            seen.append("write returned")
            return len(data)

        def shutdown(self, how: int) -> None:
            shut.set()

        def close(self) -> None:
            seen.append("closed")

    writer = Writer(Socket(), lambda exc: None, "test-writer")  # type: ignore[arg-type]
    sender = threading.Thread(target=writer.send, args=(b"frame",))
    sender.start()
    assert entered.wait(10)
    closer = threading.Thread(target=writer.close)
    closer.start()
    assert shut.wait(10)  # the closer is past its shutdown, at the write it waits for
    assert [] == seen  # the sender still writes on it
    release.set()
    sender.join(10)
    closer.join(10)
    assert ["write returned", "closed"] == seen
    assert not any(t.name == "test-writer" for t in threading.enumerate())


def test_a_load_crosses_without_its_reply_and_otherwise_unchanged() -> None:
    load = Load("q", "leaf", {"n": 1}, "C", ("C",), object())  # type: ignore[arg-type]
    assert load.detached() == dataclasses.replace(load, reply=None)


def test_every_wire_message_crosses_without_its_reply() -> None:
    fetch = Fetch("leaf", "C", object())  # type: ignore[arg-type]
    assert fetch.detached() == dataclasses.replace(fetch, reply=None)
    assert Revoke(("q",)).detached() == Revoke(("q",))  # (no reply to keep)


# -- cutting frames out of the byte stream ------------------------------------------------------


def _frames_of(chunks: list[bytes]) -> list[bytes]:
    """What `_frames` yields for a peer that writes `chunks` one by one, then closes."""
    ours, theirs = socket.socketpair()
    conn = multiprocessing.connection.Connection(ours.detach())
    got: list[bytes] = []
    reader = threading.Thread(target=lambda: got.extend(frames(conn)))
    reader.start()
    with theirs:
        for chunk in chunks:
            theirs.sendall(chunk)
    reader.join(10)
    conn.close()
    return got


def _wire(payload: bytes) -> bytes:
    return struct.pack("!i", len(payload)) + payload


def test_many_frames_that_arrive_in_one_read_are_each_handed_on() -> None:
    payloads = [b"a", b"", b"bb" * 1000, b"c" * 70_000]

    assert payloads == _frames_of([b"".join(_wire(p) for p in payloads)])


def test_a_frame_that_arrives_a_byte_at_a_time_is_handed_on_whole() -> None:
    wire = _wire(b"hello") + _wire(b"world")

    assert [b"hello", b"world"] == _frames_of([wire[i : i + 1] for i in range(len(wire))])


def test_a_frame_larger_than_a_read_is_handed_on_whole() -> None:
    big = bytes(range(256)) * 4_000  # 1 MB: four reads' worth

    assert [big, b"after"] == _frames_of([_wire(big) + _wire(b"after")])


def test_the_long_header_of_multiprocessing_connection_is_understood() -> None:
    # Frames over 2 GiB carry -1 and then an 8-byte length; any size may use it.
    assert [b"long", b"short"] == _frames_of(
        [struct.pack("!iQ", -1, 4) + b"long" + _wire(b"short")]
    )


def test_a_connection_that_ends_inside_a_frame_hands_on_only_the_whole_ones() -> None:
    assert [b"whole"] == _frames_of([_wire(b"whole") + struct.pack("!i", 10) + b"cut"])


def test_frames_read_match_what_connection_recv_bytes_reads() -> None:
    sent = [frame(token, value) for token, value in enumerate([1, "two", {"three": [3]}])]

    got = _frames_of([b"".join(sent)])

    left, right = multiprocessing.Pipe()
    with left, right:
        for data in sent:
            left.send_bytes(data[4:])  # the payload; send_bytes adds the same header
        expected = [right.recv_bytes() for _ in sent]
    assert expected == got
