"""Helpers of the observer tests: the figure 2.7 tree, a real HTTP client, an SSE reader.

The observer is tested against its real server: uvicorn on a loopback port, spoken to over
TCP (`http.client`), never through Starlette's `TestClient`, which buffers an endless
event stream.
"""

from __future__ import annotations

import contextlib
import dataclasses
import http.client
import json
import os
import shutil
import signal
import tempfile
import threading
import time
import urllib.parse
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._catalog import ClientRecord, Resource, ResourceState
from rr_actors._transport.zenoh.net import Services
from rr_actors._transport.zenoh.wire import Keys
from rr_actors_lab.observe import observe
from rr_actors_lab.observe._delta import apply
from rr_actors_lab.observe._view import short, summarise_catalog
from tests.support.observed_tree import REQUEST

CHROMIUM = os.environ.get("RR_CHROMIUM", "/usr/bin/chromium")
"""The browser the browser tests drive (Debian's chromium; `.ci/run` installs it)."""

CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
    "--disable-sync",
]


# -- HTTP ---------------------------------------------------------------------------------------


def base(url: str) -> str:
    """The observer's URL without its `?token=...`."""
    return url.split("?", 1)[0]


def token(url: str) -> str:
    """The token in an observer's URL (`?token=...`)."""
    return urllib.parse.parse_qs(urllib.parse.urlsplit(url).query)["token"][0]


def request(
    url: str,
    path: str,
    *,
    method: str = "GET",
    body: bytes | None = None,
    headers: dict[str, str] | None = None,
    timeout: float = 10.0,
    with_token: bool = True,
) -> tuple[int, dict[str, str], bytes]:
    """One request to the observer at `url` (with its token, as the page's cookie does, unless
    `with_token` is false); `(status, headers, body)`."""
    parts = urllib.parse.urlsplit(url)
    conn = http.client.HTTPConnection(parts.hostname, parts.port, timeout=timeout)
    headers = dict(headers or {})
    if with_token and "token=" in url:
        headers.setdefault("X-RR-Token", token(url))
    try:
        conn.request(method, path, body=body, headers=headers)
        response = conn.getresponse()
        return response.status, {k.lower(): v for k, v in response.getheaders()}, response.read()
    finally:
        conn.close()


def get_json(url: str, path: str) -> Any:
    status, _, body = request(url, path)
    assert 200 == status, body
    return json.loads(body)


def post_fault(url: str, kind: str, data: Any, *, with_token: bool = True) -> tuple[int, Any]:
    """POST a fault request as the page does; `(status, answer)`."""
    headers = {"Content-Type": "application/json"}
    status, _, body = request(
        url,
        f"/api/faults/{kind}",
        method="POST",
        body=json.dumps(data).encode(),
        headers=headers,
        with_token=with_token,
    )
    return status, json.loads(body)


def wait_state(url: str, predicate: Callable[[Any], bool], timeout: float = 10.0) -> Any:
    """Poll `/api/state` until `predicate(state)` (each poll is a real request)."""
    deadline = time.monotonic() + timeout
    pause = threading.Event()
    state = get_json(url, "/api/state")
    while not predicate(state):
        if time.monotonic() > deadline:
            pytest.fail(f"the observer's state did not get there within {timeout:g} s: {state}")
        pause.wait(0.02)
        state = get_json(url, "/api/state")
    return state


def child(tree: dict[str, Any], name: str) -> dict[str, Any]:
    """The child `name` anywhere in a tree section."""
    for entry in tree["children"]:
        if entry["name"] == name:
            return entry
        if entry["kind"] == "supervisor":
            with contextlib.suppress(KeyError):
                return child(entry, name)
    raise KeyError(name)


class Stream:
    """The observer's event stream, read over a real connection (`http.client`).

    Args:
        url: the observer's URL.
        timeout: seconds one read may wait.
    """

    def __init__(self, url: str, timeout: float = 10.0) -> None:
        parts = urllib.parse.urlsplit(url)
        self.conn = http.client.HTTPConnection(parts.hostname, parts.port, timeout=timeout)
        self.conn.request(
            "GET",
            "/api/stream",
            headers={"Accept": "text/event-stream", "X-RR-Token": token(url)},
        )
        self.response = self.conn.getresponse()
        if self.response.status != 200:
            self.response.read()
            self.conn.close()
        assert 200 == self.response.status
        self.sections: dict[str, Any] = {}
        self.versions: dict[str, int] = {}
        self.events: list[dict[str, Any]] = []
        self.patches = 0
        self.largest_patch = 0

    def next(self) -> tuple[str, Any]:
        """The next message: `(event name, parsed data)` (keep-alive comments skipped).

        Raises:
            EOFError: the server ended the stream.
        """
        name, data = "message", []
        while True:
            raw = self.response.readline()
            if not raw:
                raise EOFError("the stream ended")
            line = raw.decode().rstrip("\r\n")
            if not line:
                if data:
                    value = json.loads("\n".join(data))
                    if name == "section":
                        self.sections[value["key"]] = value["value"]
                        self.versions[value["key"]] = value["version"]
                    elif name == "patch":  # (as the page does: app.js applyPatch)
                        key = value["key"]
                        self.sections[key] = apply(self.sections.get(key), value["patch"])
                        self.versions[key] = value["version"]
                        self.patches += 1
                        self.largest_patch = max(self.largest_patch, len(data[0]))
                    elif name == "events":
                        self.events.extend(value["events"])
                    return name, value
                continue
            if line.startswith(":"):
                continue
            field, _, value = line.partition(":")
            value = value.removeprefix(" ")
            if field == "event":
                name = value
            elif field == "data":
                data.append(value)

    def until(self, predicate: Callable[[Stream], bool], timeout: float) -> float:
        """Read until `predicate(self)`; the seconds it took (fails the test past `timeout`)."""
        start = time.monotonic()
        while not predicate(self):
            if time.monotonic() - start > timeout:
                pytest.fail(f"the stream did not get there within {timeout:g} s")
            self.next()
        return time.monotonic() - start

    def close(self) -> None:
        self.conn.close()


