"""What cannot cross between processes, and what should never happen, each have a name.

A message or an answer that does not (un)pickle is a `TransferError`; a peer that breaks
the carrier's own protocol (an answer to a message that wants none, an answer in no
form a carrier sends) is an `InternalError`. Both are `RrError`s.
"""

from __future__ import annotations

import contextlib
import multiprocessing.connection
import pickle
import socket
import struct
import threading
import uuid
from collections.abc import Iterator
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._transport import System
from rr_actors.errors import InternalError, TransferError
from rr_actors.testing.carrier import Fetch, Served


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
