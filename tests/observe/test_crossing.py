"""What crosses hosts for the observer (`rr_actors_lab.observe._crossing`): keys, JSON, and what is
refused.

Two plain Zenoh sessions of this process stand for two hosts on loopback (no rr_actors
system, so no access control: these tests are about what a page's host accepts from a
member, not who gets in, which `tests/multihost/test_observe_hosts.py` covers with TLS):

- the observer's keys are built and parsed in `Keys` only, and a malformed one is `None`;
- a `Share` publishes its hub's sections as JSON a `SystemView` on the other session
  turns into the page's `host/<member>/...` sections (a patch, not the whole catalog,
  when one resource changes);
- what a host sends that is not what a `LiveSource` makes (garbage, a section of an
  unknown name, a tree of the wrong shape) never reaches the page, and a delta out of
  sequence makes the page's host ask for the whole state again;
- a fault command to a host that did not allow faults is refused by that host, with why.
"""

from __future__ import annotations

import json
import logging
import time
import uuid
from typing import Any

import pytest
import zenoh

import rr_actors as rr
import rr_actors_lab.observe as _lab_observe
from rr_actors import events
from rr_actors._transport.zenoh.wire import ObserverKey
from rr_actors_lab.observe._crossing import (
    decode,
    valid_catalog,
    valid_event,
    valid_section,
    valid_tree,
)
from rr_actors_lab.observe._faults import FaultRefused
from rr_actors_lab.observe._hub import Hub
from rr_actors_lab.observe._share import Share
from rr_actors_lab.observe._system import SystemView
from tests.support.observing import KEYS, request, services, wait_section
from tests.support.supervising import echo_setup
from tests.support.waiting import wait_for

BOUND = 10.0
BLOCK = zenoh.CongestionControl.BLOCK
"""The test's puts wait for room instead of being dropped: with Zenoh's default (`DROP`),
the 110-byte put right after the 100 kB garbage never reached a subscriber 1 run in 7 (a
raw subscriber saw the 100 kB put and not it), and the test waited for its effect."""


def catalog(registrar: str, requests: list[str]) -> dict[str, Any]:
    resources = [
        {
            "id": f"r{i}",
            "server": "camera",
            "state": "loaded",
            "in_doubt": False,
            "request": request,
            "response": "ok",
            "label": None,
            "consumers": [{"query_id": f"q{i}", "origin": "app"}],
        }
        for i, request in enumerate(requests)
    ]
    return {
        "registrar": registrar,
        "kind": "process manager",
        "state": "running",
        "available": True,
        "error": None,
        "catalog": {
            "registrar": registrar,
            "servers": ["camera"],
            "resources": resources,
            "clients": [],
            "in_doubt": [],
        },
    }


TREE = {
    "name": "robot",
    "kind": "supervisor",
    "state": "running",
    "children": [{"name": "cam", "kind": "manager", "state": "running", "pid": 7, "children": []}],
}


def test_observer_keys_are_built_and_parsed_in_one_place() -> None:
    for part in ("state", "delta", "fault", "here"):
        key = KEYS.observer(ObserverKey("bravo", part))
        assert f"rr/lab/obs/bravo/{part}" == key
        assert ObserverKey("bravo", part) == KEYS.parse_observer(key)
    assert "rr/lab/obs/*/delta" == KEYS.observers("delta")
    for bad in ("rr/lab/obs/bravo/pickle", "rr/lab/obs/../state", "rr/x/obs/bravo/state", ""):
        assert KEYS.parse_observer(bad) is None
    assert KEYS.parse_observer("rr/lab/obs/a/b/state") is None
    assert KEYS.observer(ObserverKey("bravo", "state")).startswith(KEYS.everything()[:-2])


