"""What the mission does about the statuses it hears: the recoveries of F1, F2 and F6.

    Drive ── each status event ──► Recovery.handle(event, active fault)
        F1  LiDAR FATAL         ─► robot.stop(), release LiDAR 1, load LiDAR 2, robot.go()
        F2  robot FATAL         ─► detected; rm restarts the driver itself ─► UPDATE: recovered
            robot FATAL, no F2  ─► MissionError (the robot failed)
        F6  FATAL (the lease)   ─► detected ─► Drive calls ride_out_cut(record):
            forget rm's ids, unload cm's LiDARs; call rm until the link is back (each call
            fails fast) ─► load LiDAR 1 again, robot.go(): recovered

F3-F5 (a manager killed) need nothing of the mission: `Faults` follows the supervisor
through the restart, and every call the mission makes waits a restart out.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import rr_actors as rr
from rr_actors_lab.mission.config import MissionConfig, MissionError
from rr_actors_lab.mission.faults import Faults
from rr_actors_lab.mission.loads import Loads, StatusEvent
from rr_actors_lab.mission.report import FaultRecord
from rr_actors_lab.mission.robot import TICK, Robot

__all__ = ["Recovery"]


class Recovery:
    """The mission's side of each recovery (runs on the mission's thread).

    Args:
        config: the mission (its `recovery_timeout`).
        loads: what the mission holds.
        robot: the robot's goal.
        faults: the faults injected (F6: whether the link is healed).
        say: tells one line of the story.
    """

    def __init__(
        self,
        config: MissionConfig,
        *,
        loads: Loads,
        robot: Robot,
        faults: Faults,
        say: Callable[[str], None],
    ) -> None:
        self._config = config
        self._loads = loads
        self._robot = robot
        self._faults = faults
        self._say = say

    def handle(self, event: StatusEvent, active: FaultRecord | None) -> None:
        """Tell the story of a status heard, and recover from what it says.

        Args:
            event: the status.
            active: the fault injected and not recovered yet, if any.

        Raises:
            MissionError: the robot failed with no fault that explains it.
        """
        status = event.update.status
        held = self._loads.holds(event.query_id)
        late = "" if held else " (late: the mission let go of that query already; nothing to do)"
        self._say(
            f"{event.kind} query {event.query_id[:8]} hears {status.name} from "
            f"{event.update.source}: {event.update.message}{late}"
        )
        if not held:
            return  # about a query the mission let go of already (F6 reloads both)
        if active is not None and active.id == "F6" and status is rr.Status.FATAL:
            if active.detected_at is None:  # the station saw the cut: its lease ran out
                active.detected_at = event.at
            return
        if event.kind == "lidar" and status is rr.Status.FATAL:
            record = active if active is not None and active.id == "F1" else None
            if record is not None:
                record.detected_at = event.at
            self._substitute_lidar(event.query_id, record)
        elif event.kind == "robot" and status is rr.Status.FATAL:
            if active is None or active.id != "F2":
                raise MissionError(f"the robot failed: {event.update.message}")
            active.detected_at = event.at
            if active.early_update_at is not None:
                active.recovered_at = active.early_update_at
        elif (
            event.kind == "robot"
            and status is rr.Status.UPDATE
            and active is not None
            and active.id == "F2"
        ):
            if active.detected_at is None:  # the UPDATE overtook its FATAL
                active.early_update_at = event.at
            else:
                active.recovered_at = event.at
            active.note = f"rm: {event.update.message}"

    def _substitute_lidar(self, dead_id: str, record: FaultRecord | None) -> None:
        """F1: stop the robot, release LiDAR 1, load LiDAR 2, drive on."""
        self._robot.stop()
        self._say("robot stopped; substituting LiDAR 2 for LiDAR 1")
        self._loads.release(dead_id)
        lidar = self._loads.lidar("lidar2")
        self._robot.go()
        if record is not None:
            record.recovered_at = time.monotonic()
            record.note = f"LiDAR 2 (pid {lidar.response['pid']}) replaced LiDAR 1"
        self._say(f"LiDAR 2 loaded (pid {lidar.response['pid']}); driving on")

    def ride_out_cut(self, record: FaultRecord) -> None:
        """F6 on the station: the link is cut; fail fast, wait for the heal, load again.

        The station heard `FATAL` for the robot (`rm` lost, rule 19) and the LiDAR, and forgot
        the robot's id; calls fail at once during the cut. Once the link is back the mission
        loads both again, and the reconcile releases the forgotten ids at the robot (rule 20).

        Raises:
            MissionError: the robot was not back within `recovery_timeout`.
        """
        cfg = self._config
        self._say("station: lost the robot's managers (FATAL); waiting for the link")
        self._loads.forget("rm")  # forgotten (rule 19)
        self._loads.unload_now("cm")  # cm is here: its LiDAR lost the ERM's program
        deadline = record.injected_at + cfg.recovery_timeout
        robot: rr.Query | None = None
        while robot is None:
            began = time.monotonic()
            try:
                robot = self._loads.robot_once(timeout=max(deadline - began, 1e-3))
            except (rr.RegistrarUnavailableError, rr.errors.UnknownRegistrarError) as exc:
                failed = time.monotonic() - began
                if record.healed_at is None:
                    record.failed_calls.append(failed)
                if len(record.failed_calls) == 1 and record.healed_at is None:
                    self._say(
                        f"station: a call to rm during the cut failed after {failed * 1000:.0f} "
                        f"ms ({exc.__class__.__name__}), not at its timeout"
                    )
                if time.monotonic() >= deadline:
                    raise MissionError(
                        f"F6: the robot was not back within {cfg.recovery_timeout:g} s"
                    ) from exc
                self._wait_for_heal(deadline)
        lidar = self._loads.lidar("lidar1")
        self._robot.go()
        record.recovered_at = time.monotonic()
        record.note = (
            f"robot reloaded (driver pid {robot.response['driver_pid']}), LiDAR 1 reloaded "
            f"(pid {lidar.response['pid']}); {len(record.failed_calls)} call(s) failed fast "
            "during the cut"
        )
        self._say(
            f"F6 recovered: link back, robot (driver pid {robot.response['driver_pid']}) and "
            f"LiDAR (pid {lidar.response['pid']}) loaded again; the robot's host released what "
            "the station forgot; driving on"
        )

    def _wait_for_heal(self, deadline: float) -> None:
        """Wait for F6's heal (or a short while once healed: Zenoh reconnects by itself)."""
        healed = self._faults.healed
        if not healed.is_set():
            healed.wait(max(0.0, deadline - time.monotonic()))
        else:
            time.sleep(TICK * 5)  # the link is up; Zenoh is dialling again: ask again soon
