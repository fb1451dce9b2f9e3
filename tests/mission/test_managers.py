"""The mission's managers (`rr_actors.mission.managers`): what the erm adopts after a
restart."""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import rr_actors as rr
from rr_actors.mission.managers import ProcessTable
from rr_actors.mission.programs import start_time


def test_the_erm_does_not_adopt_a_process_whose_pid_was_reused(tmp_path: Path) -> None:
    registrar = rr.ResourceRegistrar.start(f"erm-{uuid.uuid4().hex[:8]}")
    try:
        table = ProcessTable(registrar)
        me = os.getpid()
        created = start_time(me)
        assert created is not None
        impostor = rr.Query(
            "q1",
            "program",
            registrar.name,
            "cm",
            {"name": "lidar1", "bus": str(tmp_path)},
            {"name": "lidar1", "pid": me, "start_time": created + 1},
        )

        dead = table.adopt([impostor])
    finally:
        registrar.stop()

    assert [impostor] == dead
