"""`MemberAddresses`: which addresses are members', the ones the handshake gate never drops
(issue 40). Two TLS routers on loopback with the config `ZenohNetwork` makes
(`tests/support/tls_lab.py`): `robot` listens, `operator` dials it; their certificates
come from `tests/support/pki.py`.
"""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from rr_actors._transport.zenoh.ops.gate import ASK_AGAIN, MemberAddresses
from rr_actors._transport.zenoh.wire import Keys
from tests.support import pki
from tests.support.supervising import FakeClock
from tests.support.tls_lab import free_port, member_tls, router
from tests.support.waiting import wait_for

BOUND = 10.0  # seconds a link and a get may take on a loaded machine


@pytest.fixture
def lab(tmp_path: Path) -> tuple[Path, Path]:
    return pki.make_ca(tmp_path / "lab", "lab")


@pytest.fixture
def said(caplog: pytest.LogCaptureFixture) -> pytest.LogCaptureFixture:
    caplog.set_level(logging.INFO, logger="rr_actors")
    return caplog


@pytest.fixture
def endpoint() -> str:
    return f"tls/127.0.0.1:{free_port()}"


def test_the_addresses_a_members_certificate_names_are_known_and_stay_known(
    tmp_path: Path, lab: tuple[Path, Path], endpoint: str
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
    tmp_path: Path, lab: tuple[Path, Path], endpoint: str
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


def answering(session: object, pem: bytes) -> object:
    """A queryable of `session` that answers a get of operator's certificate with `pem`."""
    return session.declare_queryable(  # type: ignore[attr-defined]
        Keys("lab").certificate("operator"), lambda query: query.reply(query.key_expr, pem)
    )


@pytest.mark.parametrize("answer", ["robot's certificate", "a self-signed one", "no PEM"])
def test_a_certificate_that_is_not_the_members_own_is_refused_once_and_not_used(
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
    tmp_path: Path, lab: tuple[Path, Path], endpoint: str
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
