"""What the mission holds (`rr_actors_lab.mission.loads`): `Loads.unload_now` (F6: cm's LiDARs let
go of at once) when the provider dies meanwhile.

Seen in a two-host demo run under load: during F6's cut, cm was killed by its heartbeat
while the mission's `unload` of its LiDAR query was in flight there. `unload` then raises
`RegistrarUnavailableError`, whose contract is that the id is released all the same (the
provider releases it when it reconciles after its restart: rule 20); the mission took it
for a failure and ended ("the mission failed: registrar 'cm' ... cannot be reached").

Real manager process, real SIGKILL (the provider kills itself as the `Unload` arrives).
"""

from __future__ import annotations

import sys
import uuid
from collections.abc import Callable
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors.testing import SharedObjects
from rr_actors_lab.mission.config import MissionConfig
from rr_actors_lab.mission.loads import Loads
from tests.registrar.test_consumer import dying_provider

pytestmark = [
    pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals"),
    pytest.mark.usefixtures("by_value"),  # (tests/conftest.py)
]


def test_unload_now_takes_a_provider_that_died_during_the_unload_as_released(
    tmp_path: Path, process_helpers: SharedObjects, eventually: Callable[..., bool]
) -> None:
    unloads, armed = process_helpers.list(), process_helpers.event()
    name = f"cm-{uuid.uuid4().hex[:8]}"
    spec = rr.ManagerSpec(name, dying_provider(unloads, armed, ran=False), isolation="process")
    told: list[str] = []

    with rr.Supervisor([spec], state_dir=tmp_path, max_restarts=5, period=10.0) as sup:
        app = sup.registrar(f"mission-{uuid.uuid4().hex[:8]}")
        loads = Loads(MissionConfig(), sup, app, tmp_path, say=told.append)  # type: ignore[arg-type]
        query = app.call(name, "leaf", "lidar", timeout=10)
        loads._held.append((query.id, name))
        armed.set()  # the provider dies as the Unload arrives, before it handles it

        loads.unload_now(name)  # no error: the id is released all the same (rule 20)

        assert not loads.holds(query.id)
        assert query.id not in [q.id for q in app.client_queries()]
        sup.wait_restarted(name, timeout=20)
        # the restarted provider releases it when it reconciles with the mission
        assert eventually(lambda: ["lidar"] == list(unloads), timeout=20)
        assert eventually(
            lambda: [] == sup.run_in(name, lambda r: r.server_queries("leaf")), timeout=20
        )
