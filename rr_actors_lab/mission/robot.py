"""The robot as the mission drives it: the goal it is given and the odometry it leaves.

    Mission, Drive, Recovery, Step ── go() / stop() ──► bus/goal.json (distance, speed, paused)
                                                           │ the navigation program drives to it
    Drive, Step ◄── odometry.read() ◄── bus/odom.jsonl ◄───┘ the motor driver appends each sample

`rr-actors demo --step` stops the robot before each fault, shows the class the pids,
and drives on (`Step`):

    Drive (a fault point reached) ─► Step.pause(fault, pids)
        robot.stop() ─► before_fault(fault, pids(fault))   (the CLI waits for Enter)
                     ─► robot stands? ─► robot.go() ─► robot moves?   (PAUSE_SETTLE s each)
        ─► clock.add_pause(stop order, last seen standing)  ─► Drive injects the fault

The pause is left out of the mission clock.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from rr_actors_lab.mission import programs
from rr_actors_lab.mission.config import MissionConfig
from rr_actors_lab.mission.report import MissionClock, Odometry

__all__ = ["PAUSE_SETTLE", "TICK", "Robot", "Step"]

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


PAUSE_SETTLE = 5.0
"""Seconds a `--step` pause waits at most for the robot to stand, and to drive again (it
returns as soon as the odometry says so: a fraction of a second on a quiet machine; a
drive program starved of CPU took over 2 s, and its start then fell in the next fault's
time as the robot standing still)."""


class Step:
    """The pauses before the faults (`rr-actors demo --step`).

    Args:
        before_fault: called on the mission's thread with the fault and the processes it
            involves (one line each), while the robot waits; the fault is injected when
            it returns.
        robot: the robot to stop and drive on.
        clock: the mission clock the pauses are left out of.
    """

    def __init__(
        self,
        before_fault: Callable[[str, list[str]], object],
        robot: Robot,
        clock: MissionClock,
    ) -> None:
        self._before_fault = before_fault
        self._robot = robot
        self._clock = clock

    def pause(self, fault: str, pids: Callable[[str], list[str]]) -> float:
        """Stop the robot, hand the fault to `before_fault`, drive on; the seconds it took.

        The pause runs from the stop order to the last odometry sample that saw the robot
        standing (or the go order, if later): a stop after the first move is the fault's.

        Args:
            fault: the fault about to be injected.
            pids: the lines of the processes a fault involves (`Faults.pids`).
        """
        paused = time.monotonic()
        resumed: float | None = None
        self._robot.stop()
        try:
            self._before_fault(fault, pids(fault))
            self._wait_until_moving(False)  # (long done, unless Enter came at once)
            went = time.monotonic()  # (before the order: no move the order caused precedes it)
            self._robot.go()
            if self._wait_until_moving(True):
                resumed = max(went, self._robot.odometry.last_standing() or went)
        finally:  # (after a Ctrl-C at the prompt the robot waits for the unloading)
            if resumed is None:  # (not seen moving within PAUSE_SETTLE, or interrupted)
                resumed = time.monotonic()
            self._clock.add_pause(paused, resumed)
        return resumed - paused

    def _wait_until_moving(self, moving: bool) -> bool:
        """Whether the odometry says the robot moves (or stands) within `PAUSE_SETTLE` s."""
        odometry = self._robot.odometry
        deadline = time.monotonic() + PAUSE_SETTLE
        while True:
            odometry.read()
            now = time.monotonic()
            if odometry.moving(now) == moving:
                return True
            if now >= deadline:
                return False
            time.sleep(TICK)  # the odometry is a file the driver appends to: look again
