"""The observer's page (`rr_actors_lab/observe/static/`: its HTML and JavaScript) in a real browser:
Playwright driving Debian's chromium.

`playwright install` cannot download a browser here, so the tests launch the system's
chromium (`/usr/bin/chromium`, or `RR_CHROMIUM`) through `executable_path`, headless, with
a fresh profile. `.ci/run` (and the README's test command) installs chromium when it is
missing; a missing browser or Playwright fails these tests, it never skips them.

Screenshots for the docs are taken here too: with `RR_DOCS_SCREENSHOTS=1` they are
written to `docs/img/` (`RR_DOCS_SCREENSHOTS=1 python -m pytest
tests/observe/test_page.py`), otherwise to the test's temporary directory.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
import rr_actors_lab.observe as _lab_observe
from tests.support.gating import GatedLoad
from tests.support.observed_tree import REQUEST, device, figure_27
from tests.support.observing import mission_held_before, open_a_page_late, request

DOCS_IMG = Path(__file__).resolve().parents[2] / "docs" / "img"

pytestmark = pytest.mark.timeout(120)


def screenshot(page: Any, name: str, tmp_path: Path) -> Path:
    """Save a screenshot: to docs/img/ with RR_DOCS_SCREENSHOTS=1, else to `tmp_path`."""
    where = DOCS_IMG if os.environ.get("RR_DOCS_SCREENSHOTS") == "1" else tmp_path
    path = where / name
    page.screenshot(path=str(path), full_page=True)
    return path


def row(page: Any, name: str) -> Any:
    return page.locator(f'.node[data-child="{name}"]')


def test_the_page_shows_the_tree(tree: rr.Supervisor, page: Any, tmp_path: Path) -> None:
    observer = _lab_observe.observe(tree)
    actions = [tree.registrar(name) for name in ("action1", "action2")]  # figure 2.7 ...
    queries = [action.call("cm", "filtered_camera", REQUEST) for action in actions]

    page.goto(observer.url)
    page.wait_for_selector('.node[data-child="cm"][data-state="running"]')

    assert (
        f"pid {tree.child('erm').pid}"
        == row(page, "erm").locator('[data-field="pid"]').inner_text()
    )
    assert "0 restarts" == row(page, "cm").locator('[data-field="restarts"]').inner_text()
    assert "live" == page.locator("#connection").inner_text()
    assert 0 == page.locator("[data-fault]").count()  # no teaching mode: no buttons
    page.wait_for_selector('#catalogs [data-registrar="action2"] .client')  # ... on the page
    screenshot(page, "observer-tree.png", tmp_path)
    for action, query in zip(actions, queries, strict=True):
        action.unload(query.id)


def test_a_sigkill_of_a_manager_shows_its_restart_count_going_to_1(
    tree: rr.Supervisor, page: Any
) -> None:
    # (how soon is the benchmark's: bench_observer.py, "kill -> page shows restarts + 1",
    # 588 ms; asserted under 1 s here, it took longer on a loaded machine)
    observer = _lab_observe.observe(tree)
    page.goto(observer.url)
    page.wait_for_selector('.node[data-child="erm"][data-restarts="0"][data-state="running"]')
    pid = tree.child("erm").pid
    assert pid is not None

    os.kill(pid, signal.SIGKILL)
    page.wait_for_selector('.node[data-child="erm"][data-restarts="1"]', timeout=30_000)

    assert "1 restart" == row(page, "erm").locator('[data-field="restarts"]').inner_text()
    assert "killed by SIGKILL" in row(page, "erm").locator('[data-field="last-exit"]').inner_text()


def test_a_fatal_appears_in_the_timeline_with_its_hops(
    tree: rr.Supervisor, page: Any, tmp_path: Path
) -> None:
    observer = _lab_observe.observe(tree)
    app = tree.registrar("action")
    query = app.call("cm", "filtered_camera", REQUEST, on_status=lambda q, u: None)
    page.goto(observer.url)
    page.wait_for_selector('#catalogs [data-registrar="erm"] [data-server="camera"] .resource')

    tree.run_in(
        "erm",
        lambda reg: reg.send_status(
            reg.server_queries("camera")[0].id, rr.Status.FATAL, "camera unplugged"
        ),
    )
    fatal = page.locator('#timeline li[data-status="FATAL"]')
    fatal.locator('[data-hop="2"]').wait_for(timeout=5000)

    assert "camera unplugged" in fatal.inner_text()
    assert ["1", "2"] == sorted(
        fatal.locator("[data-hop]").evaluate_all("items => items.map(i => i.dataset.hop)")
    )
    screenshot(page, "observer-fatal.png", tmp_path)
    app.unload(query.id)


def test_the_teaching_mode_kill_button_kills_the_managers_process(
    tree: rr.Supervisor, page: Any, tmp_path: Path
) -> None:
    observer = _lab_observe.observe(tree, allow_faults=True)
    page.goto(observer.url)
    page.wait_for_selector('.node[data-child="cm"][data-state="running"]')
    pid = tree.child("cm").pid
    assert pid is not None
    erm_pid = tree.child("erm").pid

    row(page, "cm").locator('button[data-fault="kill"]').click()
    page.wait_for_selector("#confirm:not([hidden])")
    question = page.locator("#confirm-text").inner_text()
    screenshot(page, "observer-confirm.png", tmp_path)
    page.locator("#confirm-ok").click()
    # (the notice shows the answer for 8 s: waited for now, not after the restart)
    page.wait_for_selector('#notice:not([hidden]):has-text("SIGKILL sent to cm")')
    info = tree.wait_restarted("cm", timeout=10)

    assert f"SIGKILL cm (pid {pid})?" == question
    assert not Path(f"/proc/{pid}").exists()  # that process is gone ...
    assert (1, "killed by SIGKILL") == (info.restarts, info.last_exit)
    assert (erm_pid, 0) == (tree.child("erm").pid, tree.child("erm").restarts)  # ... and only it
    page.wait_for_selector('.node[data-child="cm"][data-restarts="1"]')


def test_the_cancel_button_sends_nothing(tree: rr.Supervisor, page: Any) -> None:
    observer = _lab_observe.observe(tree, allow_faults=True)
    page.goto(observer.url)
    page.wait_for_selector('.node[data-child="erm"][data-state="running"]')
    pid = tree.child("erm").pid

    row(page, "erm").locator('button[data-fault="kill"]').click()
    page.locator("#confirm-cancel").click()

    assert page.locator("#confirm").is_hidden()
    assert (pid, 0) == (tree.child("erm").pid, tree.child("erm").restarts)


def test_the_page_shows_the_dependency_graph(tree: rr.Supervisor, page: Any) -> None:
    observer = _lab_observe.observe(tree)
    app = tree.registrar("action")
    query = app.call("cm", "filtered_camera", REQUEST)
    page.goto(observer.url)
    page.wait_for_selector('#catalogs [data-registrar="action"] .client')

    page.wait_for_function("() => document.querySelector('#graph canvas') !== null")

    assert page.locator("#graph canvas").count() >= 1
    app.unload(query.id)


def test_the_offline_page_shows_the_backups(
    supervisors: Any, process_helpers: Any, page: Any, tmp_path: Path
) -> None:
    state = tmp_path / "state"
    sup = figure_27(supervisors, state_dir=state).start()
    app = sup.registrar("action")
    query = app.call("cm", "filtered_camera", REQUEST)

    from rr_actors_lab.observe import observe_backups  # noqa: PLC0415

    with observe_backups(state) as observer:  # (the files of a running tree: read-only)
        page.goto(observer.url)
        page.wait_for_selector('#catalogs [data-registrar="cm"] .resource')
        files = page.locator("#tree").inner_text()
        screenshot(page, "observer-backups.png", tmp_path)

    assert "offline" == page.locator("#connection").inner_text()  # and nothing says "live"
    assert page.locator("#mode").is_hidden()
    assert "cm.db" in files
    assert "erm.db" in files
    app.unload(query.id)


def test_the_mission_right_after_f3(page: Any, process_helpers: Any, tmp_path: Path) -> None:
    """The demo's page once F3 was recovered, the mission held before F4 (the tutorial's)."""
    with mission_held_before("F4", tmp_path / "demo") as mission:
        page.goto(mission.url)
        assert mission.held.wait(60)
        page.wait_for_selector('.node[data-child="erm"][data-restarts="1"]')
        page.wait_for_selector('#catalogs [data-registrar="erm"]:not(.stale) .resource')
        screenshot(page, "observer-mission-f3.png", tmp_path)
        timeline = page.locator("#timeline").inner_text()
        page.close()  # before the page's server stops: no reconnect to log as an error

    assert "erm restarted after" in timeline
    assert "FATAL" in timeline  # F1 and F2 before it
    assert not mission.thread.is_alive()
    assert [True] == [report.ok for report in mission.result]


class TestLabels:
    """The demo's dependency graph in a real browser: resources read by their names.

    Issue 24 item 2: the demo's requests all start with the bus path, so `server: repr(request)`
    cut at 40 characters made `jackal-driver` and `jackal-navigation` look the same. The
    mission's servers pass `label=`; the page draws those labels (and no query ids on edges),
    and its status timeline names a resource by the same label (issue 30).
    """

    pytestmark = pytest.mark.timeout(180)

    def test_the_demos_graph_names_each_resource_by_its_label(
        self, page: Any, process_helpers: Any, tmp_path: Path
    ) -> None:
        # Before F3: F1 had LiDAR 2 replace LiDAR 1; after F2 the robot manager sent UPDATE.
        with mission_held_before("F3", tmp_path / "demo") as mission:
            try:
                page.goto(mission.url)
                assert mission.held.wait(60)
                page.wait_for_function(
                    "() => ['lidar2', 'jackal-navigation'].every((name) => "
                    "(document.querySelector('#graph').dataset.labels || '').includes(name))",
                    timeout=20_000,
                )
                labels = json.loads(page.locator("#graph").get_attribute("data-labels"))
                page.wait_for_selector("#timeline li.status-UPDATE", timeout=20_000)  # F2's
                statuses = page.locator("#timeline li.status").all_inner_texts()
                if os.environ.get("RR_DOCS_SCREENSHOTS") == "1":
                    page.locator("#graph-panel").screenshot(
                        path=str(DOCS_IMG / "observer-graph.png")
                    )
            finally:
                page.close()  # (before the mission ends: its observer closes, the page would retry)

        names = {label.split(" \u00d7")[0] for label in labels}  # (" \u00d72": two consumers)
        assert {"lidar2", "jackal-driver", "jackal-navigation"} <= names
        assert all(len(label) <= 40 for label in labels)
        # The status timeline names a resource as the graph does, not by its long request.
        assert any("UPDATE rm/robot jackal: " in text for text in statuses), statuses
        assert not any("{'" in text for text in statuses), statuses
        assert not mission.thread.is_alive()
        assert [True] == [report.ok for report in mission.result]


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


_FORCED = {"erm": "q-erm-0000", "cm": "q-cm-00000", "action": "q-act-0000"}
"""The query ids of the forced status below: erm's, and its two hops' (cm, action)."""


def _forced_page(supervisors: Any, tabs: Any) -> tuple[Any, Any]:
    """Figure 27's tree (thread managers) and a live page on its observer, cm running."""
    observer = _lab_observe.observe(figure_27(supervisors, isolation="thread").start())
    live = tabs()
    live.goto(observer.url)
    live.wait_for_selector('.node[data-child="cm"][data-state="running"]')
    return observer, live


