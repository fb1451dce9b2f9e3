"""The link watch's WARNING about an unlinked `connect` endpoint comes at most once a minute
per endpoint (review of issue 23), also when its link comes back and goes again: a link
that flaps does not log a WARNING at every drop."""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pki
import pytest
import zenoh
from waiting import wait_for

import rr_actors as rr
from rr_actors._transport.zenoh_config import session_config
from rr_actors._transport.zenoh_watch import GRACE, TICK, LinkWatch

MEMBERS = ["robot", "operator"]


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def _tls(directory: Path, ca: tuple[Path, Path], name: str) -> Any:
    cert, key = pki.issue(directory / name, name, ("127.0.0.1",), ca=ca)
    return rr.ZenohTLS(ca=ca[0], cert=cert, key=key, members=MEMBERS)


@contextlib.contextmanager
def _session(tls: Any, listen: list[str], connect: list[str]) -> Iterator[zenoh.Session]:
    session = zenoh.open(session_config("router", listen, connect, 1.0, system="lab", tls=tls))
    try:
        yield session
    finally:
        session.close()  # type: ignore[no-untyped-call]


class _Warnings(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []
        self.guard = threading.Lock()

    def emit(self, record: logging.LogRecord) -> None:
        with self.guard:
            self.lines.append(record.getMessage())

    def about(self, text: str) -> list[str]:
        with self.guard:
            return [line for line in self.lines if text in line]


@pytest.fixture
def warnings() -> Iterator[_Warnings]:
    handler = _Warnings()
    log = logging.getLogger("rr_actors")
    log.addHandler(handler)
    yield handler
    log.removeHandler(handler)


def test_a_connect_endpoint_whose_link_flaps_is_warned_of_once_a_minute(
    tmp_path: Path, warnings: _Warnings
) -> None:
    ca = pki.make_ca(tmp_path / "lab", "lab")
    robot, operator = _tls(tmp_path, ca, "robot"), _tls(tmp_path, ca, "operator")
    port = _free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    unlinked = f"no link to connect endpoint {endpoint}"
    with _session(operator, [], [endpoint]) as session:
        watch = LinkWatch("lab", session, operator, (endpoint,))
        try:
            for _ in range(2):  # the link comes, and goes
                with _session(robot, [endpoint], []):
                    assert wait_for(lambda: len(session.info.links()) == 1, timeout=15)
                    threading.Event().wait(2 * TICK)  # the watch sees it linked
                assert wait_for(lambda: not session.info.links(), timeout=15)
                if not warnings.about(unlinked):
                    assert wait_for(lambda: bool(warnings.about(unlinked)), timeout=15)
            threading.Event().wait(GRACE + 4 * TICK)  # past when a second drop would warn
        finally:
            watch.close()
    assert 1 == len(warnings.about(unlinked)), warnings.lines
