"""The TeMoto thesis's fault-injected robot mission (chapter 6) as a runnable demo.

`rr-actors demo` runs it; see [`rr_actors_lab.mission.run`][rr_actors_lab.mission.run] for what it
does and `docs/tutorial/mission.md` for a walk through it. It needs Linux (pidfds).
`programs` are the robot's programs (a LiDAR, a motor driver, a navigation node),
`managers` the three managers, `action` the mission action (its collaborators `loads`,
`robot`, `drive`, `recovery`), `hosts` the trees and hosts, `faults` F1-F6, `report`,
`output`, `plot` (needs matplotlib) and `run` (`run_mission`, the command line).
"""

from rr_actors_lab.mission.config import (
    FAULTS,
    MissionConfig,
    MissionError,
    MissionInterruptedError,
)
from rr_actors_lab.mission.report import FaultResult, MissionReport, UnplannedRestart
from rr_actors_lab.mission.run import main, run_mission

__all__ = [
    "FAULTS",
    "FaultResult",
    "MissionConfig",
    "MissionError",
    "MissionInterruptedError",
    "MissionReport",
    "UnplannedRestart",
    "main",
    "run_mission",
]
