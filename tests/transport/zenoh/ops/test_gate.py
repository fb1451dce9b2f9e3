"""The gate on a router's `tls/` listener (`rr_actors._transport.zenoh.ops.gate`);
`TestMemberAddresses`: the addresses it never drops.
"""

from __future__ import annotations

import collections
import logging
import socket
from collections.abc import Collection, Iterator
from pathlib import Path

import pytest

from rr_actors._platform import PLATFORM
from rr_actors._platform.linux_gate import handshaken
from rr_actors._transport.zenoh.ops.gate import (
    ASK_AGAIN,
    DROP,
    HOLD,
    HandshakeGate,
    MemberAddresses,
)
from rr_actors._transport.zenoh.wire import Keys
from tests.support import pki
from tests.support.hosts import free_port
from tests.support.supervising import FakeClock, linux_trick
from tests.support.tls_lab import member_tls, router
from tests.support.waiting import wait_for


class FakeGate:
    """A `ListenerGate` whose peers the test sets; it records the filter it was given."""

    address, port = "10.0.0.1", 7447

    def __init__(self) -> None:
        self.held: collections.Counter[str] = collections.Counter()
        self.sources: set[str] = set()  # dropped (`drop_from`)
        self.only: set[str] | None = None  # the only ones admitted (`admit_only`), or None
        self.drops = 0  # packets its filter dropped (grows while a dropped source sends)
        self.backlog: int | None = None
        self.closed = False

    def shorten_backlog(self, backlog: int) -> None:
        self.backlog = backlog

    def drop_from(self, sources: Collection[str]) -> None:
        self.sources, self.only = set(sources), None

    def admit_only(self, sources: Collection[str]) -> None:
        self.sources, self.only = set(), set(sources)

    def peers(self) -> collections.Counter[str]:
        return collections.Counter(self.held)

    def dropped(self) -> int:  # (not the gate's business now: main's waited for it to stop)
        return self.drops

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


def made(members: set[str] | None = None) -> tuple[FakeGate, HandshakeGate, Clock]:
    gate, clock = FakeGate(), Clock()
    known = members if members is not None else set()
    guard = HandshakeGate("lab", [gate], lambda: set(known), clock=clock, start=False)
    return gate, guard, clock


def warnings(said: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in said.records if r.levelno == logging.WARNING]


# -- the Linux gate, on a listening socket of this process --------------------------------------


@pytest.fixture(params=["127.0.0.1", "0.0.0.0"])  # noqa: S104 (a wildcard listener too)
def listening(request: pytest.FixtureRequest) -> Iterator[socket.socket]:
    with socket.socket() as server:
        server.bind((request.param, 0))
        server.listen(64)
        yield server


def proc(address: str) -> str:
    """An IPv4 address as `/proc/net/tcp` writes it (a host-order word in hex)."""
    return socket.inet_aton(address)[::-1].hex().upper()


BOUND = 10.0  # seconds a link and a get may take on a loaded machine


def answering(session: object, pem: bytes) -> object:
    """A queryable of `session` that answers a get of operator's certificate with `pem`."""
    return session.declare_queryable(  # type: ignore[attr-defined]
        Keys("lab").certificate("operator"), lambda query: query.reply(query.key_expr, pem)
    )


def test_a_stranger_holding_more_than_hold_connections_is_dropped_and_named_once(
    said: pytest.LogCaptureFixture,
) -> None:
    gate, guard, _ = made()
    gate.held.update({"10.0.0.9": HOLD - 1, "10.0.0.3": HOLD + 1})
    guard.look()
    guard.look()

    assert {"10.0.0.3"} == gate.sources == guard.dropping()
    assert 1 == len(warnings(said))
    assert (
        "'lab': 10.0.0.3 holds 9 connections to 10.0.0.1:7447 and is not a member's address"
        in warnings(said)[0]
    )
    assert "its packets to that port are dropped for 60 s" in warnings(said)[0]


