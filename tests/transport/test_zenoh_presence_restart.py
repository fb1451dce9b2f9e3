"""Zenoh presence: a restart seen before its predecessor's token went.

Seen in a two-host demo run under load: cm was killed by its heartbeat with the
mission's `unload` in flight there; the station's presence applied the restarted cm's
token before the dead one's went, so the name never had no server, `server_gone` never
ran, and the mission's reply waited out its 15 s timeout instead of failing at once
(`RegistrarUnavailableError`). One name has one server: a second one means the first
died, and what waits on it fails now.

The presence tables are fed the liveliness events in that order, over a real session.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import zenoh

from rr_actors._transport.zenoh.presence import Presence
from rr_actors._transport.zenoh.wire import Keys, ServerKey

OLD, NEW, SUPERVISOR = "a" * 32, "b" * 32, "c" * 32


class Heard:
    """What the presence reports, in order (`PresenceEvents`)."""

    def __init__(self) -> None:
        self.said: list[tuple[str, str]] = []

    def process_gone(self, zid: str) -> None:
        self.said.append(("process_gone", zid))

    def server_gone(self, name: str) -> None:
        self.said.append(("server_gone", name))

    def lost(self, name: str) -> None:
        self.said.append(("lost", name))

    def reachable(self, name: str) -> None:
        self.said.append(("reachable", name))


@pytest.fixture
def session() -> Iterator[zenoh.Session]:
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", "[]")
    opened = zenoh.open(config)
    try:
        yield opened
    finally:
        opened.close()  # type: ignore[no-untyped-call]


def test_a_restart_seen_before_its_predecessor_went_fails_what_waits_on_that_one(
    session: zenoh.Session,
) -> None:
    keys, heard = Keys("t"), Heard()
    presence = Presence("t", session, str(session.zid()), heard)
    try:

        def token(put: bool, zid: str) -> None:  # (as the presence thread applies one)
            presence._apply((put, keys.server(ServerKey("cm", zid, SUPERVISOR, 1 << 20)), None))

        token(True, OLD)
        assert [] == heard.said
        token(True, NEW)  # the restarted cm, before the killed one's token went
        assert [("server_gone", "cm")] == heard.said  # what waits on the dead one fails
        assert NEW == presence.server("cm").zid  # type: ignore[union-attr]
        token(False, OLD)  # its end, late: nothing more (cm is served)
        assert [("server_gone", "cm")] == heard.said
        assert presence.serves("cm")
    finally:
        presence.close()
