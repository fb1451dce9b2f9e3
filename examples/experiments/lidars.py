"""A request factory for experiment plans: LiDAR requests for the mission's component manager.

A plan names it as `factory = "lidars:lidar"` (the plan's own directory is searched first
for import paths); the workload calls it for every call of that kind, with the call's key.
"""

from __future__ import annotations

from typing import Any

from rr_actors_lab.experiments import RequestContext


def lidar(key: str, context: RequestContext) -> dict[str, Any]:
    """The request for the component manager's `lidar` server: one LiDAR per key.

    Args:
        key: `"shared-<n>"` for one of the shared requests, `"unique-<client>-<n>"` for a
            request of this call's own.
        context: the client, the run's directory and the run process's pid.

    Returns:
        Equal keys give equal requests (the same LiDAR, loaded once).
    """
    return {
        "name": f"lidar-{key}",
        "bus": f"{context.run_dir}/bus",  # the programs' topic files
        "watch_pid": context.pid,  # the program exits when the run process does
        "rate": 2.0 if key.startswith("shared") else 5.0,
        "seed": 0,  # the LiDAR's noise: the same for every client, or keys would not share
    }
