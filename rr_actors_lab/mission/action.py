"""The mission action (thesis figure 6.2): load the robot and a LiDAR, drive, recover, unload.

    Mission.run ─► open_two_hosts (hosts.py, with --hosts 2): the robot's host, the network
                ─► managers_tree (hosts.py): Supervisor(erm, cm, rm) ─► on_supervisor
                ─► _supervised: the mission's registrar; its collaborators, each in its module:
                     Faults (faults.py)      the fault schedule, injecting F1-F6, restarts seen
                     Loads (loads.py)        what the mission holds; the statuses it hears
                     Robot (robot.py)        the goal topic and the odometry
                     Recovery (recovery.py)  F1: LiDAR 2; F2: wait for UPDATE; F6: ride out the cut
                     Step (robot.py)         --step: stop before each fault, off the clock
                   ─► _mission: Loads.robot(), Loads.lidar("lidar1"), Robot.go()
                                ─► Drive.run (drive.py): the loop, to the goal
                   ─► _unload_all: Robot.stop(), Loads.unload_all(), Loads.catalogs()
                ─► kill_left_behind (faults.py) ─► build_report (report.py)

The collaborators share no fields: each is handed the others it calls. A Ctrl-C runs the
same cleanup, then raises `MissionInterruptedError`. Every call to a manager waits out its
restarts (`Trees.call_with_retry`, `retry_through_restarts`), whatever restarted it.
"""

from __future__ import annotations

import contextlib
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path

import rr_actors as rr
from rr_actors_lab.mission.config import (
    HOST_OF,
    MANAGERS,
    MissionConfig,
    MissionError,
    MissionInterruptedError,
)
from rr_actors_lab.mission.drive import Drive
from rr_actors_lab.mission.faults import Faults, kill_left_behind
from rr_actors_lab.mission.hosts import (
    ROBOT_MANAGERS,
    RobotHost,
    RobotObserver,
    Tree,
    Trees,
    managers_tree,
    open_two_hosts,
)
from rr_actors_lab.mission.loads import Loads
from rr_actors_lab.mission.netns import TwoHosts
from rr_actors_lab.mission.output import Progress
from rr_actors_lab.mission.recovery import Recovery
from rr_actors_lab.mission.report import MissionClock, MissionReport, build_report
from rr_actors_lab.mission.robot import Robot, Step

__all__ = ["Mission"]


