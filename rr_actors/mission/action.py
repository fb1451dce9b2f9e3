"""The mission action (thesis figure 6.2): load the robot and a LiDAR, drive, recover, unload.

    Mission.run ─► Supervisor(erm, cm, rm) ─► _mission: load robot (rm), LiDAR 1 (cm)
                                              _drive: each tick (TICK s)
                                                ├─ status events from the callbacks ─► _handle
                                                │    (F1: substitute LiDAR 2; F2: wait for UPDATE)
                                                ├─ Odometry.read(): has a fault point been reached?
                                                │    ─► Faults.inject (faults.py)
                                                ├─ Faults.notice_restarts(): restarts no fault made
                                                └─ progress(Progress)
               ─► _unload_all: release what the mission holds, count the catalogs' rows
               ─► leaked programs killed ─► build_report (report.py)

A Ctrl-C (`KeyboardInterrupt` in the mission's thread) anywhere on the way is told to
`on_interrupt` at once; the same cleanup runs, then `MissionInterruptedError` is raised.

Every call to a manager goes through `Supervisor.call_with_retry` or
`retry_through_restarts`, so a manager that was restarted for any reason (a fault, or a
kill by hand) is waited for, not taken as a failure of the mission.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import queue
import random
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import rr_actors as rr
from rr_actors.mission import managers, programs
from rr_actors.mission.config import (
    FAULT_WHAT,
    HOST_OF,
    MANAGERS,
    MissionConfig,
    MissionError,
    MissionInterruptedError,
)
from rr_actors.mission.faults import Faults, alive, retry_through_restarts, sigkill
from rr_actors.mission.hosts import (
    CERTS,
    MEMBERS,
    PORT,
    ROBOT_LOG,
    ROBOT_MANAGERS,
    SYSTEM,
    RobotHost,
    RobotObserver,
    RobotSettings,
    Tree,
    Trees,
)
from rr_actors.mission.netns import TwoHosts
from rr_actors.mission.output import Progress
from rr_actors.mission.report import (
    FaultRecord,
    MissionClock,
    MissionReport,
    Odometry,
    build_report,
)
from rr_actors.testing import catalog_snapshot

__all__ = ["TICK", "Mission"]

TICK = 0.02
"""Seconds between two looks at the odometry (and at the progress line)."""

PAUSE_SETTLE = 2.0
"""Seconds a `--step` pause waits at most for the robot to stand, and to drive again."""


@dataclass(frozen=True)
class _Event:
    kind: Literal["lidar", "robot"]
    query_id: str
    update: rr.StatusUpdate
    at: float


def _catalog_size(registrar: rr.ResourceRegistrar) -> int:
    """Rows in a registrar's catalog (run inside the manager, via `Supervisor.run_in`)."""
    view = catalog_snapshot(registrar)
    return len(view.resources) + len(view.clients)


