"""The demo's dependency graph in a real browser: resources read by their names.

Issue 24 item 2: the demo's requests all start with the bus path, so `server: repr(request)`
cut at 40 characters made `jackal-driver` and `jackal-navigation` look the same. The
mission's servers pass `label=`; the page draws those labels (and no query ids on edges).
"""

from __future__ import annotations

import json
import os
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import playwright.sync_api as playwright_api  # (the dev extra; a missing one fails, never skips)
import pytest
from observing import CHROMIUM_ARGS, chromium

import rr_actors as rr

DOCS_IMG = Path(__file__).resolve().parents[2] / "docs" / "img"

pytestmark = pytest.mark.timeout(180)


@pytest.fixture
def page() -> Iterator[Any]:
    """A headless chromium tab (a fresh profile); fails the test if the page logs an error."""
    path = chromium()
    if path is None:
        pytest.fail("no chromium to drive (apt-get install -y chromium; .ci/run does)")
    with playwright_api.sync_playwright() as playwright, tempfile.TemporaryDirectory() as profile:
        context = playwright.chromium.launch_persistent_context(
            profile,
            executable_path=path,
            headless=True,
            args=CHROMIUM_ARGS,
            viewport={"width": 1400, "height": 1000},
        )
        tab = context.new_page()
        errors: list[str] = []
        tab.on("pageerror", lambda exc: errors.append(str(exc)))
        tab.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        yield tab
        context.close()
        assert [] == errors


def test_the_demos_graph_names_each_resource_by_its_label(
    page: Any, process_helpers: Any, tmp_path: Path
) -> None:
    from rr_actors.mission.config import MissionConfig  # noqa: PLC0415
    from rr_actors.mission.run import run_mission  # noqa: PLC0415

    urls: list[str] = []
    opened, at_f2, go_on = threading.Event(), threading.Event(), threading.Event()

    def observe(sup: rr.Supervisor) -> None:
        urls.append(sup.observe().url)
        opened.set()

    def before_fault(fault: str, _pids: list[str]) -> None:  # on the mission's thread
        if fault == "F2":  # (F1 replaced LiDAR 1 by LiDAR 2)
            at_f2.set()
            go_on.wait(60)

    result: list[Any] = []
    mission = threading.Thread(
        target=lambda: result.append(
            run_mission(
                MissionConfig.fast(),
                tmp_path / "demo",
                on_supervisor=observe,
                before_fault=before_fault,
            )
        ),
        daemon=True,
    )
    mission.start()
    try:
        assert opened.wait(30)
        page.goto(urls[0])
        assert at_f2.wait(60)
        page.wait_for_function(
            "() => ['lidar2', 'jackal-navigation'].every((name) => "
            "(document.querySelector('#graph').dataset.labels || '').includes(name))",
            timeout=20_000,
        )
        labels = json.loads(page.locator("#graph").get_attribute("data-labels"))
        if os.environ.get("RR_DOCS_SCREENSHOTS") == "1":
            page.locator("#graph-panel").screenshot(path=str(DOCS_IMG / "observer-graph.png"))
    finally:
        page.close()  # (before the mission ends: its observer closes, the page would retry)
        go_on.set()
        mission.join(120)

    names = {label.split(" \u00d7")[0] for label in labels}  # (" \u00d72": two consumers)
    assert {"lidar2", "jackal-driver", "jackal-navigation"} <= names
    assert all(len(label) <= 40 for label in labels)
    assert not mission.is_alive()
    assert [True] == [report.ok for report in result]