class Mission:
    """One run of the mission: the action of thesis figure 6.2, with faults injected.

    Args:
        config: what to do.
        out: directory for the topics (`bus/`) and the managers' catalogs (`state/`), both
            emptied at the start.
        say: called with each line of the story (from the mission's and other threads).
        progress: called with where the mission is, about every `TICK` seconds.
        on_supervisor: called with the managers' supervisor before it starts (to open its
            observer); what it raises fails the run.
        before_fault: called on the mission's thread before each fault, with the fault and
            the processes it involves, while the robot waits; the fault follows its return.
        on_interrupt: called once on the mission's thread with the mission time (seconds) of
            a Ctrl-C, before the mission unloads everything.
        link: with `config.hosts == 2`: the two hosts' namespaces (this process runs in the
            station's; the robot's managers start in a process in the robot's).
        robot_observer: with `link`: the robot's host shares its tree with the station's page.
        step_span: called on the mission's thread with each step's name (`"mission step load
            robot"`, `"... drive"`, ...), the context it runs in (`otel.root_span` for
            `--trace`; the robot's host then makes spans of its tree too).

    Attributes:
        supervisor: the managers' supervisor while the mission runs, else `None`.
        clock: the mission clock (of the story's stamps, the progress line and the report).
    """

    def __init__(
        self,
        config: MissionConfig,
        out: Path,
        *,
        say: Callable[[str], None] = lambda _: None,
        progress: Callable[[Progress], None] = lambda _: None,
        on_supervisor: Callable[[rr.Supervisor], object] | None = None,
        before_fault: Callable[[str, list[str]], object] | None = None,
        on_interrupt: Callable[[float], object] | None = None,
        link: TwoHosts | None = None,
        robot_observer: RobotObserver | None = None,
        step_span: Callable[[str], contextlib.AbstractContextManager[object]] | None = None,
    ) -> None:
        if (config.hosts == 2) != (link is not None):
            raise MissionError("a mission on two hosts needs their namespaces (and only it)")
        self.config = config
        self.link = link
        self._robot_observer = robot_observer
        self._on_supervisor = on_supervisor
        self._on_interrupt = on_interrupt
        self._traced = step_span is not None
        self._step_span = step_span or (lambda _: contextlib.nullcontext())
        self._interrupted_at: float | None = None  # mission time of the Ctrl-C
        self._leaked_pids: list[int] = []
        self.out = out
        self.bus = out / "bus"
        self.state = out / "state"
        self.supervisor: rr.Supervisor | None = None
        self._say = say
        self._story_lock = threading.Lock()  # one line at a time, in the order of the stamps
        self._last_stamp = 0.0
        self._progress = progress
        self._robot = Robot(self.bus, config)
        self.clock = MissionClock(time.monotonic())
        self._step = None if before_fault is None else Step(before_fault, self._robot, self.clock)
        self._faults: Faults | None = None
        self._loads: Loads | None = None

    def say(self, text: str, *, at: float | None = None) -> None:
        """One line of the story, stamped with the mission time (`clock`): now, or of `at`
        (a `time.monotonic()` value: when what the line tells happened).

        Lines come from several threads; they are told in the order of their stamps: a
        line whose `at` is earlier than a line already told is stamped with that line's
        time (it is told then), so the story never goes back in time.
        """
        with self._story_lock:
            stamp = self.clock.now() if at is None else self.clock.at(at)
            stamp = max(stamp, self._last_stamp)
            self._last_stamp = stamp
            self._say(f"[{stamp:6.2f} s] {text}")

    # -- the run ----------------------------------------------------------------------

    def run(self) -> MissionReport:
        """Run the mission to the end, unload everything and report.

        Raises:
            MissionError: the mission could not be completed; everything was unloaded
                and stopped all the same.
            MissionInterruptedError: a Ctrl-C (`KeyboardInterrupt`) ended it; everything was
                unloaded and stopped all the same.
        """
        try:
            return self._run()
        except KeyboardInterrupt:
            self._interrupt()  # (if it came while the managers started, or at the end)
            assert self._interrupted_at is not None
            failed = self._loads.failed_unloads if self._loads is not None else 0
            raise MissionInterruptedError(self._interrupted_at, failed, self._leaked_pids) from None

    def _interrupt(self) -> None:
        """A Ctrl-C: tell `on_interrupt` (once) when it came."""
        if self._interrupted_at is None:
            self._interrupted_at = self.clock.now()
            if self._on_interrupt is not None:
                self._on_interrupt(self._interrupted_at)

    def _run(self) -> MissionReport:
        for sub in (self.bus, self.state):
            shutil.rmtree(sub, ignore_errors=True)
            sub.mkdir(parents=True)
        cfg = self.config
        two = self.link is not None
        here = tuple(m for m in MANAGERS if not two or m not in ROBOT_MANAGERS)
        with contextlib.ExitStack() as hosts:
            network: rr.ZenohNetwork | None = None
            robot: RobotHost | None = None
            if self.link is not None:
                network, robot = open_two_hosts(
                    self.link,
                    cfg,
                    self.out,
                    state=self.state,
                    bus=self.bus,
                    robot_observer=self._robot_observer,
                    say=self.say,
                    stack=hosts,
                    trace=self._traced,
                )
            else:
                self.say(f"starting the managers erm, cm and rm ({cfg.isolation} isolation)")
            sup = managers_tree(
                here,
                isolation=cfg.isolation,
                state_dir=self.state / "station" if two else self.state,
                network=network,
                name="station" if two else None,
            )
            if self._on_supervisor is not None:
                try:
                    self._on_supervisor(sup)  # before the start: an observer sees it start
                except BaseException:
                    sup.stop()  # (closes what it opened on it)
                    raise
            of: dict[str, Tree] = dict.fromkeys(MANAGERS, sup)
            if robot is not None:
                of.update(dict.fromkeys(ROBOT_MANAGERS, robot))
            trees = Trees(of, {m: HOST_OF[m] for m in MANAGERS} if two else None)
            try:
                start, arrived, entries = self._supervised(sup, trees, network, robot)
            except MissionError:
                raise
            except rr.RrError as exc:
                raise MissionError(f"the mission failed: {exc}") from exc
            finally:
                self.supervisor = None
                hosts.close()  # the robot's host, then the station's network
                leaked = self._leaked_pids = kill_left_behind(self.bus)
                if leaked:
                    self.say(f"{len(leaked)} process(es) were left behind: {leaked}; killed them")
        faults = self._faults
        assert faults is not None
        return build_report(
            odometry=self._robot.odometry,
            clock=self.clock,
            faults=faults.records,
            unplanned=faults.unplanned,
            start=start,
            arrived=arrived,
            nominal_time_s=cfg.nominal_time_s,
            leaked=leaked,
            entries=entries,
            host_of=HOST_OF if two else None,
        )

    def _supervised(
        self,
        sup: rr.Supervisor,
        trees: Trees,
        network: rr.ZenohNetwork | None,
        robot: RobotHost | None,
    ) -> tuple[float, float, dict[str, int]]:
        """Start this host's managers, run the mission, unload; (start, arrival, catalogs)."""
        cfg = self.config
        entries: dict[str, int] = {}
        with sup:
            self.supervisor = sup
            app = sup.registrar(rr.RegistrarConfig(name="mission", call_timeout=cfg.call_timeout))
            if network is not None:
                for name in ROBOT_MANAGERS:
                    network.wait_for(name, timeout=cfg.call_timeout)
            faults = self._faults = Faults(
                trees,
                app,
                recovery_timeout=cfg.recovery_timeout,
                say=self.say,
                link=self.link,
                cut_s=cfg.cut_s,
            )
            loads = self._loads = Loads(cfg, trees, app, self.bus, say=self.say)
            if robot is not None:
                robot.on_watch = faults.robot_saw
            try:
                start, arrived = self._mission(loads, faults)
            except KeyboardInterrupt:
                self._interrupt()  # said before the unloading, which takes a while
                raise
            finally:
                entries = self._unload_all(loads, faults)
                trees.flush_events()  # the last exits and restarts of the drive are heard
                faults.close()
                if robot is not None:  # before the station leaves (the robot would see it go)
                    robot.close()
        return start, arrived, entries

    def _mission(self, loads: Loads, faults: Faults) -> tuple[float, float]:
        """Load the robot and LiDAR 1, drive; return when the drive started and ended."""
        cfg = self.config
        with self._step_span("mission step load robot"):
            robot = loads.robot()
        self.say(
            f"robot loaded: driver pid {robot.response['driver_pid']}, "
            f"navigation pid {robot.response['navigation_pid']}"
        )
        with self._step_span("mission step load lidar1"):
            lidar = loads.lidar("lidar1")
        self.say(f"LiDAR 1 loaded: pid {lidar.response['pid']}")
        start = time.monotonic()
        self._robot.go()
        self.say(f"driving {cfg.distance_m:g} m at {cfg.speed:g} m/s")
        recovery = Recovery(cfg, loads=loads, robot=self._robot, faults=faults, say=self.say)
        drive = Drive(
            cfg,
            robot=self._robot,
            loads=loads,
            faults=faults,
            recovery=recovery,
            step=self._step,
            clock=self.clock,
            progress=self._progress,
            arrived=lambda at: self.say(  # (one clock with the report)
                f"goal reached after {self.clock.at(at) - self.clock.at(start):.2f} s", at=at
            ),
        )
        with self._step_span("mission step drive"):
            arrived = drive.run()
        return start, arrived

    def _unload_all(self, loads: Loads, faults: Faults) -> dict[str, int]:
        """Stop the robot, unload what the mission holds, count what the catalogs keep."""
        with self._step_span("mission step unload"):
            self._robot.stop()
            faults.notice_restarts()
            loads.unload_all()
            return loads.catalogs()
