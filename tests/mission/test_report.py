"""Timing and the report (`rr_actors_lab.mission.report`): the odometry log read back."""

from __future__ import annotations

import json
from pathlib import Path

from rr_actors_lab.mission.report import Odometry


def test_the_odometry_counts_a_gap_without_a_driver_as_a_stop(tmp_path: Path) -> None:
    log = tmp_path / "odom.jsonl"
    samples = [(0.0, 0.0, 1.0), (0.1, 0.1, 1.0), (0.2, 0.2, 1.0), (0.7, 0.2, 0.0), (0.8, 0.3, 1.0)]
    log.write_text("".join(json.dumps({"t": t, "x": x, "v": v}) + "\n" for t, x, v in samples))
    odometry = Odometry(log)

    odometry.read()

    assert [(0.2, 0.7)] == odometry.stops(0.0, 1.0)
