"""`rr-actors demo --step`: before each fault the robot stops and the class is shown the pids.

    Drive (a fault point reached) ─► Step.pause(fault, pids)
        robot.stop() ─► before_fault(fault, pids(fault))   (the CLI waits for Enter)
                     ─► robot stands? ─► robot.go() ─► robot moves?   (PAUSE_SETTLE s each)
        ─► clock.add_pause(stop order, moving again)  ─► Drive injects the fault

The pause is left out of the mission clock: no stamp, timeline row or plot counts the
time the class took to press Enter.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from rr_actors.mission.report import MissionClock
from rr_actors.mission.robot import TICK, Robot

__all__ = ["PAUSE_SETTLE", "Step"]

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

        The pause lasts from the stop order until the robot drives again: its coming to a
        halt and its start after the Enter belong to the pause, not to the fault that
        follows (which would otherwise count them as the robot standing still).

        Args:
            fault: the fault about to be injected.
            pids: the lines of the processes a fault involves (`Faults.pids`).
        """
        paused = time.monotonic()
        self._robot.stop()
        try:
            self._before_fault(fault, pids(fault))
            self._wait_until_moving(False)  # (long done, unless Enter came at once)
            self._robot.go()
            self._wait_until_moving(True)
        finally:  # (after a Ctrl-C at the prompt the robot waits for the unloading)
            resumed = time.monotonic()
            self._clock.add_pause(paused, resumed)
        return resumed - paused

    def _wait_until_moving(self, moving: bool) -> None:
        """Wait until the odometry says the robot moves (or stands), `PAUSE_SETTLE` s at most."""
        odometry = self._robot.odometry
        deadline = time.monotonic() + PAUSE_SETTLE
        while True:
            odometry.read()
            now = time.monotonic()
            if odometry.moving(now) == moving or now >= deadline:
                return
            time.sleep(TICK)  # the odometry is a file the driver appends to: look again
