"""The mission's figure (`rr_actors_lab.mission.plot`): `mission.png`: this run beside the thesis's
run (figure 6.5), and a zoom on a stop.

With `RR_DOCS_SCREENSHOTS=1` the last test runs the full mission and redraws the
tutorial's figure, `docs/img/mission.png` (as the observer's browser tests retake their
screenshots).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import os
import shutil
from pathlib import Path

import pytest

pytest.importorskip("matplotlib")


from matplotlib.figure import Figure
from matplotlib.image import imread

from rr_actors_lab.mission import FaultResult, MissionReport
from rr_actors_lab.mission.config import MissionConfig
from rr_actors_lab.mission.plot import plot, thesis_trace
from rr_actors_lab.mission.run import run_mission

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


def on_two_hosts(report: MissionReport) -> MissionReport:
    """The same run as `demo --hosts 2` reports it: F4 on the station, F6 the WiFi cut."""
    faults = (
        dataclasses.replace(report.faults[0], host="robot"),
        FaultResult("F4", "component manager killed", 14.0, 0.01, 0.1, 0.0, host="station"),
        FaultResult(
            "F6", "WiFi cut", 20.0, 3.0, 6.5, 0.0, host="both", details={"link_up_after_s": 5.0}
        ),
    )
    hosts = {
        "robot": {"managers": ["erm", "rm"], "faults": ["F1", "F6"]},
        "station": {"managers": ["cm"], "faults": ["F4", "F6"]},
    }
    return dataclasses.replace(report, faults=faults, hosts=hosts)


def texts(figure: Figure) -> list[str]:
    """Every annotation, title and legend label of a figure."""
    found = [t.get_text() for t in figure.texts]
    for ax in figure.axes:
        found += [t.get_text() for t in ax.texts] + [ax.get_title()]
        legend = ax.get_legend()
        found += [t.get_text() for t in legend.get_texts()] if legend is not None else []
    return found


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


def test_on_two_hosts_each_fault_marker_names_its_host_and_the_cut_is_shown(
    tmp_path: Path, drawn: list[Figure]
) -> None:
    plot(on_two_hosts(a_run()), tmp_path / "mission.png")
    (figure,) = drawn
    shown = texts(figure)

    assert {"F1 robot", "F4 station", "F6 both"} <= set(shown)
    assert "link between the hosts down" in shown
    assert any("two hosts (robot, station)" in text for text in shown)


def test_the_zoom_on_the_wifi_cut_says_the_thesis_had_none(
    tmp_path: Path, drawn: list[Figure]
) -> None:
    """F6 is ours: the thesis's run (section 6.2) had F1-F5 and no WiFi cut, so its stop
    there is no "0 s" to compare with (issue 44 item 8)."""
    report = on_two_hosts(a_run())
    *others, cut = report.faults
    longest = dataclasses.replace(
        report, faults=(*others, dataclasses.replace(cut, robot_stopped_s=3.75))
    )

    plot(longest, tmp_path / "mission.png")
    (figure,) = drawn
    [title] = [text for text in texts(figure) if "up close:" in text]

    assert "F6 both up close: stopped 3750 ms\n(thesis: no WiFi cut)" == title


def test_the_zoom_on_a_thesis_fault_gives_the_thesis_stop(
    tmp_path: Path, drawn: list[Figure]
) -> None:
    plot(a_run(), tmp_path / "mission.png")
    (figure,) = drawn
    [title] = [text for text in texts(figure) if "up close:" in text]

    assert "F1 up close: stopped 200 ms\n(thesis: 3 s)" == title


def test_on_one_host_the_markers_are_the_fault_ids_alone(
    tmp_path: Path, drawn: list[Figure]
) -> None:
    plot(a_run(), tmp_path / "mission.png")
    (figure,) = drawn
    shown = texts(figure)

    assert "F1" in shown
    assert any(text.startswith("F1 up close:") for text in shown)
    assert not any("F1 robot" in text or "two hosts" in text for text in shown)


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
