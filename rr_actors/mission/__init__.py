"""The TeMoto thesis's fault-injected robot mission (chapter 6) as a runnable demo.

`rr-actors demo` runs it; see [`rr_actors.mission.run`][rr_actors.mission.run] for what it
does and `docs/tutorial/mission.md` for a walk through it. It needs Linux (pidfds). The
subpackage holds:

- `programs`: the robot's programs (a LiDAR, a motor driver, a navigation node), small
  standard-library Python programs that talk over topic files;
- `managers`: the three managers (`erm_setup`, `cm_setup`, `rm_setup`);
- `config`: the faults and `MissionConfig`;
- `action`: the mission action, a coordinator of the collaborators below: `loads` (what
  the mission holds: load, release, unload), `robot` (the goal topic and the odometry),
  `drive` (the loop to the goal, the faults injected on the way), `recovery` (F1, F2,
  F6), `step` (`--step`'s pauses);
- `hosts`: the managers' trees, each host's network, the robot's host process;
- `faults`: where each fault strikes, injecting them (F1-F6), and following the managers
  through their restarts;
- `report`: the odometry, the report and the timeline's rows;
- `output`: the story, the live progress line and the timeline on a terminal (with
  `rich`) or as plain lines;
- `run`: `run_mission` and the command line;
- `plot`: the distance-over-time figure (needs matplotlib: `pip install 'rr-actors[demo]'`).
"""

from rr_actors.mission.config import FAULTS, MissionConfig, MissionError, MissionInterruptedError
from rr_actors.mission.report import FaultResult, MissionReport, UnplannedRestart
from rr_actors.mission.run import main, run_mission

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