@pytest.mark.parametrize("held", [HOLD + 20, 1])
def test_a_members_address_is_never_dropped_nor_counted_with_strangers(held: int) -> None:
    # (named in a member's certificate, or of a member's link: `members.MemberAddresses`)
    gate, guard, _ = made(members={"10.0.0.2"})
    gate.held.update({"10.0.0.2": held, "10.0.0.7": HOLD})
    guard.look()

    assert (set(), None) == (gate.sources, gate.only)
    assert not guard.members_only()


def test_a_drop_ends_after_drop_seconds_whatever_the_source_keeps_sending(
    said: pytest.LogCaptureFixture,
) -> None:
    # main's gate waited for 60 s without a dropped packet: the member's own re-dials (or
    # anyone forging its address) kept that from coming
    gate, guard, clock = made()
    gate.held.update({"10.0.0.3": HOLD + 1})
    guard.look()
    for _ in range(int(DROP) - 1):  # its queued connections linger, it keeps sending
        clock.now += 1
        gate.drops += 1
        guard.look()
    assert {"10.0.0.3"} == gate.sources
    gate.held.clear()
    clock.now += 1
    gate.drops += 1
    guard.look()

    assert set() == gate.sources == guard.dropping()
    assert "'lab': 10.0.0.1:7447 takes packets from 10.0.0.3 again (dropped for 60 s)" in (
        said.text
    )


def test_a_source_that_floods_again_after_its_drop_is_dropped_again(
    said: pytest.LogCaptureFixture,
) -> None:
    gate, guard, clock = made()
    gate.held.update({"10.0.0.3": HOLD + 1})
    guard.look()
    gate.held.clear()  # (the listener paid what it had queued)
    clock.now += DROP
    guard.look()
    assert set() == gate.sources
    gate.held.update({"10.0.0.3": HOLD + 1})
    guard.look()

    assert {"10.0.0.3"} == gate.sources
    assert 2 == len(warnings(said))


def test_strangers_together_over_hold_make_the_port_take_members_addresses_only(
    said: pytest.LogCaptureFixture,
) -> None:
    gate, guard, clock = made(members={"10.0.0.2", "10.0.0.5"})
    gate.held.update({f"10.0.1.{n}": 1 for n in range(32)})  # one machine's 32 addresses
    gate.held.update({"10.0.0.2": 1})
    guard.look()
    assert not guard.members_only()  # (at two looks in a row)
    guard.look()
    guard.look()

    assert ({"10.0.0.2", "10.0.0.5"}, set()) == (gate.only, gate.sources)
    assert guard.members_only()
    assert 1 == len(warnings(said))
    assert (
        "'lab': 32 addresses, none a member's, hold 32 connections to 10.0.0.1:7447 (failed "
        "or unfinished TLS handshakes): the port takes packets only from members' addresses "
        "(10.0.0.2, 10.0.0.5) for 60 s"
    ) in warnings(said)[0]
    clock.now += DROP - 1
    guard.look()
    assert guard.members_only()
    clock.now += 1
    gate.held.clear()
    guard.look()

    assert (None, set()) == (gate.only, gate.sources)
    assert not guard.members_only()
    assert "10.0.0.1:7447 takes packets from every address again (dropped for 60 s)" in said.text