def _deliveries(observer: Any, at: float) -> None:
    """Put the two hops' deliveries of a FATAL that erm sent at `at` into the hub."""
    for hop, registrar, latency in ((1, "cm", 0.007), (2, "action", 0.009)):
        observer._hub.add_event(
            {
                "type": "StatusDelivered",
                "registrar": registrar,
                "query_id": _FORCED[registrar],
                "status": "FATAL",
                "hop": hop,
                "latency_s": latency,
                "at": at + latency,
                "text": f"{registrar} received FATAL",
            }
        )


def _send(observer: Any, at: float) -> None:
    """Put erm's send of that FATAL (at `at`) into the hub."""
    observer._hub.add_event(
        {
            "type": "StatusSent",
            "registrar": "erm",
            "query_id": _FORCED["erm"],
            "status": "FATAL",
            "message": "camera unplugged",
            "at": at,
            "text": "erm sent FATAL",
        }
    )


class TestInAClass:
    """The observer in a class: the history a late page draws, the teacher's demo flags, the clock,
    the one badge, the offline page's first paint. A real chromium (Playwright), real processes.
    """

    pytestmark = pytest.mark.timeout(180)

    # -- the timeline of a page opened late --------------------------------------------------------

    def test_a_page_opened_after_a_status_draws_it_as_a_page_open_during_it_did(
        self, supervisors: Any, process_helpers: Any, tabs: Any, monkeypatch: Any
    ) -> None:
        """The observer's catalog of erm lags the send, as under load; forced here: it was
        read while the camera loaded (its row, not yet its consumer), and the next read waits
        until the live page drew the status. The late page opens on a fresher catalog."""
        loading = GatedLoad(process_helpers.event(), process_helpers.event(), device, wait=60)
        sup = figure_27(supervisors, camera=loading).start()
        page = open_a_page_late(sup, loading, tabs, monkeypatch, within_ms=30_000)

        assert 1 == page.late.locator("#timeline li[data-kind=status]").count()  # one row
        assert (
            page.live.locator("#timeline").inner_text()
            == page.late.locator("#timeline").inner_text()
        )

    def test_deliveries_that_reached_the_page_before_their_send_merge_live_and_replayed(
        self, supervisors: Any, tabs: Any
    ) -> None:
        """The order above depends on which process's events come first; here it is forced:
        the events go into the observer's hub (what its subscription does) deliveries first."""
        observer, live = _forced_page(supervisors, tabs)
        at = time.time()
        _deliveries(observer, at)
        _send(observer, at)
        live.locator('#timeline li[data-status="FATAL"] [data-hop="2"]').wait_for(timeout=5000)
        live.wait_for_function(f"() => Date.now() / 1000 > {at + 2.5}")  # late: 2.5 s after
        late = tabs()
        late.goto(observer.url)
        late.locator('#timeline li[data-status="FATAL"] [data-hop="2"]').wait_for(timeout=5000)
        late.wait_for_function(f"() => Date.now() / 1000 > {time.time() + 2.5}")  # (orphans out)

        assert 1 == live.locator("#timeline li[data-kind=status]").count()
        assert 1 == late.locator("#timeline li[data-kind=status]").count()  # one row, not three
        assert live.locator("#timeline").inner_text() == late.locator("#timeline").inner_text()

    def test_a_send_that_reaches_the_page_after_its_deliveries_were_shown_alone_takes_them_in(
        self, supervisors: Any, tabs: Any
    ) -> None:
        """Under load a send can come more than the page's wait (`ORPHAN_S`, 2 s) after its
        deliveries (CI saw it): they were drawn alone ("its send was not seen"), then the
        send drew a third row. Forced here: the send goes into the hub once the page shows
        the deliveries alone."""
        observer, live = _forced_page(supervisors, tabs)
        at = time.time()
        _deliveries(observer, at)
        alone = live.locator('#timeline li[data-kind=status]:has-text("its send was not seen")')
        alone.nth(1).wait_for(timeout=10_000)  # (both, each a row of its own)
        _send(observer, at)
        live.locator('#timeline li[data-status="FATAL"]:has-text("camera unplugged")').wait_for(
            timeout=5000
        )

        rows = live.locator("#timeline li[data-kind=status]")
        assert 1 == rows.count()  # one row, not three
        assert ["1", "2"] == sorted(
            rows.locator("[data-hop]").evaluate_all("items => items.map(i => i.dataset.hop)")
        )

    def test_demo_allow_faults_shows_the_buttons_and_the_mission_time_and_lingers_after_the_end(
        self, tabs: Any, process_helpers: Any, tmp_path: Path
    ) -> None:
        from rr_actors_lab.mission import run as demo  # noqa: PLC0415

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

    # -- the offline page -------------------------------------------------------------------------

    def test_the_offline_page_says_offline_only_and_its_first_paint_is_not_empty(
        self, supervisors: Any, process_helpers: Any, tabs: Any, tmp_path: Path
    ) -> None:
        state = tmp_path / "state"
        sup = figure_27(supervisors, state_dir=state).start()
        action = sup.registrar("action")
        query = action.call("cm", "filtered_camera", REQUEST)
        from rr_actors_lab.observe import observe_backups  # noqa: PLC0415

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


