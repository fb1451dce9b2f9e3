"""The robot as the mission drives it: the goal it is given and the odometry it leaves.

    Mission, Drive, Recovery, Step ── go() / stop() ──► bus/goal.json (distance, speed, paused)
                                                           │ the navigation program drives to it
    Drive, Step ◄── odometry.read() ◄── bus/odom.jsonl ◄───┘ the motor driver appends each sample

Both are topic files (`programs.publish`, `programs.read_topic`): the mission talks to
the robot's programs only through them, whichever host those programs run on.
"""

from __future__ import annotations

from pathlib import Path

from rr_actors.mission import programs
from rr_actors.mission.config import MissionConfig
from rr_actors.mission.report import Odometry

__all__ = ["TICK", "Robot"]

TICK = 0.02
"""Seconds between two looks at the odometry (and at the progress line)."""


class Robot:
    """The goal topic the mission publishes, and the odometry it follows.

    Args:
        bus: the programs' topics.
        config: the mission (its `distance_m` and `speed`).

    Attributes:
        odometry: every sample the drivers published (read on the mission's thread).
    """

    def __init__(self, bus: Path, config: MissionConfig) -> None:
        self._bus = bus
        self._distance_m = config.distance_m
        self._speed = config.speed
        self.odometry = Odometry(bus / "odom.jsonl")

    def go(self) -> None:
        """Drive to the goal (the navigation program starts at once)."""
        self._goal(paused=False)

    def stop(self) -> None:
        """Stand still (the navigation program stops the robot)."""
        self._goal(paused=True)

    def _goal(self, *, paused: bool) -> None:
        programs.publish(
            self._bus,
            "goal",
            {"distance_m": self._distance_m, "speed": self._speed, "paused": paused},
        )
