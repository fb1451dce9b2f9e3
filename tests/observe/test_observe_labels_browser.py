"""The demo's dependency graph in a real browser: resources read by their names.

Issue 24 item 2: the demo's requests all start with the bus path, so `server: repr(request)`
cut at 40 characters made `jackal-driver` and `jackal-navigation` look the same. The
mission's servers pass `label=`; the page draws those labels (and no query ids on edges),
and its status timeline names a resource by the same label (issue 30).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import pytest

from tests.support.observing import mission_held_before

DOCS_IMG = Path(__file__).resolve().parents[2] / "docs" / "img"

pytestmark = pytest.mark.timeout(180)


def test_the_demos_graph_names_each_resource_by_its_label(
    page: Any, process_helpers: Any, tmp_path: Path
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
                page.locator("#graph-panel").screenshot(path=str(DOCS_IMG / "observer-graph.png"))
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