# -- a tree of 1,000 managers ------------------------------------------------------------------

TEAMS, PER_TEAM = 10, 100
"""The big tree: 10 supervisors of 100 thread managers each."""


def manager_node(name: str, restarts: int = 0) -> dict[str, Any]:
    """A thread manager as `LiveSource.tree()` gives it to the page."""
    return {
        "name": name,
        "kind": "manager",
        "isolation": "thread",
        "restart": "permanent",
        "state": "running",
        "pid": os.getpid(),
        "restarts": restarts,
        "last_exit": "crashed (registrar actor died)" if restarts else None,
        "restart_due": None,
        "hang_after": None,
    }


def big_tree(
    restarted: frozenset[str] = frozenset(), teams: int = TEAMS, per_team: int = PER_TEAM
) -> dict[str, Any]:
    """`LiveSource.tree()` of a running tree of `teams` x `per_team` thread managers."""
    teams = [
        {
            "name": f"team{t}",
            "kind": "supervisor",
            "isolation": None,
            "restart": "permanent",
            "state": "running",
            "pid": None,
            "restarts": 0,
            "last_exit": None,
            "restart_due": None,
            "strategy": "one_for_one",
            "max_restarts": 3,
            "period": 5.0,
            "children": [
                manager_node(name, int(name in restarted))
                for name in (f"t{t}-m{m:03d}" for m in range(per_team))
            ],
        }
        for t in range(teams)
    ]
    return {
        "name": "big",
        "kind": "supervisor",
        "strategy": "one_for_one",
        "max_restarts": 3,
        "period": 5.0,
        "children": teams,
        "state": "running",
        "gave_up": None,
        "server_time": time.time(),
    }