class Mission:
    """One run of the mission: the action of thesis figure 6.2, with faults injected.

    Args:
        config: what to do.
        out: directory for the topics (`bus/`) and the managers' catalogs (`state/`);
            those two are emptied at the start.
        say: called with each line of the story (from the mission's and other threads).
        progress: called with where the mission is, about every `TICK` seconds.
        on_supervisor: called with the managers' supervisor before it starts (to open
            its observer: `rr-actors demo --observe`); what it raises fails the run.
        before_fault: called on the mission's thread before each fault, with the fault
            and the processes it involves (one line each), while the robot waits
            (`rr-actors demo --step`); the fault is injected when it returns.
        on_interrupt: called on the mission's thread with the mission time (seconds)
            of a Ctrl-C, before the mission unloads everything (`rr-actors demo` then
            says so); once, however many Ctrl-Cs follow.
        link: with `config.hosts == 2`: the two hosts' namespaces (this process runs in
            the station's); the robot's managers start in a process in the robot's.
        robot_observer: with `link`: the robot's host shares its tree with the
            station's observer page (`on_supervisor` opens that page).

    Attributes:
        supervisor: the managers' supervisor while the mission runs, else `None`.
        clock: the mission clock (since the mission started, without `--step`'s pauses)
            of the story's stamps, the progress line and the report.
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
    ) -> None:
        if (config.hosts == 2) != (link is not None):
            raise MissionError("a mission on two hosts needs their namespaces (and only it)")
        self.config = config
        self.link = link
        self._robot_observer = robot_observer
        self._on_supervisor = on_supervisor
        self._before_fault = before_fault
        self._on_interrupt = on_interrupt
        self._interrupted_at: float | None = None  # mission time of the Ctrl-C
        self._failed_unloads = 0
        self._leaked_pids: list[int] = []
        self.out = out
        self.bus = out / "bus"
        self.state = out / "state"
        self.supervisor: rr.Supervisor | None = None
        self._say = say
        self._progress = progress
        self._events: queue.SimpleQueue[_Event] = queue.SimpleQueue()
        self._odom = Odometry(self.bus / "odom.jsonl")
        self.clock = MissionClock(time.monotonic())
        self._held: list[tuple[str, str]] = []  # (query id, provider) the mission holds
        self._faults: Faults | None = None
        rng = random.Random(config.seed)  # noqa: S311 - jitter, not cryptography
        self._points = {
            f: config.fault_at[f] + rng.uniform(-0.02, 0.02) * min(1.0, config.fault_at[f])
            for f in config.faults
        }

    def say(self, text: str) -> None:
        """One line of the story, stamped with the mission time (`clock`)."""
        self._say(f"[{self.clock.now():6.2f} s] {text}")

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
            raise MissionInterruptedError(
                self._interrupted_at, self._failed_unloads, self._leaked_pids
            ) from None

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
        setups = managers.setups()
        two = self.link is not None
        here = tuple(m for m in MANAGERS if not two or m not in ROBOT_MANAGERS)
        specs = [
            rr.ManagerSpec(name, setup=setups[name], isolation=cfg.isolation, restart="permanent")
            for name in here
        ]
        with contextlib.ExitStack() as hosts:
            network: rr.ZenohNetwork | None = None
            robot: RobotHost | None = None
            if two:
                network, robot = self._two_hosts(hosts)
            else:
                self.say(f"starting the managers erm, cm and rm ({cfg.isolation} isolation)")
            sup = rr.Supervisor(
                specs,
                strategy="one_for_one",
                max_restarts=10,
                period=10.0,
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
                leaked = self._leaked_pids = self._leaked()
                if leaked:
                    self.say(f"{len(leaked)} process(es) were left behind: {leaked}; killed them")
        faults = self._faults
        assert faults is not None
        return build_report(
            odometry=self._odom,
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
            self._faults = Faults(
                trees,
                app,
                recovery_timeout=cfg.recovery_timeout,
                say=self.say,
                link=self.link,
                cut_s=cfg.cut_s,
            )
            if robot is not None:
                robot.on_watch = self._robot_watch
            try:
                start, arrived = self._mission(trees, app)
            except KeyboardInterrupt:
                self._interrupt()  # said before the unloading, which takes a while
                raise
            finally:
                entries = self._unload_all(trees, app)
                trees.flush_events()  # the last exits and restarts of the drive are heard
                self._faults.close()
                if robot is not None:  # before the station leaves (the robot would see it go)
                    robot.close()
        return start, arrived, entries

    def _two_hosts(self, stack: contextlib.ExitStack) -> tuple[rr.ZenohNetwork, RobotHost]:
        """Start the robot's host (erm, rm) and open the station's network; both on `stack`."""
        link = self.link
        assert link is not None
        cfg = self.config
        certs = self.out / CERTS
        self.say(
            f"two hosts: the robot ({link.robot_address}: erm, rm and their programs) and the "
            f"station ({link.station_address}: the mission and cm), mutual TLS ({certs})"
        )
        tls = rr.ZenohTLS(
            ca=certs / "ca.pem",
            cert=certs / "station.pem",
            key=certs / "station.key",
            members=list(MEMBERS),
        )
        network = rr.ZenohNetwork(
            system=SYSTEM,
            listen=[f"tls/{link.station_address}:{PORT}"],
            connect=[f"tls/{link.robot_address}:{PORT}"],
            tls=tls,
            lease=cfg.lease,
        )
        stack.callback(network.close)
        robot = RobotHost.start(
            link.exec_in(link.robot),
            RobotSettings(
                system=SYSTEM,
                certs=str(certs),
                listen=f"tls/{link.robot_address}:{PORT}",
                connect=f"tls/{link.station_address}:{PORT}",
                lease=cfg.lease,
                state=str(self.state / "robot"),
                bus=str(self.bus),
                isolation=cfg.isolation,
                log=str(self.out / ROBOT_LOG),
                observer=self._robot_observer,
            ),
            say=self.say,
        )
        stack.callback(robot.close)
        self.say(f"robot's host up (pid {robot.pid}): erm and rm started there")
        return network, robot

    def _robot_watch(self, kind: str, at: float) -> None:
        """The robot's host saw the station go (`"lost"`) or come back (`"back"`) at `at`."""
        faults = self._faults
        if faults is None:
            return
        with faults.lock:
            cut = next((r for r in faults.records if r.id == "F6"), None)
            if cut is None:
                return
            if kind == "lost" and cut.robot_saw_at is None:
                cut.robot_saw_at = at
            elif kind == "back" and cut.robot_saw_back_at is None:
                cut.robot_saw_back_at = at

    def _load(
        self,
        sup: Trees,
        app: rr.ResourceRegistrar,
        provider: str,
        server: str,
        request: dict[str, Any],
        on_status: rr.StatusCallback,
    ) -> rr.Query:
        """Load from `provider`, waiting out a restart of it; the mission holds the id."""
        query = sup.call_with_retry(
            app, provider, server, request, on_status=on_status, timeout=self.config.call_timeout
        )
        self._held.append((query.id, provider))
        return query

    def _mission(self, sup: Trees, app: rr.ResourceRegistrar) -> tuple[float, float]:
        """Load the robot and LiDAR 1, drive; return when the drive started and ended."""
        cfg = self.config
        robot = self._load(sup, app, "rm", "robot", self._robot_request(), self._robot_cb)
        self.say(
            f"robot loaded: driver pid {robot.response['driver_pid']}, "
            f"navigation pid {robot.response['navigation_pid']}"
        )
        lidar = self._load(sup, app, "cm", "lidar", self._lidar_request("lidar1"), self._lidar_cb)
        self.say(f"LiDAR 1 loaded: pid {lidar.response['pid']}")
        start = time.monotonic()
        self._goal(paused=False)
        self.say(f"driving {cfg.distance_m:g} m at {cfg.speed:g} m/s")
        arrived = self._drive(sup, app)
        self.say(f"goal reached after {self.clock.at(arrived) - self.clock.at(start):.2f} s")
        return start, arrived

    def _unload_all(self, sup: Trees, app: rr.ResourceRegistrar) -> dict[str, int]:
        """Stop the robot, unload what the mission holds, count what the catalogs keep."""
        self._goal(paused=True)
        if self._faults is not None:
            self._faults.notice_restarts()
        timeout = self.config.call_timeout
        for query_id, provider in reversed(self._held):
            try:
                # A provider restarted meanwhile still knows the id (its catalog is durable);
                # one that had committed the unload before it died no longer does.
                with contextlib.suppress(rr.UnknownQueryError):
                    retry_through_restarts(
                        sup, provider, functools.partial(app.unload, query_id), timeout=timeout
                    )
            except rr.RrError as exc:
                self._failed_unloads += 1
                self.say(f"unloading {query_id[:8]} failed: {exc}")
        self._held.clear()
        self.say("everything unloaded")
        entries = {"mission": _catalog_size(app)}
        for name in MANAGERS:
            try:
                entries[name] = int(
                    retry_through_restarts(
                        sup,
                        name,
                        functools.partial(sup.run_in, name, _catalog_size),
                        timeout=timeout,
                    )
                )
            except rr.RrError as exc:
                self.say(f"could not read the catalog of {name}: {exc}")
                entries[name] = -1
        return entries

    # -- requests, topics, callbacks ----------------------------------------------------

    def _robot_request(self) -> dict[str, Any]:
        cfg = self.config
        return {
            "robot": "jackal",
            "bus": str(self.bus),
            "watch_pid": os.getpid(),
            "driver_rate": cfg.driver_rate,
            "nav_rate": cfg.nav_rate,
            "cmd_timeout": cfg.cmd_timeout,
            "scan_timeout": cfg.scan_timeout,
        }

    def _lidar_request(self, name: str) -> dict[str, Any]:
        return {
            "name": name,
            "bus": str(self.bus),
            "watch_pid": os.getpid(),
            "rate": self.config.lidar_rate,
            "seed": self.config.seed,
        }

    def _goal(self, *, paused: bool) -> None:
        programs.publish(
            self.bus,
            "goal",
            {"distance_m": self.config.distance_m, "speed": self.config.speed, "paused": paused},
        )

    def _lidar_cb(self, query: rr.Query, update: rr.StatusUpdate) -> None:
        self._events.put(_Event("lidar", query.id, update, time.monotonic()))

    def _robot_cb(self, query: rr.Query, update: rr.StatusUpdate) -> None:
        self._events.put(_Event("robot", query.id, update, time.monotonic()))

    # -- the drive ----------------------------------------------------------------------

    def _drive(self, sup: Trees, app: rr.ResourceRegistrar) -> float:
        """Drive to the goal, injecting the faults on the way; return the arrival time."""
        cfg = self.config
        faults = self._faults
        assert faults is not None
        pending = sorted(cfg.faults, key=lambda f: self._points[f])
        active: FaultRecord | None = None
        deadline = (
            time.monotonic() + 3 * cfg.nominal_time_s + 30 + cfg.recovery_timeout * len(pending)
        )
        while True:
            try:
                event: _Event | None = self._events.get(timeout=TICK)
            except queue.Empty:
                event = None
            self._odom.read()
            if event is not None:
                self._handle(event, active, sup, app)
            if active is not None and active.id == "F6" and active.detected_at is not None:
                self._ride_out_cut(sup, app, active)
            faults.notice_restarts()
            with faults.lock:
                if active is not None and active.recovered_at is not None:
                    active = None
            if active is not None and time.monotonic() - active.injected_at > cfg.recovery_timeout:
                raise MissionError(
                    f"{active.id} was not recovered within {cfg.recovery_timeout:g} s"
                )
            if (
                active is None
                and pending
                and self._odom.x >= self._points[pending[0]] * cfg.distance_m
                and faults.ready()  # not while a manager is down for another reason
            ):
                if self._before_fault is not None:
                    deadline += self._pause_for(pending[0], faults)
                active = faults.inject(pending[0])
                if active is not None:
                    pending.pop(0)
            if self._odom.x >= cfg.distance_m and not pending and active is None:
                arrival = self._odom.arrival(cfg.distance_m)
                return arrival if arrival is not None else time.monotonic()
            if time.monotonic() > deadline:
                raise MissionError(f"the goal was not reached in time (at {self._odom.x:.2f} m)")
            now = time.monotonic()
            self._progress(
                Progress(
                    elapsed_s=self.clock.at(now),
                    distance_m=self._odom.x,
                    goal_m=cfg.distance_m,
                    moving=self._odom.moving(now),
                    status=f"{active.id}: {FAULT_WHAT[active.id]}" if active is not None else "",
                )
            )

    def _pause_for(self, fault: str, faults: Faults) -> float:
        """Stop the robot, hand the fault to `before_fault`, drive on; the seconds it took.

        The pause is left out of the mission clock: no stamp, timeline row or plot
        counts the time the class took to press Enter. It lasts from the stop order
        until the robot drives again: its coming to a halt and its start after the
        Enter belong to the pause, not to the fault that follows (which would otherwise
        count them as the robot standing still).
        """
        assert self._before_fault is not None
        paused = time.monotonic()
        self._goal(paused=True)
        try:
            self._before_fault(fault, faults.pids(fault))
            self._wait_until_moving(False)  # (long done, unless Enter came at once)
            self._goal(paused=False)
            self._wait_until_moving(True)
        finally:  # (after a Ctrl-C at the prompt the robot waits for the unloading)
            resumed = time.monotonic()
            self.clock.add_pause(paused, resumed)
        return resumed - paused

    def _wait_until_moving(self, moving: bool) -> None:
        """Wait until the odometry says the robot moves (or stands), `PAUSE_SETTLE` s at most."""
        deadline = time.monotonic() + PAUSE_SETTLE
        while True:
            self._odom.read()
            now = time.monotonic()
            if self._odom.moving(now) == moving or now >= deadline:
                return
            time.sleep(TICK)  # the odometry is a file the driver appends to: look again

    def _handle(
        self,
        event: _Event,
        active: FaultRecord | None,
        sup: Trees,
        app: rr.ResourceRegistrar,
    ) -> None:
        status = event.update.status
        self.say(
            f"{event.kind} query {event.query_id[:8]} hears {status.name} from "
            f"{event.update.source}: {event.update.message}"
        )
        if all(event.query_id != held for held, _ in self._held):
            return  # about a query the mission let go of already (F6 reloads both)
        if active is not None and active.id == "F6" and status is rr.Status.FATAL:
            if active.detected_at is None:  # the station saw the cut: its lease ran out
                active.detected_at = event.at
            return
        if event.kind == "lidar" and status is rr.Status.FATAL:
            record = active if active is not None and active.id == "F1" else None
            if record is not None:
                record.detected_at = event.at
            self._substitute_lidar(sup, app, event.query_id, record)
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

    def _substitute_lidar(
        self,
        sup: Trees,
        app: rr.ResourceRegistrar,
        dead_id: str,
        record: FaultRecord | None,
    ) -> None:
        """F1: stop the robot, release LiDAR 1, load LiDAR 2, drive on."""
        self._goal(paused=True)
        self.say("robot stopped; substituting LiDAR 2 for LiDAR 1")
        with contextlib.suppress(rr.UnknownQueryError):
            retry_through_restarts(
                sup, "cm", lambda: app.unload(dead_id), timeout=self.config.call_timeout
            )
        self._held = [(q, p) for q, p in self._held if q != dead_id]
        lidar = self._load(sup, app, "cm", "lidar", self._lidar_request("lidar2"), self._lidar_cb)
        self._goal(paused=False)
        if record is not None:
            record.recovered_at = time.monotonic()
            record.note = f"LiDAR 2 (pid {lidar.response['pid']}) replaced LiDAR 1"
        self.say(f"LiDAR 2 loaded (pid {lidar.response['pid']}); driving on")

    def _ride_out_cut(self, sup: Trees, app: rr.ResourceRegistrar, record: FaultRecord) -> None:
        """F6 on the station: the link is cut; fail fast, wait for the heal, load again.

        The station heard `FATAL` for the robot (its provider `rm` is on the far side:
        lost, rule 19) and for the LiDAR (`cm` lost the ERM's program it depends on), and
        forgot the robot's id. The robot's host stopped the robot itself. Each call made
        during the cut fails at once (`RegistrarUnavailableError`), not at its timeout;
        once the link is back the mission loads the robot and the LiDAR again, and the
        reconciliation releases, at the robot, the ids the station forgot (rule 20).
        """
        cfg = self.config
        self.say("station: lost the robot's managers (FATAL); waiting for the link")
        self._held = [(q, p) for q, p in self._held if p != "rm"]  # forgotten (rule 19)
        lidars = [q for q, p in self._held if p == "cm"]
        for query_id in lidars:  # cm is here: its LiDAR lost the ERM's program
            with contextlib.suppress(rr.UnknownQueryError):
                app.unload(query_id)
        self._held = [(q, p) for q, p in self._held if p != "cm"]
        deadline = record.injected_at + cfg.recovery_timeout
        robot: rr.Query | None = None
        while robot is None:
            began = time.monotonic()
            try:
                robot = app.call(
                    "rm", "robot", self._robot_request(), on_status=self._robot_cb,
                    timeout=max(deadline - began, 1e-3),
                )  # fmt: skip
            except (rr.RegistrarUnavailableError, rr.UnknownRegistrarError) as exc:
                failed = time.monotonic() - began
                if record.healed_at is None:
                    record.failed_calls.append(failed)
                if len(record.failed_calls) == 1 and record.healed_at is None:
                    self.say(
                        f"station: a call to rm during the cut failed after {failed * 1000:.0f} "
                        f"ms ({exc.__class__.__name__}), not at its timeout"
                    )
                if time.monotonic() >= deadline:
                    raise MissionError(
                        f"F6: the robot was not back within {cfg.recovery_timeout:g} s"
                    ) from exc
                self._faults_healed(deadline)
        self._held.append((robot.id, "rm"))
        lidar = self._load(sup, app, "cm", "lidar", self._lidar_request("lidar1"), self._lidar_cb)
        self._goal(paused=False)
        record.recovered_at = time.monotonic()
        record.note = (
            f"robot reloaded (driver pid {robot.response['driver_pid']}), LiDAR 1 reloaded "
            f"(pid {lidar.response['pid']}); {len(record.failed_calls)} call(s) failed fast "
            "during the cut"
        )
        self.say(
            f"F6 recovered: link back, robot (driver pid {robot.response['driver_pid']}) and "
            f"LiDAR (pid {lidar.response['pid']}) loaded again; the robot's host released what "
            "the station forgot; driving on"
        )

    def _faults_healed(self, deadline: float) -> None:
        """Wait for F6's heal (or a short while once healed: Zenoh reconnects by itself)."""
        faults = self._faults
        assert faults is not None
        if not faults.healed.is_set():
            faults.healed.wait(max(0.0, deadline - time.monotonic()))
        else:
            time.sleep(TICK * 5)  # the link is up; Zenoh is dialling again: ask again soon

    # -- the end ------------------------------------------------------------------------

    def _leaked(self) -> list[int]:
        """Programs of this mission still alive (from their pid files); they get killed."""
        leaked = []
        for path in sorted((self.bus / "pids").glob("*.json")):
            with contextlib.suppress(OSError, ValueError, KeyError):
                record = json.loads(path.read_text())
                if alive(record["pid"], record["start_time"]):
                    leaked.append(record["pid"])
                    with contextlib.suppress(OSError, MissionError):
                        os.close(sigkill(record["pid"], record["start_time"]))
        return leaked
