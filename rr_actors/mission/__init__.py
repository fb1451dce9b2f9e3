"""The TeMoto thesis's fault-injected robot mission (chapter 6) as a runnable demo.

`rr-actors demo` runs it; see [`rr_actors.mission.run`][rr_actors.mission.run] for what it
does and `docs/tutorial/mission.md` for a walk through it. The subpackage holds:

- `programs`: the robot's programs (a LiDAR, a motor driver, a navigation node), small
  standard-library Python programs that talk over topic files;
- `managers`: the three managers (`erm_setup`, `cm_setup`, `rm_setup`);
- `run`: the mission action, fault injection, timing and the report;
- `plot`: the distance-over-time figure (needs matplotlib: `pip install 'rr-actors[demo]'`).
"""

from rr_actors.mission.run import (
    FAULTS,
    FaultResult,
    MissionConfig,
    MissionError,
    MissionReport,
    main,
    run_mission,
)

__all__ = [
    "FAULTS",
    "FaultResult",
    "MissionConfig",
    "MissionError",
    "MissionReport",
    "main",
    "run_mission",
]
