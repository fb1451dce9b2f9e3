"""The observer in a class: the history a late page draws, the teacher's demo flags, the clock,
the one badge, the offline page's first paint. A real chromium (Playwright), real processes."""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from tests.support.observed_tree import REQUEST, figure_27
from tests.support.observing import get_json, request

DOCS_IMG = Path(__file__).resolve().parents[2] / "docs" / "img"

pytestmark = pytest.mark.timeout(180)


@pytest.fixture
def tabs(browser: Any) -> Iterator[Any]:
    """`tabs()` opens a new tab; every tab is closed at the end, and none may log an error."""
    opened: list[Any] = []
    errors: list[str] = []

    def new() -> Any:
        tab = browser.new_page()
        tab.on("pageerror", lambda exc: errors.append(str(exc)))
        tab.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        opened.append(tab)
        return tab

    yield new
    for tab in opened:
        tab.close()
    assert [] == errors


def screenshot(page: Any, name: str, tmp_path: Path) -> None:
    """To docs/img/ with RR_DOCS_SCREENSHOTS=1, else to `tmp_path`."""
    where = DOCS_IMG if os.environ.get("RR_DOCS_SCREENSHOTS") == "1" else tmp_path
    page.screenshot(path=str(where / name), full_page=True)


# -- the timeline of a page opened late -----------------------------------------------------------


def test_a_page_opened_after_a_status_draws_it_as_a_page_open_during_it_did(
    supervisors: Any, process_helpers: Any, tabs: Any
) -> None:
    sup = figure_27(supervisors).start()
    observer = sup.observe()
    app = sup.registrar("action")
    query = app.call("cm", "filtered_camera", REQUEST, on_status=lambda q, u: None)
    live = tabs()
    live.goto(observer.url)
    live.wait_for_selector('#catalogs [data-registrar="erm"] [data-server="camera"] .resource')

    sup.run_in(
        "erm",
        lambda reg: reg.send_status(
            reg.server_queries("camera")[0].id, rr.Status.FATAL, "camera unplugged"
        ),
    )
    sup.flush_events()
    live.locator('#timeline li[data-status="FATAL"] [data-hop="2"]').wait_for(timeout=5000)
    sent = next(
        e for e in get_json(observer.url, "/api/state")["events"] if e["type"] == "StatusSent"
    )
    live.wait_for_function(f"() => Date.now() / 1000 > {sent['at'] + 2.5}")  # late: 2.5 s after
    late = tabs()
    late.goto(observer.url)  # gets the whole history at once
    late.locator('#timeline li[data-status="FATAL"] [data-hop="2"]').wait_for(timeout=5000)

    assert 1 == late.locator("#timeline li[data-kind=status]").count()  # one row, not three
    assert live.locator("#timeline").inner_text() == late.locator("#timeline").inner_text()
    app.unload(query.id)


def test_deliveries_that_reached_the_page_before_their_send_merge_live_and_replayed(
    supervisors: Any, tabs: Any
) -> None:
    """The order above depends on which process's events come first; here it is forced:
    the events go into the observer's hub (what its subscription does) deliveries first."""
    sup = figure_27(supervisors, isolation="thread").start()
    observer = sup.observe()
    live = tabs()
    live.goto(observer.url)
    live.wait_for_selector('.node[data-child="cm"][data-state="running"]')
    at = time.time()
    query = {"erm": "q-erm-0000", "cm": "q-cm-00000", "action": "q-act-0000"}
    for hop, registrar, latency in ((1, "cm", 0.007), (2, "action", 0.009)):
        observer._hub.add_event(
            {
                "type": "StatusDelivered",
                "registrar": registrar,
                "query_id": query[registrar],
                "status": "FATAL",
                "hop": hop,
                "latency_s": latency,
                "at": at + latency,
                "text": f"{registrar} received FATAL",
            }
        )
    observer._hub.add_event(
        {
            "type": "StatusSent",
            "registrar": "erm",
            "query_id": query["erm"],
            "status": "FATAL",
            "message": "camera unplugged",
            "at": at,
            "text": "erm sent FATAL",
        }
    )
    live.locator('#timeline li[data-status="FATAL"] [data-hop="2"]').wait_for(timeout=5000)
    live.wait_for_function(f"() => Date.now() / 1000 > {at + 2.5}")  # late: 2.5 s after
    late = tabs()
    late.goto(observer.url)
    late.locator('#timeline li[data-status="FATAL"] [data-hop="2"]').wait_for(timeout=5000)
    late.wait_for_function(f"() => Date.now() / 1000 > {time.time() + 2.5}")  # (orphans out)

    assert 1 == live.locator("#timeline li[data-kind=status]").count()
    assert 1 == late.locator("#timeline li[data-kind=status]").count()  # one row, not three
    assert live.locator("#timeline").inner_text() == late.locator("#timeline").inner_text()


# -- the teacher's demo ---------------------------------------------------------------------------


class _Lines(io.StringIO):
    """The demo's output, with an event per line wanted (set when a line holds its text)."""

    def __init__(self, *wanted: str) -> None:
        super().__init__()
        self.seen = {text: threading.Event() for text in wanted}

    def write(self, text: str) -> int:
        for wanted, event in self.seen.items():
            if wanted in text:
                event.set()
        return super().write(text)

    def url(self) -> str:
        line = next(x for x in self.getvalue().splitlines() if x.startswith("observer: http"))
        return line.split()[1]


