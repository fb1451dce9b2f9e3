"""A page's view of every host (`rr_actors_lab.observe._system`): a status sent on another host
is named once, as it enters the page's history, from what that host's provider published
before it, not at each render from the page's copy of its catalog (issue 51).

- `test_a_status_on_the_systems_stream_is_named_once_from_its_hosts_events_before_it`:
  a `SystemView` on a plain Zenoh session (another session's `Share` stands for host
  `bravo`); the system's event stream's callback is called as the stream calls it.
  `bravo`'s catalog of `erm` lags the send, forced: it lists the camera (loading), not yet
  its consumer, when the provider's events and its `StatusSent` arrive.
- `test_a_page_opened_after_a_status_draws_it_as_a_page_open_during_it_did`: the same in a
  real browser (chromium, Playwright), a real tree on a `ZenohNetwork` (its page is the
  system's); the observer's catalog of `erm` lags the send, forced as on one host
  (`test_page.py`): it was read while the camera loaded, and the next read waits until the
  live page drew the status. The late page opens on a fresher catalog.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

import rr_actors as rr
import rr_actors_lab.observe as _lab_observe
from rr_actors import events
from rr_actors.events import kinds
from rr_actors_lab.observe._hub import Hub
from rr_actors_lab.observe._share import Share
from rr_actors_lab.observe._system import SystemView
from tests.support import pki
from tests.support.gating import GatedLoad
from tests.support.observed_tree import device, figure_27
from tests.support.observing import get_json, open_a_page_late, services, wait_section
from tests.support.tls_lab import member_tls

BOUND = 10.0

pytestmark = pytest.mark.timeout(180)


def erm_catalog(consumers: list[str]) -> dict[str, Any]:
    """`erm`'s catalog section (as a `LiveSource` makes it): the camera, with `consumers`."""
    return {
        "registrar": "erm",
        "kind": "process manager",
        "state": "running",
        "available": True,
        "error": None,
        "catalog": {
            "registrar": "erm",
            "servers": ["camera"],
            "resources": [
                {
                    "id": "r1",
                    "server": "camera",
                    "state": "loaded" if consumers else "loading",
                    "in_doubt": False,
                    "request": "{'device': '/dev/video0'}",
                    "response": "",
                    "label": "'/dev/video0'",
                    "consumers": [{"query_id": q, "origin": "cm"} for q in consumers],
                }
            ],
            "clients": [],
            "in_doubt": [],
        },
    }