@contextlib.contextmanager
def fed_observer(tree: dict[str, Any]) -> Iterator[tuple[Any, Any]]:
    """An observer whose hub is fed the sections a live `tree` of thread managers gives
    (`tree`, a `catalog/<name>` each, `graph`): the real server and page, without starting
    the managers (a browser test of the page's size, not of the tree's start)."""
    from rr_actors_lab.observe._hub import Hub  # noqa: PLC0415
    from rr_actors_lab.observe._observer import Observer, _Nothing  # noqa: PLC0415
    from rr_actors_lab.observe._view import dependency_graph, summarise_catalog  # noqa: PLC0415

    hub = Hub()
    names = [m["name"] for team in tree["children"] for m in team["children"]]
    catalogs = {name: summarise_catalog(name, [], []) for name in names}
    hub.put("tree", tree)
    for name in names:
        hub.put(
            f"catalog/{name}",
            {
                "registrar": name,
                "kind": "thread manager",
                "state": "running",
                "available": True,
                "catalog": catalogs[name],
                "error": None,
            },
        )
    hub.put("graph", dependency_graph(catalogs, dict.fromkeys(names, "running")))
    hello = {"mode": "live", "title": "supervisor big", "pid": os.getpid()}
    observer = Observer(
        _Nothing(hub), hub, host="127.0.0.1", port=0, allow_remote=False, hello=hello, faults=None
    )
    try:
        yield observer, hub
    finally:
        observer.close()


