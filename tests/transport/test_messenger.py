"""What every carrier does with a message, written once (`rr_actors._transport.messenger`).

What cannot cross between processes, and what should never happen, each have a name
(the module's functions); `TestStoppingAListener`: a registrar served here is stopped
once, and a second stop waits for the first.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.connection
import multiprocessing.context
import multiprocessing.forkserver
import multiprocessing.synchronize
import os
import pickle
import socket
import struct
import threading
import uuid
from collections.abc import Iterator
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._registrar.life import Served
from rr_actors._registrar.messages import Fetch
from rr_actors._transport import System
from rr_actors._transport.unix.link import Listener
from rr_actors.errors import InternalError, TransferError
from rr_actors.testing import MemoryNetwork


@pytest.fixture
def system() -> Iterator[System]:
    created = System.create()
    yield created
    created.close()


@pytest.fixture
def served(system: System) -> Iterator[rr.ResourceRegistrar]:
    """A registrar of this process that the system serves."""
    registrar = rr.ResourceRegistrar.start(f"served-{uuid.uuid4().hex[:8]}")
    system.serve(Served(registrar))
    yield registrar
    registrar.stop()


def _ask_raw(system: System, name: str, token: int, payload: bytes) -> Any:
    """Send one frame to registrar `name` as an authenticated peer; its answer's error."""
    conn = multiprocessing.connection.Client(
        system.address.socket_path(name), family="AF_UNIX", authkey=system.address.authkey
    )
    try:
        conn.send_bytes(struct.pack("<Q", token) + payload)
        assert conn.poll(10), "no answer came"
        data = conn.recv_bytes()
    finally:
        conn.close()
    assert token == struct.unpack_from("<Q", data)[0]
    _value, error = pickle.loads(data[8:])
    return error


def _malformed_provider(listening: socket.socket, authkey: bytes) -> None:
    """Accept one connection; answer every message with an error that is no exception."""
    try:
        accepted, _ = listening.accept()
    except OSError:
        return
    accepted.settimeout(None)
    conn = multiprocessing.connection.Connection(accepted.detach())
    with contextlib.suppress(EOFError, OSError):
        multiprocessing.connection.deliver_challenge(conn, authkey)
        multiprocessing.connection.answer_challenge(conn, authkey)
        while True:
            (token,) = struct.unpack_from("<Q", conn.recv_bytes())
            if token:
                conn.send_bytes(struct.pack("<Q", token) + pickle.dumps((None, "not an error")))
    conn.close()


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


def test_a_message_that_cannot_be_unpickled_is_answered_with_a_transfer_error(
    system: System, served: rr.ResourceRegistrar
) -> None:
    error = _ask_raw(system, served.name, 3, b"\x80\x05not a pickle")

    assert (TransferError, True) == (type(error), "cannot be unpickled" in str(error))


def test_an_answer_to_a_message_that_wants_none_is_an_internal_error(
    system: System, served: rr.ResourceRegistrar
) -> None:
    error = _ask_raw(system, served.name, 9, pickle.dumps(42))

    assert (InternalError, True) == (type(error), "cannot be answered" in str(error))


def test_an_answer_that_cannot_be_unpickled_is_by_default_a_transfer_error() -> None:
    fetch = Fetch("leaf", "consumer", None)  # type: ignore[arg-type]

    unreadable = fetch.unreadable_answer("provider", ValueError("no such class"))
    unsendable = fetch.unsendable_answer("provider", object(), ValueError("no pickle"))

    assert (TransferError, TransferError) == (type(unreadable), type(unsendable))


def test_an_answer_in_no_form_a_carrier_sends_is_an_internal_error(system: System) -> None:
    consumer = rr.ResourceRegistrar.start(f"consumer-{uuid.uuid4().hex[:8]}")
    system.serve(Served(consumer))
    name = f"malformed-{uuid.uuid4().hex[:8]}"
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as listening:
            listening.bind(system.address.socket_path(name))
            listening.listen(1)
            listening.settimeout(10)
            threading.Thread(
                target=_malformed_provider, args=(listening, system.address.authkey), daemon=True
            ).start()
            with pytest.raises(InternalError, match="malformed answer"):
                consumer.call(name, "echo", "r", timeout=10)
    finally:
        consumer.stop()