def test_strangers_that_together_hold_at_most_hold_are_let_be() -> None:
    gate, guard, _ = made()
    gate.held.update({f"10.0.1.{n}": 2 for n in range(HOLD // 2)})
    guard.look()
    guard.look()

    assert (set(), None) == (gate.sources, gate.only)


def test_strangers_over_hold_together_at_one_look_only_are_let_be() -> None:
    # members dialling a router just started are strangers to it until linked: their
    # handshakes, however many at once, are over by the next look
    gate, guard, _ = made()
    for _ in range(3):
        gate.held.update({f"10.0.1.{n}": 1 for n in range(HOLD + 1)})
        guard.look()
        gate.held.clear()
        guard.look()

    assert (set(), None) == (gate.sources, gate.only)


def test_a_dropped_source_counts_no_more_with_the_other_strangers() -> None:
    # (its queued connections linger until Zenoh has paid them)
    gate, guard, _ = made()
    gate.held.update({"10.0.0.3": HOLD + 1, "10.0.0.4": 1})
    guard.look()
    guard.look()

    assert ({"10.0.0.3"}, None) == (gate.sources, gate.only)


def test_a_members_address_learned_while_members_only_is_let_in() -> None:
    members = {"10.0.0.2"}
    gate, clock = FakeGate(), Clock()
    guard = HandshakeGate("lab", [gate], lambda: set(members), clock=clock, start=False)
    gate.held.update({f"10.0.1.{n}": 1 for n in range(HOLD + 1)})
    guard.look()
    guard.look()
    members.add("10.99.0.7")  # (a member's certificate came in)
    guard.look()

    assert {"10.0.0.2", "10.99.0.7"} == gate.only


def test_close_lets_go_of_the_gates() -> None:
    gate, guard, _ = made()
    guard.close()
    guard.close()

    assert gate.closed


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
def test_the_gate_can_admit_only_the_sources_given(listening: socket.socket) -> None:
    address, port = listening.getsockname()
    gate = PLATFORM.listener_gate(address, port)
    assert gate is not None
    try:
        gate.admit_only(["10.0.0.3", "::1"])
        with pytest.raises(TimeoutError):
            socket.create_connection(("127.0.0.1", port), timeout=1.5)
        gate.admit_only(["10.0.0.3", "127.0.0.1"])
        socket.create_connection(("127.0.0.1", port), timeout=5).close()
        gate.drop_from([])
        socket.create_connection(("127.0.0.1", port), timeout=5).close()
    finally:
        gate.close()


def test_only_connections_past_the_tcp_handshake_count() -> None:
    # a half-open one (SYN_RECV, 03) may carry a forged source address: never counted
    states = {"01": 1, "03": 5, "04": 1, "05": 1, "06": 3, "08": 1, "09": 1, "0A": 1, "0B": 1}
    rows = [
        ("10.0.0.1", 7447, proc("10.0.0.2"), state, 0)
        for state, n in states.items()
        for _ in range(n)
    ]
    rows += [
        ("10.0.0.1", 7448, proc("10.0.0.4"), "01", 0),  # another port
        ("10.0.0.9", 7447, proc("10.0.0.5"), "01", 0),  # another address of the host
    ]

    assert {"10.0.0.2": 6} == handshaken(rows, "10.0.0.1", 7447)
    assert {"10.0.0.2": 6, "10.0.0.5": 1} == handshaken(rows, "0.0.0.0", 7447)  # noqa: S104


@linux_trick
def test_there_is_no_gate_on_a_socket_this_process_does_not_listen_on() -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
        assert PLATFORM.listener_gate("127.0.0.1", port) is None  # bound, not listening


class TestMemberAddresses:
    """`MemberAddresses`: which addresses are members', the ones the handshake gate never drops
    (issue 40). Two TLS routers on loopback with the config `ZenohNetwork` makes
    (`tests/support/tls_lab.py`): `robot` listens, `operator` dials it; their certificates
    come from `tests/support/pki.py`.
    """

    @pytest.fixture
    def lab(self, tmp_path: Path) -> tuple[Path, Path]:
        return pki.make_ca(tmp_path / "lab", "lab")

    @pytest.fixture
    def said(self, caplog: pytest.LogCaptureFixture) -> pytest.LogCaptureFixture:
        caplog.set_level(logging.INFO, logger="rr_actors")
        return caplog

    @pytest.fixture
    def endpoint(self) -> str:
        return f"tls/127.0.0.1:{free_port()}"

    def test_the_addresses_a_members_certificate_names_are_known_and_stay_known(
        self, tmp_path: Path, lab: tuple[Path, Path], endpoint: str
    ) -> None:
        robot = member_tls(tmp_path, lab, "robot")
        operator = member_tls(
            tmp_path, lab, "operator", ("127.0.0.1", "10.99.0.7", "fd00::7", "operator.local")
        )
        with router(robot, [endpoint], []) as a:
            here = MemberAddresses("lab", a, robot)
            try:
                assert set() == here.now()
                with router(operator, [], [endpoint]) as b:
                    there = MemberAddresses("lab", b, operator)  # (it answers for its certificate)
                    try:
                        named = {"127.0.0.1", "10.99.0.7", "fd00::7"}  # (IP addresses only)
                        assert wait_for(lambda: named == here.now(), BOUND), here.now()
                    finally:
                        there.close()
                assert wait_for(lambda: not a.info.links(), BOUND)
                assert named == here.now()  # (out of reach, or gone: still the member's)
            finally:
                here.close()

    def test_a_members_link_address_is_known_without_its_certificate(
        self, tmp_path: Path, lab: tuple[Path, Path], endpoint: str
    ) -> None:
        # operator answers for no certificate (a member of an older rr_actors, say)
        robot = member_tls(tmp_path, lab, "robot")
        operator = member_tls(tmp_path, lab, "operator", ("10.99.0.7",))
        with router(robot, [endpoint], []) as a, router(operator, [], [endpoint]):
            here = MemberAddresses("lab", a, robot)
            try:
                assert wait_for(lambda: {"127.0.0.1"} == here.now(), BOUND)
            finally:
                here.close()

    @pytest.mark.parametrize("answer", ["robot's certificate", "a self-signed one", "no PEM"])
    def test_a_certificate_that_is_not_the_members_own_is_refused_once_and_not_used(
        self,
        tmp_path: Path,
        lab: tuple[Path, Path],
        endpoint: str,
        said: pytest.LogCaptureFixture,
        answer: str,
    ) -> None:
        robot = member_tls(tmp_path, lab, "robot", ("127.0.0.1", "10.99.0.8"))
        operator = member_tls(tmp_path, lab, "operator")
        pem = {
            "robot's certificate": Path(robot.cert).read_bytes(),
            "a self-signed one": pki.issue(tmp_path / "self", "operator", ("10.99.0.8",))[
                0
            ].read_bytes(),
            "no PEM": b"10.99.0.8",
        }[answer]
        reason = {
            "robot's certificate": "of member 'operator' has the common name 'robot'",
            "a self-signed one": "is not signed by ca",
            "no PEM": "is not PEM certificates",
        }[answer]
        clock = FakeClock()
        with router(robot, [endpoint], []) as a, router(operator, [], [endpoint]) as b:
            queryable = answering(b, pem)
            # The first ask must reach the queryable: under load its declaration can reach `a`
            # after the link does, and a missed ask is asked again only after ASK_AGAIN on the
            # fake clock (a full-suite run under load failed so).
            key = Keys("lab").certificate("operator")
            assert wait_for(lambda: any(r.ok for r in a.get(key, timeout=1.0)), BOUND)
            here = MemberAddresses("lab", a, robot, clock=clock)
            try:

                def refused() -> list[str]:
                    here.now()
                    return [r.getMessage() for r in said.records if r.levelno == logging.WARNING]

                assert wait_for(lambda: bool(refused()), BOUND)
                clock.now += ASK_AGAIN  # asked again: refused again, said no more
                assert not wait_for(lambda: len(refused()) > 1, 1.0)
            finally:
                here.close()
                queryable.undeclare()  # type: ignore[attr-defined]
        assert 1 == len(refused())
        assert (
            "ZenohNetwork 'lab': member 'operator' answered for its certificate with one that does "
            "not hold: the certificate of member 'operator' "
        ) in refused()[0]
        assert reason in refused()[0]
        assert {"127.0.0.1"} == here.now()

    def test_close_stops_answering_for_this_hosts_certificate(
        self, tmp_path: Path, lab: tuple[Path, Path], endpoint: str
    ) -> None:
        robot = member_tls(tmp_path, lab, "robot")
        with router(robot, [endpoint], []) as a:
            here = MemberAddresses("lab", a, robot)
            key = Keys("lab").certificate("robot")
            assert [Path(robot.cert).read_bytes()] == [
                reply.ok.payload.to_bytes() for reply in a.get(key, timeout=BOUND) if reply.ok
            ]
            here.close()
            here.close()
            assert [] == [reply for reply in a.get(key, timeout=1.0) if reply.ok]