def test_a_status_on_the_systems_stream_is_named_once_from_its_hosts_events_before_it(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    mine, theirs = sessions
    local, page = Hub(), Hub()
    local.put("catalog/erm", erm_catalog([]))  # read while the camera loaded
    share = Share(
        local,
        services(theirs, "bravo"),
        "bravo",
        host={"title": "t", "pid": 1},
        faults=None,
        all_events=False,  # (the events come on the system's stream)
    )
    view = SystemView(page, services(mine, "alpha"), "alpha", None)
    stream = view._on_event  # (what the system's event stream calls, in its order)
    try:
        wait_section(page, "host/bravo/catalog/erm")
        stream(
            events.ResourceLoaded("erm", "camera", "r1", "q1", 0.01, None, "'cam'", host="bravo")
        )
        stream(events.ConsumerAdded("erm", "r1", "q1", "cm", host="bravo"))
        stream(events.StatusSent("erm", "q1", rr.Status.FATAL, "unplugged", host="bravo"))
        # The catalog that lists the consumers comes after: q2's ConsumerAdded was before
        # this page's host followed the stream; charlie's erm is another registrar.
        local.put("catalog/erm", erm_catalog(["q1", "q2"]))
        wait_section(
            page, "host/bravo/catalog/erm", lambda v: v["catalog"]["resources"][0]["consumers"]
        )
        stream(events.StatusSent("erm", "q2", rr.Status.FATAL, "unplugged", host="bravo"))
        stream(events.StatusSent("erm", "q1", rr.Status.FATAL, "unplugged", host="charlie"))
        # The FATAL unloads the camera: a page opened now has no row to name it by.
        stream(events.ConsumerReleased("erm", "r1", "q1", "cm", "unload", host="bravo"))
        stream(events.ResourceUnloaded("erm", "camera", "r1", host="bravo"))
        local.put("catalog/erm", {**erm_catalog([]), "catalog": None})
        wait_section(page, "host/bravo/catalog/erm", lambda v: v["catalog"] is None)
        late = page.changes({}, 0).events  # what a page opened now gets
    finally:
        view.close()
        share.close()

    sent = [(e["member"], e.get("resource")) for e in late if e["type"] == "StatusSent"]
    assert [
        ("bravo", "erm/camera '/dev/video0'"),  # (the catalog's label: what the graph draws)
        ("bravo", "erm/camera '/dev/video0'"),
        ("charlie", "erm (query q1)"),
    ] == sent


# -- in a real browser ------------------------------------------------------------------------


@pytest.fixture
def robot(
    process_helpers: Any, monkeypatch: Any, tmp_path: Path
) -> Iterator[tuple[rr.Supervisor, GatedLoad]]:
    """Figure 2.7's tree on a `ZenohNetwork` with TLS, as across machines (the events' host
    is the member name, `robot`, its page's catalogs are shared under: without TLS the
    host name and the member name differ), the camera's load held at a gate; stopped
    before its network closes."""
    monkeypatch.setattr(kinds._HOST, "name", kinds._HOST.name)  # (the network sets it)
    tls = member_tls(tmp_path, pki.make_ca(tmp_path / "ca", "lab"), "robot")
    loading = GatedLoad(process_helpers.event(), process_helpers.event(), device, wait=60)
    with rr.ZenohNetwork(system=f"named-{uuid.uuid4().hex[:8]}", tls=tls) as net:
        sup = figure_27(rr.Supervisor, camera=loading, network=net).start()
        try:
            yield sup, loading
        finally:
            loading.gate.set()
            sup.stop()


def test_a_page_opened_after_a_status_draws_it_as_a_page_open_during_it_did(
    robot: tuple[rr.Supervisor, GatedLoad], tabs: Any, monkeypatch: Any
) -> None:
    sup, loading = robot
    assert (
        "robot" == get_json(_lab_observe.observe(sup).url, "/api/state")["hello"]["member"]
    )  # (every host's)
    page = open_a_page_late(sup, loading, tabs, monkeypatch, within_ms=30_000)  # (held 0.5 s)

    assert 1 == page.late.locator("#timeline li[data-kind=status]").count()  # one row, not three
    assert (
        page.live.locator("#timeline").inner_text() == page.late.locator("#timeline").inner_text()
    )
    assert "erm/camera '/dev/video0'" == page.sent["resource"]  # (the graph's label)


# -- opened as its network leaves (`Services.on_leave`: a close at once) ---------------------


def _left(session: zenoh.Session, member: str) -> Any:
    """`services` of a network that left already: its carrier's `on_leave` runs `close()`
    at once, before it returns what forgets it (`ZenohCarrier.on_leave`)."""
    import dataclasses  # noqa: PLC0415

    def on_leave(close: Any) -> Any:
        close()
        return lambda: None

    return dataclasses.replace(services(session, member), on_leave=on_leave)


def test_a_share_opened_as_its_network_leaves_is_closed_not_an_attribute_error(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    """Review of the close ordering: `Share` and `SystemView` give their `close` to
    `on_leave` as the last step of `__init__`, and `close` ends by calling what
    `on_leave` returns; a network that left meanwhile closes them at once, inside that
    call, before `_forget` is set: `AttributeError` from the constructor."""
    mine, _theirs = sessions
    share = Share(Hub(), _left(mine, "bravo"), "bravo", host={"title": "t", "pid": 1}, faults=None)
    share.close()  # (closed already: nothing more)


def test_a_system_view_opened_as_its_network_leaves_is_closed_not_an_attribute_error(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    mine, _theirs = sessions
    view = SystemView(Hub(), _left(mine, "alpha"), "alpha", None)
    view.close(timeout=1.0)