@contextlib.contextmanager
def stream(url: str, timeout: float = 10.0) -> Iterator[Stream]:
    """An open `Stream`, closed at the end of the block."""
    opened = Stream(url, timeout)
    try:
        yield opened
    finally:
        opened.close()


# -- processes ----------------------------------------------------------------------------------


def process_state(pid: int) -> str | None:
    """The state letter of process `pid` (`"T"`: stopped), or `None` if it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[0]


def kill(pid: int) -> None:
    os.kill(pid, signal.SIGKILL)


def chromium() -> str | None:
    """The browser to drive, if there is one."""
    if os.path.isfile(CHROMIUM) and os.access(CHROMIUM, os.X_OK):
        return CHROMIUM
    return shutil.which("chromium")


@contextlib.contextmanager
def headless_chromium(width: int = 1400, height: int = 1000) -> Iterator[Any]:
    """A headless chromium with a fresh profile (its Playwright browser context), its window
    `width` x `height` pixels; fails the test where there is no chromium (or Playwright)."""
    import playwright.sync_api as playwright_api  # noqa: PLC0415 - the dev extra

    path = chromium()
    if path is None:
        pytest.fail("no chromium to drive (apt-get install -y chromium; .ci/run does)")
    with playwright_api.sync_playwright() as playwright, tempfile.TemporaryDirectory() as profile:
        context = playwright.chromium.launch_persistent_context(
            profile,
            executable_path=path,
            headless=True,
            args=CHROMIUM_ARGS,
            viewport={"width": width, "height": height},
        )
        yield context
        context.close()


@dataclasses.dataclass
class HeldMission:
    """The fast demo mission running on a thread, with an observer (`url`); it is `held`
    before one fault until the `mission_held_before` block ends. `result`: its report."""

    url: str
    held: threading.Event
    result: list[Any]
    thread: threading.Thread


@contextlib.contextmanager
def mission_held_before(fault: str, out: Path) -> Iterator[HeldMission]:
    """Run the `--fast` mission under an observer; it stops before `fault` (e.g. "F4")
    until the block ends, then finishes (joined, with a bound)."""
    from rr_actors_lab.mission.config import MissionConfig  # noqa: PLC0415 - the mission is big
    from rr_actors_lab.mission.run import run_mission  # noqa: PLC0415

    urls: list[str] = []
    opened, held, go_on = threading.Event(), threading.Event(), threading.Event()

    def observed(sup: Any) -> None:
        urls.append(observe(sup).url)
        opened.set()

    def before_fault(name: str, _pids: list[str]) -> None:  # on the mission's thread
        if name == fault:
            held.set()
            go_on.wait(60)

    result: list[Any] = []
    thread = threading.Thread(
        target=lambda: result.append(
            run_mission(
                MissionConfig.fast(), out, on_supervisor=observed, before_fault=before_fault
            )
        ),
        daemon=True,
    )
    thread.start()
    try:
        assert opened.wait(30)
        yield HeldMission(urls[0], held, result, thread)
    finally:
        go_on.set()
        thread.join(120)


def loaded(state: dict[str, Any]) -> bool:
    """Whether the observer shows figure 2.7 loaded: erm's 2 resources, cm's, action's query."""
    sections = state["sections"]

    def count(name: str, rows: str) -> int:
        section = sections.get(f"catalog/{name}")
        return len(section["catalog"][rows]) if section and section["catalog"] else 0

    graph = sections.get("graph") or {"edges": []}
    return (count("erm", "resources"), count("cm", "resources"), count("action", "clients")) == (
        2,
        1,
        1,
    ) and len(graph["edges"]) == 3


# -- a page opened after a status -----------------------------------------------------------------

FATAL_AT_HOP_2 = '#timeline li[data-status="FATAL"] [data-hop="2"]'
"""The timeline's row of figure 2.7's FATAL status, as it reached its second hop."""


@dataclasses.dataclass
class LatePage:
    """What `open_a_page_late` left: the tab open all along (`live`), the one opened 2.5 s
    after the status (`late`), the status's `StatusSent` event (as `/api/state` gives it)."""

    live: Any
    late: Any
    sent: dict[str, Any]


