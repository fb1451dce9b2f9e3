"""Zenoh presence: a restart seen before its predecessor's token went, and two servers of
one name after a healed link (rule 22).

Seen in a two-host demo run under load: cm was killed by its heartbeat with the
mission's `unload` in flight there; the station's presence applied the restarted cm's
token before the dead one's went, so the name never had no server, `server_gone` never
ran, and the mission's reply waited out its 15 s timeout instead of failing at once
(`RegistrarUnavailableError`). A later server of one name from the same supervisor
means the first died, and what waits on it fails now.

Two servers of one name from different supervisors are two live registrars (each side
of a healed cut served it): both are kept in the tables, the one served first (the
earlier clock stamp) is the one calls go to, the process that serves the other hears
`served_elsewhere`, and when the other goes its consumers are told `reachable`.

The presence tables are fed the liveliness events in those orders, over a real session.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import zenoh

from rr_actors._transport.resolve import Resolution
from rr_actors._transport.zenoh.presence import NO_WAITING, Presence, Server
from rr_actors._transport.zenoh.wire import HostKey, Keys, ServerKey

OLD, NEW, SUPERVISOR, OTHER = "a" * 32, "b" * 32, "c" * 32, "d" * 32


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

    def served_elsewhere(self, name: str, server: Server) -> None:
        self.said.append(("served_elsewhere", f"{name} {server.zid[:1]}"))


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


@pytest.fixture
def presence(session: zenoh.Session) -> Iterator[Presence]:
    heard = Heard()
    made = Presence("t", session, str(session.zid()), heard, hearer=heard)
    yield made
    made.close()


def token(
    presence: Presence,
    put: bool,
    zid: str,
    stamp: int,
    supervisor: str = SUPERVISOR,
    side: tuple[int, int] = (0, 0),
) -> None:
    """A registrar token of cm (`side`: its side and the system's members), applied as
    the presence thread applies one (on this thread, which must not stay marked as the
    presence thread: later tests here ask)."""
    key = Keys("t").server(ServerKey("cm", zid, supervisor, 1 << 20, stamp, *side))
    apply(presence, put, key)


def apply(presence: Presence, put: bool, key: str) -> None:
    try:
        presence._apply((put, key, None))
    finally:
        NO_WAITING.active = False


def said(presence: Presence) -> list[tuple[str, str]]:
    heard: Heard = presence._events  # type: ignore[assignment]
    return [(what, about) for what, about in heard.said if what != "served_elsewhere"]


def test_a_restart_seen_before_its_predecessor_went_fails_what_waits_on_that_one(
    presence: Presence,
) -> None:
    token(presence, True, OLD, 100)
    assert [] == said(presence)
    token(presence, True, NEW, 200)  # the restarted cm, before the killed one's token went
    assert [("server_gone", "cm")] == said(presence)  # what waits on the dead one fails
    assert NEW == presence.server("cm").zid  # type: ignore[union-attr]
    token(presence, False, OLD, 100)  # its end, late: nothing more (cm is served)
    assert [("server_gone", "cm")] == said(presence)
    assert presence.serves("cm")


def test_a_predecessors_token_heard_after_its_restart_is_stale_news(presence: Presence) -> None:
    token(presence, True, NEW, 200)
    token(presence, True, OLD, 100)  # (an answer of `ask` that still listed the dead one)

    assert NEW == presence.server("cm").zid  # type: ignore[union-attr]
    token(presence, False, NEW, 200)
    assert not presence.serves("cm")


def test_a_restart_in_the_same_process_replaces_its_predecessor_whatever_its_supervisor(
    presence: Presence,
) -> None:
    token(presence, True, OLD, 100, "none")
    token(presence, True, OLD, 200, "none")  # (served again there, its old token not gone yet)
    token(presence, False, OLD, 100, "none")

    assert 200 == presence.server("cm").stamp  # type: ignore[union-attr]


@pytest.mark.parametrize("first", [OLD, NEW])
def test_of_two_servers_of_other_supervisors_the_one_served_first_is_kept(
    presence: Presence, first: str
) -> None:
    later = NEW if first == OLD else OLD
    token(presence, True, later, 200, SUPERVISOR)  # one side of a healed cut
    token(presence, True, first, 100, OTHER)  # the other side's, served first

    assert first == presence.server("cm").zid  # type: ignore[union-attr]
    assert [] == said(presence)  # nobody died: nothing fails
    heard: Heard = presence._events  # type: ignore[assignment]
    assert [f"cm {later[:1]}", f"cm {first[:1]}"] == [
        about for what, about in heard.said if what == "served_elsewhere"
    ]
    token(presence, False, later, 200, SUPERVISOR)  # it yielded
    assert [("reachable", "cm")] == said(presence)  # its consumers reconcile with the other
    assert first == presence.server("cm").zid  # type: ignore[union-attr]


def test_of_two_servers_with_one_stamp_the_lower_zenoh_id_is_kept(presence: Presence) -> None:
    token(presence, True, NEW, 100, OTHER)
    token(presence, True, OLD, 100, SUPERVISOR)

    assert OLD == presence.server("cm").zid  # type: ignore[union-attr]


@pytest.mark.parametrize("order", ["lone first", "newcomer first"])
def test_with_resolve_majority_the_server_begun_on_a_majority_side_is_kept(
    session: zenoh.Session, order: str
) -> None:
    """Issue 51, finding 9, as the tokens say it: the lone host's erm began with every
    member heard (3 of 3); the newcomer began beyond the cut with 2 of 3, later. Either
    order of hearing them, "majority" keeps the newcomer, "first_served" the lone one."""
    kept = {}
    for resolve in ("first_served", "majority"):
        heard = Heard()
        presence = Presence(
            "t", session, str(session.zid()), heard, hearer=heard, resolution=Resolution(resolve)
        )
        try:
            tokens = [(OLD, 100, SUPERVISOR, (3, 3)), (NEW, 200, OTHER, (2, 3))]
            for zid, stamp, supervisor, side in tokens[:: 1 if order == "lone first" else -1]:
                token(presence, True, zid, stamp, supervisor, side)
            kept[resolve] = presence.server("cm").zid  # type: ignore[union-attr]
        finally:
            presence.close()

    assert {"first_served": OLD, "majority": NEW} == kept


def test_hosts_are_counted_from_their_routers_host_tokens(session: zenoh.Session) -> None:
    """A side is the hosts heard (one token per host's router); the system's size without
    TLS the most any router heard at once, unknown (0) in a process that has not heard
    its own router's token yet. A router hears when that most grows (`on_hosts`), and
    says it in its own token, so every router's converges on the system's."""
    heard, grown = Heard(), []
    presence = Presence(
        "t", session, str(session.zid()), heard, hearer=heard, on_hosts=grown.append
    )
    keys = Keys("t")
    try:
        apply(presence, True, keys.host(HostKey(OTHER, 3)))  # (a router that heard 3 once)
        assert (1, 0, 3) == (presence.hosts(), presence.most(SUPERVISOR), presence.most(None))
        apply(presence, True, keys.host(HostKey(SUPERVISOR, 1)))
        apply(presence, True, keys.host(HostKey(SUPERVISOR, 2)))  # (declared anew, then the
        apply(presence, False, keys.host(HostKey(SUPERVISOR, 1)))  # old one goes)
        assert (2, 3) == (presence.hosts(), presence.most(SUPERVISOR))
        apply(presence, False, keys.host(HostKey(OTHER, 3)))  # (a cut)
        assert (1, 3) == (presence.hosts(), presence.most(SUPERVISOR))
        assert [3] == grown  # (the router's own token then says 3: `_hosts_heard`)
    finally:
        presence.close()


@pytest.mark.parametrize("mine_first", [True, False])
def test_a_server_gone_while_this_process_serves_the_name_is_lost_only_if_it_was_kept(
    presence: Presence, mine_first: bool
) -> None:
    """Rule 22's yield: this process serves cm, and so does another (none supervises it);
    the other's token goes before this process's own is seen to go. If the other was
    kept (served first), this one is yielding: the other is lost (`Messenger.lost`, and
    the one here serves on); if this one was kept, the other yielded: nothing."""
    mine, theirs = (100, 200) if mine_first else (200, 100)
    token(presence, True, presence._zid, mine, "none")
    token(presence, True, OLD, theirs, "none")
    token(presence, False, OLD, theirs, "none")

    expected = [] if mine_first else [("server_gone", "cm"), ("lost", "cm")]
    assert expected == said(presence)