def test_a_share_reaches_another_hosts_page_as_json_sections_and_patches(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    mine, theirs = sessions
    local, page = Hub(), Hub()
    local.put("tree", TREE)
    local.put("catalog/cam", catalog("cam", ["a"]))
    share = Share(
        local, services(theirs, "bravo"), "bravo", host={"title": "t", "pid": 1}, faults=None
    )
    view = SystemView(page, services(mine, "alpha"), "alpha", None)
    try:
        wait_section(page, "host/bravo/tree")
        assert "cam" == wait_section(page, "host/bravo/catalog/cam")["registrar"]
        sent = share.sent_bytes
        local.put("catalog/cam", catalog("cam", ["a", "b"]))
        wait_section(page, "host/bravo/catalog/cam", lambda v: len(v["catalog"]["resources"]) == 2)
        assert share.sent_bytes - sent < 1000  # a patch of one resource, not the catalog
        hosts_shown = wait_section(page, "hosts", lambda v: v and v["hosts"][0]["state"] == "live")
        assert [("bravo", False)] == [
            (h["member"], h["allow_faults"]) for h in hosts_shown["hosts"]
        ]
    finally:
        view.close()
        share.close()


def test_what_a_host_sends_that_a_live_source_does_not_make_never_reaches_the_page(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    mine, theirs = sessions
    page = Hub()
    asked = []
    state = {
        "v": 1,
        "member": "evil",
        "instance": "i1",
        "seq": 5,
        "sections": {
            "tree": {"name": "x", "kind": "supervisor", "state": "running", "children": "no"},
            "catalog/cam": catalog("cam", ["a"]),
            "catalog/../../x": catalog("cam", ["a"]),
            "script": "<img src=x onerror=alert(1)>",
            "host": {"member": "evil", "title": "t", "pid": 1, "allow_faults": False},
        },
        "events": [{"type": "Nope", "at": 1.0, "text": "hi", "seq": 1}, {"type": 3}],
    }

    def answer(query: zenoh.Query) -> None:
        asked.append(1)
        query.reply(query.key_expr, json.dumps(state).encode())

    queryable = theirs.declare_queryable(KEYS.observer(ObserverKey("evil", "state")), answer)
    view = SystemView(page, services(mine, "alpha"), "alpha", None)
    token = theirs.liveliness().declare_token(KEYS.observer(ObserverKey("evil", "here")))
    delta = KEYS.observer(ObserverKey("evil", "delta"))
    try:
        wait_section(page, "host/evil/catalog/cam")
        assert page.get("host/evil/tree") is None
        assert ["host/evil/catalog/cam"] == page.keys("host/")
        assert 1 == len(page.changes({}, 0).events)  # the well-formed one
        for garbage in (b"\x80\x04pickle", b"[]", b'{"v": 1}', b"{" * 100_000):
            theirs.put(delta, garbage, congestion_control=BLOCK)
        before = len(asked)
        bad = {"v": 1, "member": "evil", "instance": "i1", "seq": 6, "events": []}
        bad["sections"] = [["tree", "v", {"name": 1}]]
        # in sequence, but not a tree: asked again
        theirs.put(delta, json.dumps(bad).encode(), congestion_control=BLOCK)
        assert wait_for(lambda: len(asked) > before, BOUND)
        skipped = {**bad, "seq": 9, "sections": [["catalog/cam", "v", None]]}
        # out of sequence: not applied
        theirs.put(delta, json.dumps(skipped).encode(), congestion_control=BLOCK)
        assert wait_for(lambda: len(asked) > before + 1, BOUND)
        assert page.get("host/evil/catalog/cam") is not None
        assert page.get("host/evil/tree") is None
    finally:
        token.undeclare()  # type: ignore[no-untyped-call]
        view.close()
        queryable.undeclare()  # type: ignore[no-untyped-call]


def test_a_fault_command_to_a_host_that_did_not_allow_faults_is_refused_there(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    mine, theirs = sessions
    local, page = Hub(), Hub()
    local.put("tree", TREE)
    share = Share(
        local, services(theirs, "bravo"), "bravo", host={"title": "t", "pid": 1}, faults=None
    )
    view = SystemView(page, services(mine, "alpha"), "alpha", None)
    try:
        wait_section(page, "host/bravo/tree")
        with pytest.raises(FaultRefused) as refused:
            view.fault("bravo", "kill", {"child": "cam", "pid": 7, "host": "bravo"})
        assert 403 == refused.value.status
        assert "bravo does not allow faults" in str(refused.value)
        with pytest.raises(FaultRefused, match="no host 'nobody'"):
            view.fault("nobody", "kill", {"child": "cam", "pid": 7})
    finally:
        view.close()
        share.close()


def test_the_shapes_a_page_accepts_are_those_a_live_source_makes() -> None:
    assert valid_tree(TREE)
    assert valid_catalog(catalog("cam", ["a"]))
    assert not valid_tree({**TREE, "children": [{"name": "x"}]})
    assert not valid_tree({**TREE, "pid": "7"})
    broken = catalog("cam", ["a"])
    broken["catalog"]["resources"][0]["consumers"] = [{"query_id": 1}]
    assert not valid_catalog(broken)
    assert not valid_catalog({**catalog("cam", []), "registrar": None})


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_a_number_that_is_not_finite_is_refused_anywhere_in_an_event_or_a_section(
    bad: float,
) -> None:
    """Issue 40: `NaN` passed `_number` (it is a float), and a page's `JSON.parse` refuses
    the whole message that holds one."""
    event = {"type": "InDoubt", "at": 1.0, "text": "t", "seq": 1}
    assert valid_event(event)
    assert not valid_event({**event, "at": bad})
    assert not valid_event({**event, "load_s": bad})
    assert not valid_event({**event, "deep": [{"x": [bad]}]})
    assert not valid_section("tree", {**TREE, "pid": bad})
    assert not valid_section("ended", {"at": bad})
    sick = catalog("cam", ["a"])
    sick["catalog"]["resources"][0]["extra"] = {"load_s": bad}
    assert not valid_section("catalog/cam", sick)
    assert valid_section("catalog/cam", catalog("cam", ["a"]))


def test_a_hosts_event_with_a_nan_is_dropped_and_its_other_events_reach_the_page(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    """One bad event never costs the others: a buggy member's state carries three events
    (`json.dumps` writes the `NaN`), the page gets the two good ones and its sections."""
    mine, theirs = sessions
    page = Hub()
    good = {"type": "InDoubt", "at": 1.0, "text": "good one", "seq": 1}
    state = {
        "v": 1,
        "member": "buggy",
        "instance": "i1",
        "seq": 5,
        "sections": {"tree": TREE, "ended": {"at": float("inf")}},
        "events": [
            good,
            {"type": "InDoubt", "at": float("nan"), "text": "bad", "seq": 2},
            {"type": "InDoubt", "at": 2.0, "text": "good two", "seq": 3, "load_s": 0.5},
        ],
    }

    def answer(query: zenoh.Query) -> None:
        query.reply(query.key_expr, json.dumps(state).encode())

    queryable = theirs.declare_queryable(KEYS.observer(ObserverKey("buggy", "state")), answer)
    view = SystemView(page, services(mine, "alpha"), "alpha", None)
    token = theirs.liveliness().declare_token(KEYS.observer(ObserverKey("buggy", "here")))
    try:
        wait_section(page, "host/buggy/tree")
        shown = page.changes({}, 0).events
    finally:
        token.undeclare()  # type: ignore[no-untyped-call]
        view.close()
        queryable.undeclare()  # type: ignore[no-untyped-call]

    assert ["good one", "good two"] == [e["text"] for e in shown]
    assert page.get("host/buggy/ended") is None  # (its `at` is infinite)


class TestHostileJson:
    """JSON from another host nested past Python's parser, or with a number that is not
    finite, is refused like any garbage.

    `json.loads` raises `RecursionError`, not a `ValueError`, for `[[[[...` a few hundred
    kilobytes deep (far under the 32 MiB a host may send): the page's host logged a
    traceback for every such message instead of dropping it unread, and a fault request of
    the page 2 KiB deep was a 500 instead of a 400.
    """

    @pytest.mark.parametrize(
        "data", [b"[" * 200_000, b'{"a":' * 200_000], ids=["arrays", "objects"]
    )
    def test_a_message_nested_too_deeply_is_dropped_without_a_traceback(
        self, data: bytes, caplog: pytest.LogCaptureFixture
    ) -> None:
        with caplog.at_level(logging.DEBUG, logger="rr_actors"):
            assert decode("robot", data) is None

        assert [] == [r for r in caplog.records if r.levelno >= logging.WARNING]

    def test_a_fault_request_nested_too_deeply_is_a_400_and_nothing_is_done(self) -> None:
        pytest.importorskip("uvicorn")
        name = f"erm-{uuid.uuid4().hex[:8]}"
        with rr.Supervisor([rr.ManagerSpec(name, echo_setup)]) as sup:
            observer = _lab_observe.observe(sup, allow_faults=True)
            headers = {"Content-Type": "application/json"}
            body = b"[" * 2000 + b"]" * 2000  # (under the 4 KiB a request may have)

            status, _, answer = request(
                observer.url, "/api/faults/kill", method="POST", body=body, headers=headers
            )

            assert (400, "the body is not JSON") == (status, json.loads(answer)["message"])
            assert "running" == sup.child(name).state

    def test_a_members_event_with_a_nan_never_costs_a_page_the_other_events(
        self, page: Any
    ) -> None:
        """Issue 40: one `NaN` in a member's event (`json` writes it, a browser's `JSON.parse`
        refuses it) made every page drop the whole message of events it came in, other
        hosts' events included. A buggy member (a raw Zenoh session attached to this host's
        router) puts one batch of three events on the system's event stream, the middle one
        with `at` NaN; the page, in a real browser, shows the other two and logs no error
        (the `page` fixture fails the test on any)."""
        import zenoh  # noqa: PLC0415 - the zenoh extra (a dev dependency: missing, it fails)

        net = rr.ZenohNetwork(system=f"nan-{uuid.uuid4().hex[:8]}", tls=None)
        good = [
            events.InDoubt("erm", f"good-{i}", at=time.time(), pid=1, host="buggy", hlc=i << 12)
            for i in (1, 2)
        ]
        bad = {**events.to_dict(events.InDoubt("erm", "bad", host="buggy")), "at": float("nan")}
        lines = [
            json.dumps(events.to_dict(good[0])),
            json.dumps(bad),
            json.dumps(events.to_dict(good[1])),
        ]
        with net, rr.Supervisor([rr.ManagerSpec("erm", echo_setup)], network=net) as sup:
            observer = _lab_observe.observe(sup)
            page.goto(observer.url)
            page.wait_for_selector('.node[data-child="erm"][data-state="running"]')
            raw = zenoh.open(
                zenoh.Config.from_json5(
                    '{"mode": "client", "scouting": {"multicast": {"enabled": false}}, '
                    f'"connect": {{"endpoints": ["unixsock-stream/{net.address.socket_path}"]}}}}'
                )
            )
            try:
                publisher = raw.declare_publisher(f"rr/{net.system}/ev/{raw.zid()}")
                assert wait_for(lambda: publisher.matching_status.matching, 10.0)
                publisher.put("\n".join(lines).encode())
                for event in good:
                    page.wait_for_selector(
                        f'#log li[data-member="buggy"]:has-text("{event.query_id}")'
                    )
            finally:
                raw.close()
            shown = page.locator('#log li[data-member="buggy"]').all_inner_texts()

        assert 2 == len(shown)
        assert not any("bad" in line for line in shown)