def open_a_page_late(
    sup: Any, loading: Any, tabs: Callable[[], Any], monkeypatch: Any, *, within_ms: int
) -> LatePage:
    """Send figure 2.7's camera a FATAL status while a page is open, then open a second page
    2.5 s later; the observer's catalog of erm lags the send, forced (as under load): it is
    read while the camera loads (its row, not yet its consumer), and the next read waits
    until the live page drew the status. `loading`: the camera's `GatedLoad`; `within_ms`:
    how long each page may take to draw the status. The call is unloaded before it returns.
    """
    observer = observe(sup)
    source = observer._source
    read_catalogs = source._refresh  # (the test reads them with it itself)
    parked, reads = threading.Event(), threading.Event()

    def held(dirty: set[str] | None) -> None:  # the refresher's next round waits here
        parked.set()
        assert reads.wait(60)
        read_catalogs(dirty)

    monkeypatch.setattr(source, "_refresh", held)
    app = sup.registrar("action")
    camera = '#catalogs [data-registrar="erm"] [data-server="camera"] .resource'
    answers: list[Any] = []
    calling = threading.Thread(
        target=lambda: answers.append(
            app.call("cm", "filtered_camera", REQUEST, on_status=lambda q, u: None)
        )
    )
    try:
        assert parked.wait(30)  # (no round under way: the catalogs are read where told)
        live = tabs()
        live.goto(observer.url)
        calling.start()
        assert loading.started.wait(30)
        for _ in range(5):  # erm's camera is loading: its row has no consumer yet
            read_catalogs(None)
            if source.hub.get("catalog/erm")["available"]:
                break  # (else the read timed out under load: read again)
        live.wait_for_selector(camera)
        loading.gate.set()
        calling.join(30)
        (query,) = answers

        sup.run_in(
            "erm",
            lambda reg: reg.send_status(
                reg.server_queries("camera")[0].id, rr.Status.FATAL, "camera unplugged"
            ),
        )
        sup.flush_events()
        live.locator(FATAL_AT_HOP_2).wait_for(timeout=within_ms)
    finally:
        loading.gate.set()
        reads.set()  # the refresher reads the catalogs again: the consumer is in erm's now
    live.wait_for_selector(f"{camera} li:has-text('consumer')")
    sent = next(
        e for e in get_json(observer.url, "/api/state")["events"] if e["type"] == "StatusSent"
    )
    live.wait_for_function(f"() => Date.now() / 1000 > {sent['at'] + 2.5}")  # late: 2.5 s after
    late = tabs()
    late.goto(observer.url)  # gets the whole history at once
    late.locator(FATAL_AT_HOP_2).wait_for(timeout=within_ms)
    app.unload(query.id)
    return LatePage(live, late, sent)


# -- the page's view of every host, on plain Zenoh sessions --------------------------------------

KEYS = Keys("lab")
"""The key space of the cross-host observer tests' system, "lab"."""


def services(session: Any, member: str) -> Services:
    """What a member `member` of "lab" gives the observer's cross-host parts, on `session`."""
    return Services(session=session, keys=KEYS, member=member, lease=1.0, links=list)


def wait_section(hub: Any, key: str, predicate: Any = lambda v: v is not None) -> Any:
    """The page hub's section `key` once `predicate(value)` holds (within 10 s)."""
    changed = threading.Event()
    unlisten = hub.listen(changed.set)
    try:
        while not predicate(hub.get(key)):
            assert changed.wait(10.0), f"{key}: {hub.get(key)!r}"
            changed.clear()
        return hub.get(key)
    finally:
        unlisten()


# -- figure 2.7's catalogs, as the observer summarises them --------------------------------------


def resource(rid: str, server: str, request: Any, consumers: dict[str, str]) -> Resource:
    """A loaded resource `rid` of `server` with `consumers` (query id -> registrar)."""
    made = Resource(rid, server, request, {"r": request}, ResourceState.LOADED, consumers)
    made.request_text = short(request)  # (a registrar makes it when it stores the request)
    return made


def client(qid: str, serving: str, server: str, parent: str | None) -> ClientRecord:
    """A loaded client record `qid` of `serving`'s `server`, for resource `parent`."""
    return ClientRecord(rr.Query(qid, server, serving, "x", "req", None), parent, loaded=True)


def figure_27() -> dict[str, Any]:
    """Figure 2.7's catalogs: action -> cm's filtered camera -> erm's camera and filter."""
    return {
        "erm": summarise_catalog(
            "erm",
            [
                resource("cam", "camera", 0, {"q2": "cm"}),
                resource("flt", "filter", "blur", {"q3": "cm"}),
            ],
            [],
        ),
        "cm": summarise_catalog(
            "cm",
            [resource("fc", "filtered_camera", {"d": 0}, {"q1": "action"})],
            [client("q2", "erm", "camera", "fc"), client("q3", "erm", "filter", "fc")],
        ),
        "action": summarise_catalog("action", [], [client("q1", "cm", "filtered_camera", None)]),
    }
