"""A closed connection ends for its peer at once, whoever closes its socket first.

A connection of the AF_UNIX carrier is read on a duplicate descriptor (`sockets.split`), so
closing the writer's socket alone does not end it: only a shutdown wakes the reader and
tells the peer. `Writer.close()` shuts the socket down after it woke the writer thread,
and that thread closes the socket as it ends; when the thread came first, the shutdown
found a closed socket and the connection stayed open. Seen as a call right after a
registrar's `stop()` that timed out (issue 30 item 5): the listener had closed the
caller's connection this way, so the caller saw no end, and the `Load` it sent next was
read and dropped unanswered.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator

import pytest
from waiting import wait_for

from rr_actors._transport import writer as writer_module
from rr_actors._transport.sockets import split
from rr_actors._transport.writer import Writer

BOUND = 5.0  # seconds the peer may take to read the end (a loaded machine)


@pytest.fixture
def pair() -> Iterator[tuple[socket.socket, socket.socket]]:
    """A connected AF_UNIX stream pair: ours (given to the writer) and the peer's."""
    ours, peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    yield ours, peer
    ours.close()
    peer.close()


def test_a_writer_closed_while_its_thread_closes_the_socket_first_ends_the_connection(
    pair: tuple[socket.socket, socket.socket], monkeypatch: pytest.MonkeyPatch
) -> None:
    ours, peer = pair
    sock, reading = split(ours)  # as a connection of the carrier: a reader's duplicate
    writer = Writer(sock, lambda _exc: None)
    real = writer_module.shutdown

    def after_the_writer_thread_closed(target: socket.socket) -> None:
        # the interleaving that lost the end: close() shuts down only once the writer
        # thread, woken by it, has closed the socket (its own shutdown goes through)
        if threading.current_thread().name != "rr-answer-test":
            assert wait_for(lambda: target.fileno() == -1, BOUND)
        real(target)

    monkeypatch.setattr(writer_module, "shutdown", after_the_writer_thread_closed)
    writer.start("rr-answer-test")
    ended = threading.Event()

    def read() -> None:  # what a connection's reader thread does
        try:
            reading.recv_bytes()
        except (EOFError, OSError):
            ended.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()

    writer.close()

    peer.settimeout(BOUND)
    assert b"" == peer.recv(1)  # the peer reads the end (not a timeout)
    assert ended.wait(BOUND)  # and the reader on the duplicate wakes
    reader.join(BOUND)
    reading.close()
