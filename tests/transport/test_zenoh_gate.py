"""The gate on a router's `tls/` listener (issue 29): who it drops, when it lets them in again,
and the Linux socket tricks under it (a listening socket of this process, on loopback).

The flood itself, from a third host, with a member re-joining during and after it, is
`tests/multihost/test_zenoh_tls.py::test_a_member_rejoins_in_10_s_while_a_third_host_
floods_the_port_with_failed_handshakes`.
"""

from __future__ import annotations

import collections
import logging
import socket
from collections.abc import Collection, Iterator

import pytest

from rr_actors._platform import PLATFORM
from rr_actors._transport.zenoh.gate import HOLD, QUIET, HandshakeGate
from tests.support.supervising import linux_trick


class FakeGate:
    """A `ListenerGate` whose peers and drop counter the test sets."""

    address, port = "10.0.0.1", 7447

    def __init__(self) -> None:
        self.held: collections.Counter[str] = collections.Counter()
        self.drops = 0
        self.sources: set[str] = set()
        self.backlog: int | None = None
        self.closed = False

    def shorten_backlog(self, backlog: int) -> None:
        self.backlog = backlog

    def drop_from(self, sources: Collection[str]) -> None:
        self.sources = set(sources)

    def dropped(self) -> int:
        return self.drops

    def peers(self) -> collections.Counter[str]:
        return collections.Counter(self.held)

    def close(self) -> None:
        self.closed = True


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def said(caplog: pytest.LogCaptureFixture) -> pytest.LogCaptureFixture:
    caplog.set_level(logging.INFO, logger="rr_actors")
    return caplog


def made(members_at: set[str] | None = None) -> tuple[FakeGate, HandshakeGate, Clock]:
    gate, clock = FakeGate(), Clock()
    guard = HandshakeGate("lab", [gate], lambda: members_at or set(), clock=clock, start=False)
    return gate, guard, clock


def test_a_source_holding_more_than_hold_connections_is_dropped_and_named_once(
    said: pytest.LogCaptureFixture,
) -> None:
    gate, guard, _ = made()
    gate.held.update({"10.0.0.9": HOLD, "10.0.0.3": HOLD + 1})
    guard.look()
    guard.look()

    assert {"10.0.0.3"} == gate.sources == guard.dropping()
    warnings = [r.getMessage() for r in said.records if r.levelno == logging.WARNING]
    assert 1 == len(warnings)
    assert "'lab': 10.0.0.3 holds 9 connections to 10.0.0.1:7447" in (warnings[0])


def test_a_source_with_a_members_link_up_is_never_dropped() -> None:
    gate, guard, _ = made(members_at={"10.0.0.2"})
    gate.held.update({"10.0.0.2": HOLD + 20})
    guard.look()

    assert set() == gate.sources


def test_the_drops_are_lifted_once_nothing_was_dropped_for_quiet_seconds(
    said: pytest.LogCaptureFixture,
) -> None:
    gate, guard, clock = made()
    gate.held.update({"10.0.0.3": HOLD + 1})
    guard.look()
    gate.held.clear()
    for _ in range(3):  # the source keeps trying: its packets are dropped, the count grows
        clock.now += QUIET
        gate.drops += 1
        guard.look()
    assert {"10.0.0.3"} == gate.sources
    clock.now += QUIET - 1
    guard.look()
    assert {"10.0.0.3"} == gate.sources
    clock.now += 1
    guard.look()

    assert set() == gate.sources == guard.dropping()
    assert "'lab': 10.0.0.1:7447 takes packets from 10.0.0.3 again" in said.text


def test_close_lets_go_of_the_gates() -> None:
    gate, guard, _ = made()
    guard.close()
    guard.close()

    assert gate.closed


# -- the Linux gate, on a listening socket of this process --------------------------------------


@pytest.fixture(params=["127.0.0.1", "0.0.0.0"])  # noqa: S104 (a wildcard listener too)
def listening(request: pytest.FixtureRequest) -> Iterator[socket.socket]:
    with socket.socket() as server:
        server.bind((request.param, 0))
        server.listen(64)
        yield server


@linux_trick
def test_the_gate_drops_only_the_sources_given_and_links_up_keep_working(
    listening: socket.socket,
) -> None:
    address, port = listening.getsockname()
    gate = PLATFORM.listener_gate(address, port)
    assert gate is not None
    try:
        gate.shorten_backlog(4)
        with socket.create_connection(("127.0.0.1", port), timeout=5) as up:
            accepted, _ = listening.accept()
            with accepted:
                assert {"127.0.0.1": 1} == gate.peers()  # (the accepted end)
                gate.drop_from(["127.0.0.1"])
                with pytest.raises(TimeoutError):
                    socket.create_connection(("127.0.0.1", port), timeout=1.5)
                assert gate.dropped() > 0
                up.sendall(b"still up")  # a connection accepted before is not touched
                assert b"still up" == accepted.recv(16)
                gate.drop_from(["10.0.0.3", "::1"])
                socket.create_connection(("127.0.0.1", port), timeout=5).close()
                gate.drop_from([])
                socket.create_connection(("127.0.0.1", port), timeout=5).close()
    finally:
        gate.close()
    assert 0 == listening.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)  # still listening


@linux_trick
def test_there_is_no_gate_on_a_socket_this_process_does_not_listen_on() -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
        assert PLATFORM.listener_gate("127.0.0.1", port) is None  # bound, not listening