@pytest.fixture
def big_page() -> Iterator[tuple[Any, Any]]:
    """The page of a tree of 1,000 thread managers (`fed_observer`)."""
    with fed_observer(big_tree()) as fed:
        yield fed


def unfolded(page: Any, url: str, supervisor: str, child: str) -> None:
    """The page at `url`, its tree drawn, `supervisor`'s row unfolded until `child` shows."""
    page.goto(url)
    page.wait_for_selector('body[data-tree-painted="yes"]')
    row(page, supervisor).locator("button[data-fold]").click()
    page.wait_for_selector(f'.node[data-child="{child}"]')


def painted_ms(page: Any, url: str) -> float:
    """Milliseconds from a navigation to `url` to the frame that drew its tree."""
    page.goto(url)
    page.wait_for_selector('body[data-tree-painted="yes"]')
    at: float = page.evaluate('performance.getEntriesByName("rr-tree-painted")[0].startTime')
    return at


def test_a_tree_of_1000_managers_is_painted_folded_within_1_s_with_its_counts(
    big_page: tuple[Any, Any], page: Any, tmp_path: Path
) -> None:
    observer, _ = big_page
    big, small = [], []
    with fed_observer(big_tree(teams=1, per_team=3)) as (floor, _):
        for _ in range(3):  # alternated, the best of three (a loaded machine's page waits)
            small.append(painted_ms(page, floor.url))
            big.append(painted_ms(page, observer.url))

    # From the navigation's start: the page, its script, the stream (1,003 messages), the
    # tree. Under 1 s on a quiet machine; on a loaded one, within 1 s of the same page with
    # a tree of 3 managers (the floor: how long any page takes there now).
    assert min(big) - min(small) < 1000, (big, small)
    assert 1 + TEAMS == page.locator("#tree .node").count()  # the root and its 10 folded teams
    assert ["no"] * TEAMS == page.locator(
        '#tree .node[data-kind="supervisor"]:not([data-child="big"])'
    ).evaluate_all("rows => rows.map(r => r.dataset.open)")
    assert (
        "100 managers · 100 running · 0 restarts below"
        == row(page, "team3").locator('[data-field="summary"]').inner_text()
    )
    assert "1000 managers" in row(page, "big").locator('[data-field="summary"]').inner_text()
    page.wait_for_selector("#catalogs [data-more-cards]")
    assert 50 == page.locator("#catalogs article.catalog").count()  # (a page of them)
    # (the graph is its own section of the stream: drawn when it came, maybe after the tree)
    page.wait_for_function(
        "() => document.querySelector('#graph-note').textContent"
        ".includes('1000 registrars without resources or queries not drawn')",
        timeout=30_000,
    )
    screenshot(page, "observer-big-tree.png", tmp_path)