class TestStoppingAListener:
    """The registrar's watcher and the system's `close()` may both stop its listener
    (`Messenger._unserve`, over the AF_UNIX carrier): the second returns once the first is done.
    """

    @pytest.fixture
    def system(self) -> Iterator[System]:  # type: ignore[no-redef]
        """A fresh AF_UNIX system (runtime directory + authkey), closed after the test."""
        created = System.create()
        yield created
        created.close()

    def test_a_second_close_of_a_listener_returns_only_once_the_first_finished(
        self, system: System, consumer: rr.ResourceRegistrar
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
        self,
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


def test_a_serve_the_process_leaves_during_stops_serving_and_says_so(
    system: System, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The system closes after its carrier served the name but before the messenger listed
    # it (a close then does not see it): the serve stops serving it and raises, as a serve
    # that began after the close does; nothing is left listening.
    from rr_actors._transport.unix.system import UnixCarrier  # noqa: PLC0415

    serve = UnixCarrier.serve

    def closed_meanwhile(carrier: UnixCarrier, endpoint: Any) -> Listener:
        listener = serve(carrier, endpoint)
        closing = threading.Thread(target=system.close, name="test-close")
        closing.start()
        closing.join(30)
        assert not closing.is_alive()
        return listener

    monkeypatch.setattr(UnixCarrier, "serve", closed_meanwhile)
    with (
        rr.ResourceRegistrar.start(f"left-{uuid.uuid4().hex[:8]}") as registrar,
        pytest.raises(rr.RegistrarStoppedError, match="left system"),
    ):
        system.serve(Served(registrar))

    assert [] == system.served()
    assert not os.path.exists(system.address.socket_path(registrar.name))


PROTOCOL = {"knows", "route", "send", "answer", "serve", "unserve", "names", "leave"}


def _called_on_the_carrier() -> set[str]:
    """Every member the messenger's code uses of a carrier: `carrier.x`, `self._carrier.x`,
    `self.link().x`, `peer.carrier.x`, and the members asked by name (`getattr`)."""
    import ast  # noqa: PLC0415
    import inspect  # noqa: PLC0415

    from rr_actors._transport import messenger  # noqa: PLC0415

    def is_carrier(node: ast.expr) -> bool:
        return (
            (isinstance(node, ast.Name) and node.id == "carrier")
            or (isinstance(node, ast.Attribute) and node.attr in ("carrier", "_carrier"))
            or (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Attribute)
                and node.func.attr == "link"
            )
        )

    used = set()
    for node in ast.walk(ast.parse(inspect.getsource(messenger))):
        if isinstance(node, ast.Attribute) and is_carrier(node.value):
            used.add(node.attr)
        asked = isinstance(node, ast.Call) and getattr(node.func, "id", "") == "getattr"
        if asked and is_carrier(node.args[0]) and isinstance(node.args[1], ast.Constant):
            used.add(node.args[1].value)
    return used


def test_a_carrier_is_one_protocol_of_eight_members_that_every_carrier_keeps() -> None:
    # Carriers only carry (issue 54): what a carrier gives the messenger is one protocol of
    # at most eight members (know a name, open a route to it, send, answer, serve a name
    # and stop serving it, who can be reached, leave). Every carrier implements them all;
    # the peer, a route's record and a served registrar's bookkeeping are the messenger's
    # own classes, which no carrier completes; the messenger asks a carrier nothing else
    # (rule 22's claim to the other server of a name is `send` over `route(name, server)`,
    # no optional member); the `Transport` the registrar sees is the messenger itself.
    import inspect  # noqa: PLC0415

    from rr_actors._transport import messenger  # noqa: PLC0415
    from rr_actors._transport.unix.system import UnixCarrier  # noqa: PLC0415
    from rr_actors._transport.zenoh.carrier import ZenohCarrier  # noqa: PLC0415
    from rr_actors.simulation._network import _SimulatedHub  # noqa: PLC0415
    from rr_actors.testing.memory import _Hub  # noqa: PLC0415

    members = {name for name in vars(messenger.Carrier) if not name.startswith("_")}
    assert PROTOCOL == members
    assert len(members) <= 8
    for carrier in (UnixCarrier, ZenohCarrier, _Hub, _SimulatedHub):
        assert set() == members - set(dir(carrier)), carrier
        assert "server" in inspect.signature(carrier.route).parameters, carrier  # (rule 22)
    assert PROTOCOL == _called_on_the_carrier()
    for own in (messenger.Remote, messenger.Route, messenger.Listening):
        assert not getattr(own, "__abstractmethods__", None), own
    for gone in ("Lanes", "Lane", "send_when_served"):
        assert not hasattr(messenger, gone)
    assert messenger.Transport is messenger.Messenger
    assert issubclass(System, messenger.Transport)
    assert issubclass(MemoryNetwork, messenger.Transport)
