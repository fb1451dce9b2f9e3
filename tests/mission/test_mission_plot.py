"""`mission.png`: this run beside the thesis's run (figure 6.5), and a zoom on a stop.

With `RR_DOCS_SCREENSHOTS=1` the last test runs the full mission and redraws the
tutorial's figure, `docs/img/mission.png` (as the observer's browser tests retake their
screenshots).
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
from pathlib import Path

import pytest

pytest.importorskip("matplotlib")


from matplotlib.image import imread

from rr_actors.mission import FaultResult, MissionReport
from rr_actors.mission.config import MissionConfig
from rr_actors.mission.plot import plot, thesis_trace
from rr_actors.mission.run import run_mission

DOCS_IMG = Path(__file__).resolve().parents[2] / "docs" / "img"


def a_run() -> MissionReport:
    """16 m at 0.5 m/s from 1 s on, stopped 0.2 s at 5 m (F1); the drive takes 32.2 s."""
    trace = [(1.0 + i * 0.02, min(16.0, i * 0.01)) for i in range(500)]  # up to 5 m
    trace += [(11.0 + i * 0.02, 5.0) for i in range(1, 11)]  # stopped until 11.2 s
    trace += [(11.2 + i * 0.02, min(16.0, 5.0 + i * 0.01)) for i in range(1, 1101)]
    return MissionReport(
        mission_time_s=32.2,
        distance_m=16.0,
        nominal_time_s=32.0,
        faults=(FaultResult("F1", "LiDAR 1 disconnected", 10.98, 0.02, 0.24, 0.2),),
        leaked_processes=0,
        catalog_entries_left=0,
        catalog_entries_by_registrar={},
        trace=tuple(trace),
        stops=((11.0, 11.2),),
        drive_started_s=1.0,
    )


def test_the_thesis_run_is_43_s_with_stops_of_3_and_5_s() -> None:
    corners = thesis_trace(16.0, start_s=2.0)
    stops = [
        (round(a[0], 6), round(b[0] - a[0], 6))
        for a, b in itertools.pairwise(corners)
        if a[1] == b[1]
    ]

    assert (2.0, 0.0) == corners[0]
    assert (45.0, 16.0) == (round(corners[-1][0], 6), corners[-1][1])
    assert [3.0, 5.0] == [seconds for _, seconds in stops]


def test_the_plot_has_the_runs_beside_each_other_and_a_zoom_panel(tmp_path: Path) -> None:
    path = tmp_path / "mission.png"

    plot(a_run(), path)
    height, width, _ = imread(path).shape

    assert width > 2 * height  # the runs' panel and the zoom's, side by side


def test_without_faults_there_is_no_zoom_panel(tmp_path: Path) -> None:
    path = tmp_path / "mission.png"
    report = a_run()
    quiet = MissionReport(**{**report.__dict__, "faults": (), "stops": ()})

    plot(quiet, path)
    height, width, _ = imread(path).shape

    assert width < 2 * height


@pytest.mark.usefixtures("process_helpers")
@pytest.mark.timeout(180)
def test_a_mission_draws_its_figure_and_the_tutorials_is_redrawn_on_request(
    tmp_path: Path,
) -> None:
    """A fast mission draws its figure; with RR_DOCS_SCREENSHOTS=1 a full one redraws the
    tutorial's (docs/img/mission.png) and prints its report for the tutorial's table."""
    redraw = os.environ.get("RR_DOCS_SCREENSHOTS") == "1"
    report = run_mission(MissionConfig() if redraw else MissionConfig.fast(), tmp_path)

    assert report.ok
    assert imread(tmp_path / "mission.png").shape[1] > 0
    if not redraw:
        return
    shutil.copyfile(tmp_path / "mission.png", DOCS_IMG / "mission.png")
    print(json.dumps(json.loads((tmp_path / "report.json").read_text()), indent=1))  # noqa: T201 - for the tutorial's table
