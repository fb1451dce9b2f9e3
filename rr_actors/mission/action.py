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
    MANAGERS,
    MissionConfig,
    MissionError,
    MissionInterruptedError,
)
from rr_actors.mission.faults import Faults, alive, retry_through_restarts, sigkill
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
    ) -> None:
        self.config = config
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
        specs = [
            rr.ManagerSpec(name, setup=setups[name], isolation=cfg.isolation, restart="permanent")
            for name in MANAGERS
        ]
        self.say(f"starting the managers erm, cm and rm ({cfg.isolation} isolation)")
        sup = rr.Supervisor(
            specs, strategy="one_for_one", max_restarts=10, period=10.0, state_dir=self.state
        )
        entries: dict[str, int] = {}
        if self._on_supervisor is not None:
            try:
                self._on_supervisor(sup)  # before the start: an observer sees it start
            except BaseException:
                sup.stop()  # (closes what it opened on it)
                raise
        try:
            with sup:
                self.supervisor = sup
                app = sup.registrar(
                    rr.RegistrarConfig(name="mission", call_timeout=cfg.call_timeout)
                )
                self._faults = Faults(sup, app, recovery_timeout=cfg.recovery_timeout, say=self.say)
                try:
                    start, arrived = self._mission(sup, app)
                except KeyboardInterrupt:
                    self._interrupt()  # said before the unloading, which takes a while
                    raise
                finally:
                    entries = self._unload_all(sup, app)
                    sup.flush_events()  # the last exits and restarts of the drive are heard
                    self._faults.close()
        except MissionError:
            raise
        except rr.RrError as exc:
            raise MissionError(f"the mission failed: {exc}") from exc
        finally:
            self.supervisor = None
            leaked = self._leaked_pids = self._leaked()
            if leaked:
                self.say(f"{len(leaked)} process(es) were left behind: {leaked}; killed them")
        faults = self._faults
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
        )

    def _load(
        self,
        sup: rr.Supervisor,
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

    def _mission(self, sup: rr.Supervisor, app: rr.ResourceRegistrar) -> tuple[float, float]:
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

    def _unload_all(self, sup: rr.Supervisor, app: rr.ResourceRegistrar) -> dict[str, int]:
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

    def _drive(self, sup: rr.Supervisor, app: rr.ResourceRegistrar) -> float:
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
        sup: rr.Supervisor,
        app: rr.ResourceRegistrar,
    ) -> None:
        status = event.update.status
        self.say(
            f"{event.kind} query {event.query_id[:8]} hears {status.name} from "
            f"{event.update.source}: {event.update.message}"
        )
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
        sup: rr.Supervisor,
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
