"""The link watch's WARNING about an unlinked `connect` endpoint comes at most once a minute
per endpoint (review of issue 23), also when its link comes back and goes again: a link
that flaps does not log a WARNING at every drop."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from pathlib import Path

import pki
import pytest
from tls_lab import free_port, member_tls, router
from waiting import wait_for

from rr_actors._transport.zenoh.watch import GRACE, TICK, LinkWatch


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
    robot, operator = member_tls(tmp_path, ca, "robot"), member_tls(tmp_path, ca, "operator")
    port = free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    unlinked = f"no link to connect endpoint {endpoint}"
    with router(operator, [], [endpoint]) as session:
        watch = LinkWatch("lab", session, operator, (endpoint,))
        try:
            for _ in range(2):  # the link comes, and goes
                with router(robot, [endpoint], []):
                    assert wait_for(lambda: len(session.info.links()) == 1, timeout=15)
                    threading.Event().wait(2 * TICK)  # the watch sees it linked
                assert wait_for(lambda: not session.info.links(), timeout=15)
                if not warnings.about(unlinked):
                    assert wait_for(lambda: bool(warnings.about(unlinked)), timeout=15)
            threading.Event().wait(GRACE + 4 * TICK)  # past when a second drop would warn
        finally:
            watch.close()
    assert 1 == len(warnings.about(unlinked)), warnings.lines