def test_demo_allow_faults_shows_the_buttons_and_the_mission_time_and_lingers_after_the_end(
    tabs: Any, process_helpers: Any, tmp_path: Path
) -> None:
    from rr_actors.mission import run as demo  # noqa: PLC0415

    args = demo.parser().parse_args(
        [
            "--fast",
            "--observe",
            "--allow-faults",
            "--linger",
            "8",
            "--quiet",
            "--out",
            str(tmp_path),
        ]
    )
    out = _Lines("observer: http", "the mission ended")
    codes: list[int] = []
    runner = threading.Thread(target=lambda: codes.append(demo.run(args, out)), daemon=True)
    runner.start()
    try:
        assert out.seen["observer: http"].wait(30)
        page = tabs()
        page.goto(out.url())
        page.wait_for_selector('.node[data-child="erm"] button[data-fault="kill"]')
        clock = page.locator("#clock").inner_text()
        badge = page.locator("#connection").inner_text()
        assert out.seen["the mission ended"].wait(90)
        page.wait_for_selector("#connection:text-is('ended')", timeout=5000)
        ended = {
            "buttons": page.locator("[data-fault]").count(),
            "clock": page.locator("#clock").inner_text(),
            "since": page.locator("#timeline time .since").count(),
            "tree": page.locator('.node[data-child="erm"]').count(),
        }
        screenshot(page, "observer-mission-ended.png", tmp_path)
        still = request(out.url(), "/api/state")
    finally:
        runner.join(60)

    assert [0] == codes
    assert clock.startswith("mission clock ")  # the story's stamps; not the mission time
    assert "live" == badge  # one badge: "live", and teaching mode apart
    assert page.locator("#mode").inner_text() == "teaching mode"
    assert {"buttons": 0, "tree": 1} == {k: ended[k] for k in ("buttons", "tree")}
    assert ended["clock"].endswith("s (ended)")
    assert ended["since"] > 0  # the timeline gives each time in mission time too
    assert 200 == still[0]
    with pytest.raises(ConnectionRefusedError):  # closed after --linger
        request(out.url(), "/", timeout=2.0)


def test_demo_observe_serves_the_final_state_until_ctrl_c_and_says_so(
    process_helpers: Any, tmp_path: Path
) -> None:
    command = ["demo", "--fast", "--observe", "--quiet", "--out", str(tmp_path)]
    with subprocess.Popen(
        [sys.executable, "-m", "rr_actors", *command],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    ) as demo:
        try:
            assert demo.stdout is not None
            lines = []
            for line in demo.stdout:
                lines.append(line)
                if "press Ctrl-C" in line:
                    break
            url = next(x for x in lines if x.startswith("observer: http")).split()[1]
            serving = request(url, "/api/state")[0]
            demo.send_signal(signal.SIGINT)
            code = demo.wait(30)
        finally:
            if demo.poll() is None:
                demo.kill()
                demo.wait(10)

    # The last thing said, wrapped at words to 80 columns: the mission ended, until Ctrl-C.
    last = next(i for i, line in enumerate(lines) if line.startswith("observer: the mission"))
    said = " ".join(line.strip() for line in lines[last:])
    assert said.startswith("observer: the mission ended;"), said
    assert said.endswith("(press Ctrl-C to stop)"), said
    assert (200, 0) == (serving, code)
    with pytest.raises(ConnectionRefusedError):
        request(url, "/", timeout=2.0)


def test_allow_faults_without_observe_is_a_usage_error(tmp_path: Path) -> None:
    from rr_actors.mission import run as demo  # noqa: PLC0415

    args = demo.parser().parse_args(["--fast", "--allow-faults", "--out", str(tmp_path)])

    assert 2 == demo.run(args, io.StringIO())


# -- the offline page -------------------------------------------------------------------------


def test_the_offline_page_says_offline_only_and_its_first_paint_is_not_empty(
    supervisors: Any, process_helpers: Any, tabs: Any, tmp_path: Path
) -> None:
    state = tmp_path / "state"
    sup = figure_27(supervisors, state_dir=state).start()
    action = sup.registrar("action")
    query = action.call("cm", "filtered_camera", REQUEST)
    from rr_actors.observe import observe_backups  # noqa: PLC0415

    with observe_backups(state) as observer:
        page = tabs()
        held: list[Any] = []
        page.route("**/api/stream*", lambda r: held.append(r))  # noqa: PLW0108 - (a bound method is refused)
        page.goto(observer.url)
        first = {
            "badge": page.locator("#connection").inner_text(),
            "tree": page.locator("#tree").inner_text(),
            "catalogs": page.locator("#catalogs").inner_text(),
            "timeline shown": page.locator("#timeline-panel").is_visible(),
        }
        page.unroute("**/api/stream*")
        page.reload()
        page.wait_for_selector('#catalogs [data-registrar="cm"] .resource')
        text = page.locator("body").inner_text()

    assert "offline" == first["badge"]
    assert first["tree"]  # "Reading the backups…", not an empty panel
    assert first["catalogs"]
    assert not first["timeline shown"]  # no live events offline: no empty timeline either
    assert "live" not in text.lower().split()
    action.unload(query.id)
