"""A closed connection ends for its peer at once, whichever shutdown of its socket works.

A connection of the AF_UNIX carrier is read on a duplicate descriptor (`sockets.split`), so
closing the writer's socket alone does not end it: only a shutdown wakes the reader and
tells the peer. `Writer.close()` shuts the socket down, and the writer's thread shuts it
down again before it closes it after the last write: when the first shutdown found the
socket closed already (it did, before the writer's thread was a `SerialExecutor`: that
thread could close it first), the connection stayed open. Seen as a call right after a
registrar's `stop()` that timed out (issue 30 item 5): the listener had closed the
caller's connection this way, so the caller saw no end, and the `Load` it sent next was
read and dropped unanswered.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator

import pytest

import rr_actors._transport.unix.link as writer_module
from rr_actors._transport.unix.link import Writer, split

BOUND = 5.0  # seconds the peer may take to read the end (a loaded machine)


@pytest.fixture
def pair() -> Iterator[tuple[socket.socket, socket.socket]]:
    """A connected AF_UNIX stream pair: ours (given to the writer) and the peer's."""
    ours, peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    yield ours, peer
    ours.close()
    peer.close()


def test_a_closed_writer_ends_the_connection_even_when_the_shutdown_at_close_failed(
    pair: tuple[socket.socket, socket.socket], monkeypatch: pytest.MonkeyPatch
) -> None:
    ours, peer = pair
    sock, reading = split(ours)  # as a connection of the carrier: a reader's duplicate
    writer = Writer(sock, lambda _exc: None, "rr-answer-test")
    real = writer_module.shutdown
    calls: list[int] = []

    def first_one_fails(target: socket.socket) -> None:
        # the interleaving that lost the end: the shutdown at close() found the socket
        # closed (EBADF, ignored); only a shutdown before the last close can end it
        calls.append(1)
        if len(calls) > 1:
            real(target)

    monkeypatch.setattr(writer_module, "shutdown", first_one_fails)
    assert writer.send(b"\x00\x00\x00\x01x")  # a frame, so a connection in use
    ended = threading.Event()

    def read() -> None:  # what a connection's reader thread does
        try:
            while True:
                reading.recv_bytes()
        except (EOFError, OSError):
            ended.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()

    writer.close()

    peer.settimeout(BOUND)
    assert peer.recv(16)  # the frame
    assert b"" == peer.recv(1)  # then the end (not a timeout)
    assert ended.wait(BOUND)  # and the reader on the duplicate wakes
    reader.join(BOUND)
    reading.close()
