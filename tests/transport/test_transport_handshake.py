"""A peer that knows the authkey but sends a malformed challenge is refused in one log
line, not a thread's traceback (issue 21), and the listener serves on."""

from __future__ import annotations

import logging
import multiprocessing.connection
import os
import socket
import struct
import uuid
from collections.abc import Iterator

import pytest

import rr_actors as rr
from rr_actors._transport import System
from rr_actors._transport.unix.link import connect
from rr_actors.testing.carrier import Served


@pytest.fixture
def system() -> Iterator[System]:
    created = System.create()
    yield created
    created.close()


@pytest.fixture
def served(system: System) -> Iterator[rr.ResourceRegistrar]:
    registrar = rr.ResourceRegistrar.start(f"served-{uuid.uuid4().hex[:8]}")
    registrar.register_server("echo", load=lambda r: r, unload=lambda _r, _s: None)
    system.serve(Served(registrar))
    yield registrar
    registrar.stop()


@pytest.mark.parametrize(
    "challenge",
    [b"hello, not a challenge", b"", b"#CHALLENGE#"[:5]],
    ids=["garbage", "empty", "cut-short"],
)
def test_a_malformed_challenge_is_refused_in_one_log_line(
    system: System,
    served: rr.ResourceRegistrar,
    challenge: bytes,
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, logger="rr_actors")
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as peer:
        peer.connect(system.address.socket_path(served.name))
        with multiprocessing.connection.Connection(os.dup(peer.fileno())) as conn:
            multiprocessing.connection.answer_challenge(conn, system.address.authkey)  # honest
        peer.sendall(struct.pack("!i", len(challenge)) + challenge)  # then a bad challenge
        peer.settimeout(10)
        assert b"" == peer.recv(4096)  # the listener closes the connection

    refused = [r for r in caplog.records if "refused a connection" in r.getMessage()]
    assert [(logging.WARNING, None)] == [(r.levelno, r.exc_info) for r in refused]
    assert "malformed handshake" in refused[0].getMessage()
    # and it serves on: an honest peer still gets in
    sock, conn = connect(system.address.socket_path(served.name), system.address.authkey)
    conn.close()
    sock.close()
