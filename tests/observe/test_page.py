"""The observer's page in a real browser: Playwright driving Debian's chromium.

`playwright install` cannot download a browser here, so the tests launch the system's
chromium (`/usr/bin/chromium`, or `RR_CHROMIUM`) through `executable_path`, headless, with
a fresh profile. `.ci/run` (and the README's test command) installs chromium when it is
missing; a missing browser or Playwright fails these tests, it never skips them.

Screenshots for the docs are taken here too: with `RR_DOCS_SCREENSHOTS=1` they are
written to `docs/img/` (`RR_DOCS_SCREENSHOTS=1 python -m pytest
tests/observe/test_observe_browser.py`), otherwise to the test's temporary directory.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from tests.support.observed_tree import REQUEST, figure_27
from tests.support.observing import mission_held_before

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


@pytest.fixture
def tree(supervisors: Any, process_helpers: Any) -> rr.Supervisor:
    return figure_27(supervisors).start()


def test_the_page_shows_the_tree(tree: rr.Supervisor, page: Any, tmp_path: Path) -> None:
    observer = tree.observe()
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
    observer = tree.observe()
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
    observer = tree.observe()
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
    observer = tree.observe(allow_faults=True)
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
    observer = tree.observe(allow_faults=True)
    page.goto(observer.url)
    page.wait_for_selector('.node[data-child="erm"][data-state="running"]')
    pid = tree.child("erm").pid

    row(page, "erm").locator('button[data-fault="kill"]').click()
    page.locator("#confirm-cancel").click()

    assert page.locator("#confirm").is_hidden()
    assert (pid, 0) == (tree.child("erm").pid, tree.child("erm").restarts)


def test_the_page_shows_the_dependency_graph(tree: rr.Supervisor, page: Any) -> None:
    observer = tree.observe()
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

    from rr_actors.observe import observe_backups  # noqa: PLC0415

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