def test_opening_a_folded_supervisor_of_the_big_tree_shows_its_children(
    big_page: tuple[Any, Any], page: Any
) -> None:
    observer, _ = big_page
    unfolded(page, observer.url, "team3", "t3-m099")

    assert "yes" == row(page, "team3").get_attribute("data-open")
    assert 1 + TEAMS + PER_TEAM == page.locator("#tree .node").count()
    assert "thread manager · permanent" == row(page, "t3-m042").locator(".what").inner_text()
    row(page, "team3").locator("button[data-fold]").click()
    page.wait_for_selector('.node[data-child="t3-m000"]', state="detached")
    assert 1 + TEAMS == page.locator("#tree .node").count()


def test_a_restart_in_the_big_tree_changes_its_rows_and_redraws_no_other(
    big_page: tuple[Any, Any], page: Any
) -> None:
    observer, hub = big_page
    unfolded(page, observer.url, "team7", "t7-m042")
    page.evaluate(  # (a mark on every row drawn: a row drawn again has none)
        "document.querySelectorAll('#tree .node').forEach(r => { r.rrProbe = true; })"
    )
    page.evaluate(  # (the rows written to: a text, a class or a data attribute set)
        """() => {
          window.rrTouched = new Set();
          new MutationObserver((records) => records.forEach((r) => {
            const at = r.target.nodeType === 1 ? r.target : r.target.parentElement;
            const node = at.closest(".node");
            if (node) window.rrTouched.add(node.dataset.child);
          })).observe(document.getElementById("tree"),
            { subtree: true, childList: true, attributes: true, characterData: true });
        }"""
    )

    hub.put("tree", big_tree(restarted=frozenset({"t7-m042", "t2-m005"})))
    page.wait_for_selector('.node[data-child="t7-m042"][data-restarts="1"]')
    page.wait_for_selector('.node[data-child="team2"][data-below="1"]')

    assert "1 restart" == row(page, "t7-m042").locator('[data-field="restarts"]').inner_text()
    assert (
        "100 managers · 100 running · 1 restart below"
        == row(page, "team2").locator('[data-field="summary"]').inner_text()
    )
    redrawn = page.evaluate(
        "[...document.querySelectorAll('#tree .node')].filter(r => !r.rrProbe).length"
    )
    assert 0 == redrawn
    touched = page.evaluate("[...window.rrTouched].sort()")
    assert ["big", "t7-m042", "team2", "team7"] == touched  # the rows on the two paths only
