"""The drive: to the goal, the faults injected at their points on the way.

    Drive.run: each tick (TICK s, or sooner when a status comes)
      ├─ loads.next_event() ─► Recovery.handle (F1: LiDAR 2; F2: wait for UPDATE; F6: seen)
      ├─ robot.odometry.read(): where is the robot?
      ├─ F6 seen ─► Recovery.ride_out_cut (until the link is back and all is loaded again)
      ├─ Faults.notice_restarts(): restarts no fault made; is the active fault recovered?
      ├─ the next fault's point reached, every manager running ─► [Step.pause] ─► Faults.inject
      ├─ at the goal, no fault pending or active ─► the arrival time
      └─ progress(Progress)

A fault not recovered within `recovery_timeout`, or a goal not reached in time, fails
the mission (`MissionError`).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from rr_actors_lab.mission.config import MissionConfig, MissionError
from rr_actors_lab.mission.faults import Faults, fault_points
from rr_actors_lab.mission.loads import Loads
from rr_actors_lab.mission.output import Progress
from rr_actors_lab.mission.recovery import Recovery
from rr_actors_lab.mission.report import SHORT_WHAT, FaultRecord, MissionClock
from rr_actors_lab.mission.robot import TICK, Robot, Step

__all__ = ["Drive"]


class Drive:
    """One drive to the goal, with the faults of `config` (runs on the mission's thread).

    Args:
        config: the mission (the path, the faults and their points, the timeouts).
        robot: the robot and its odometry.
        loads: what the mission holds (and the statuses its queries hear).
        faults: the faults to inject.
        recovery: what the mission does about each status.
        step: the pauses before the faults (`--step`), or `None`.
        clock: the mission clock (of the progress line).
        progress: called with where the mission is, about every `TICK` seconds.
        arrived: called once on the mission's thread with the arrival time (monotonic) as
            soon as the robot is seen at the goal.
    """

    def __init__(
        self,
        config: MissionConfig,
        *,
        robot: Robot,
        loads: Loads,
        faults: Faults,
        recovery: Recovery,
        step: Step | None,
        clock: MissionClock,
        progress: Callable[[Progress], None],
        arrived: Callable[[float], None] = lambda _: None,
    ) -> None:
        self._config = config
        self._arrived = arrived
        self._robot = robot
        self._loads = loads
        self._faults = faults
        self._recovery = recovery
        self._step = step
        self._clock = clock
        self._progress = progress
        self._points = fault_points(config)

    def run(self) -> float:
        """Drive to the goal, injecting the faults on the way; return the arrival time.

        Raises:
            MissionError: a fault was not recovered in time, the robot failed, or the
                goal was not reached in time.
        """
        cfg = self._config
        faults = self._faults
        odometry = self._robot.odometry
        pending = sorted(cfg.faults, key=lambda f: self._points[f])
        active: FaultRecord | None = None
        arrival: float | None = None
        deadline = (
            time.monotonic() + 3 * cfg.nominal_time_s + 30 + cfg.recovery_timeout * len(pending)
        )
        while True:
            event = self._loads.next_event(TICK)
            odometry.read()
            if event is not None:
                self._recovery.handle(event, active)
            if active is not None and active.id == "F6" and active.detected_at is not None:
                self._recovery.ride_out_cut(active)
            faults.notice_restarts()
            if active is not None and faults.recovered(active):
                active = None
            if active is not None and time.monotonic() - active.injected_at > cfg.recovery_timeout:
                raise MissionError(
                    f"{active.id} was not recovered within {cfg.recovery_timeout:g} s"
                )
            if (
                active is None
                and pending
                and odometry.x >= self._points[pending[0]] * cfg.distance_m
                and faults.ready()  # not while a manager is down for another reason
            ):
                if self._step is not None:
                    deadline += self._step.pause(pending[0], faults.pids)
                active = faults.inject(pending[0])
                if active is not None:
                    pending.pop(0)
            if arrival is None and odometry.x >= cfg.distance_m and not pending:
                arrival = odometry.arrival(cfg.distance_m) or time.monotonic()
                self._arrived(arrival)  # now, not after a fault still recovering: the story
            if arrival is not None and active is None:
                return arrival
            if time.monotonic() > deadline:
                raise MissionError(f"the goal was not reached in time (at {odometry.x:.2f} m)")
            now = time.monotonic()
            self._progress(
                Progress(
                    elapsed_s=self._clock.at(now),
                    distance_m=odometry.x,
                    goal_m=cfg.distance_m,
                    moving=odometry.moving(now),
                    status=f"{active.id}: {SHORT_WHAT[active.id]}" if active is not None else "",
                )
            )
