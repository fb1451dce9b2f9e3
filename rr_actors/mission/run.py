"""The thesis's fault-injected robot mission (chapter 6), on real processes and real signals.

A robot (a motor driver and a navigation process) and a LiDAR are loaded through three
managers, each an OS process under one [`Supervisor`][rr_actors.Supervisor]; the robot
drives a path while five faults hit it, each a real SIGKILL:

| fault | what is killed | what the mission does |
|---|---|---|
| F1 | the LiDAR 1 process | hears `FATAL`, stops, substitutes LiDAR 2, continues |
| F2 | the motor driver process | hears `FATAL`, waits for the robot manager's `UPDATE` |
| F3 | the external resource manager | nothing: it restarts and re-adopts its processes |
| F4 | the component manager | nothing: it restarts and restores its catalog |
| F5 | the robot manager | nothing: it restarts and restores its catalog |

At the end everything is unloaded; the mission checks that no process is left and every
catalog is empty, prints a timeline and writes `report.json` and `mission.png`.

Run it with `rr-actors demo` (or `python -m rr_actors.mission`, or
`python examples/jackal_mission.py`); `--help` lists the options.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import queue
import random
import select
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal, TextIO

import rr_actors as rr
from rr_actors._supervision.supervisor import ManagerSpec, Supervisor
from rr_actors.mission import managers, programs
from rr_actors.testing import catalog_snapshot

__all__ = [
    "FAULTS",
    "FaultResult",
    "MissionConfig",
    "MissionError",
    "MissionReport",
    "main",
    "run_mission",
]

FAULTS = ("F1", "F2", "F3", "F4", "F5")
"""The thesis's five faults, in the order the mission meets them."""

FAULT_WHAT = {
    "F1": "LiDAR 1 disconnected",
    "F2": "motor driver failed",
    "F3": "external resource manager killed",
    "F4": "component manager killed",
    "F5": "robot manager killed",
}

MANAGER_OF = {"F3": "erm", "F4": "cm", "F5": "rm"}
"""Which manager each software fault kills."""

SERVER_OF = {"erm": managers.PROGRAM_SERVER, "cm": "lidar", "rm": "robot"}

DEFAULT_FAULT_AT = {"F1": 0.15, "F2": 0.35, "F3": 0.5, "F4": 0.65, "F5": 0.8}
"""Where each fault is injected, as a fraction of the path."""

THESIS = {
    "mission_time_s": {"without_faults": 32.0, "with_faults": 43.0},
    "robot_stopped_s": {"F1": 3.0, "F2": 5.0, "F3": 0.0, "F4": 0.0, "F5": 0.0},
}
"""The thesis's figures (section 6.2), for the side-by-side comparison."""

TICK = 0.02
"""Seconds between two looks at the odometry (the progress line's refresh)."""

MOVING_GAP = 0.5
"""Seconds without an odometry sample after which the progress line says "stopped"."""


class MissionError(rr.RrError):
    """The mission could not be completed (a fault was not recovered, or it timed out)."""


@dataclasses.dataclass(frozen=True)
class MissionConfig:
    """What the mission does.

    Attributes:
        distance_m: length of the path, in metres.
        speed: driving speed, in metres per second.
        faults: which faults to inject (`"F1"` ... `"F5"`).
        fault_at: where to inject each, as a fraction of the path (0..1).
        seed: seeds the LiDAR noise and a small jitter of the injection points.
        isolation: `"process"` (each manager an OS process) or `"thread"`.
        lidar_rate: LiDAR scans per second.
        driver_rate: odometry updates per second.
        nav_rate: navigation updates per second.
        scan_timeout: seconds after which navigation treats the last scan as stale.
        cmd_timeout: seconds after which the driver's watchdog treats a command as stale.
        recovery_timeout: seconds a fault may take to be recovered before the mission fails.
        call_timeout: timeout of the mission's calls, in seconds.

    Raises:
        ConfigError: a field is invalid; the message names it.
    """

    distance_m: float = 16.0
    speed: float = 0.5
    faults: tuple[str, ...] = FAULTS
    fault_at: dict[str, float] = dataclasses.field(default_factory=lambda: dict(DEFAULT_FAULT_AT))
    seed: int = 0
    isolation: Literal["process", "thread"] = "process"
    lidar_rate: float = 20.0
    driver_rate: float = 50.0
    nav_rate: float = 20.0
    scan_timeout: float = 0.5
    cmd_timeout: float = 0.5
    recovery_timeout: float = 20.0
    call_timeout: float = 15.0

    def __post_init__(self) -> None:
        for field in ("distance_m", "speed", "lidar_rate", "driver_rate", "nav_rate"):
            value = getattr(self, field)
            if isinstance(value, bool) or not isinstance(value, int | float) or value <= 0:
                raise rr.ConfigError(f"{field} must be a positive number, got {value!r}")
        unknown = [f for f in self.faults if f not in FAULTS]
        if unknown:
            raise rr.ConfigError(f"faults: unknown fault(s) {unknown}; known: {list(FAULTS)}")
        object.__setattr__(self, "faults", tuple(f for f in FAULTS if f in self.faults))
        for fault in self.faults:
            point = self.fault_at.get(fault)
            if point is None or not 0.0 < point < 1.0:
                raise rr.ConfigError(
                    f"fault_at[{fault!r}] must be a fraction of the path in (0, 1), got {point!r}"
                )
        if self.isolation not in ("process", "thread"):
            raise rr.ConfigError(f"isolation must be 'process' or 'thread', got {self.isolation!r}")

    @classmethod
    def fast(cls, **changes: Any) -> MissionConfig:
        """A mission of a few seconds (for CI): a short path at high speed.

        Args:
            **changes: fields to set on top of the fast defaults.
        """
        base: dict[str, Any] = {
            "distance_m": 6.0,
            "speed": 2.0,
            "lidar_rate": 50.0,
            "nav_rate": 50.0,
            "fault_at": {"F1": 0.1, "F2": 0.25, "F3": 0.4, "F4": 0.55, "F5": 0.7},
        }
        base.update(changes)
        return cls(**base)

    @property
    def nominal_time_s(self) -> float:
        """How long the drive takes without faults: distance over speed, in seconds."""
        return self.distance_m / self.speed


@dataclasses.dataclass(frozen=True)
class FaultResult:
    """What happened at one fault. Times are seconds; `injected_at_s` counts from the start.

    Attributes:
        id: `"F1"` ... `"F5"`.
        what: a short description.
        injected_at_s: when the SIGKILL was sent, from the start of the drive.
        detected_after_s: from injection until the fault was seen (F1, F2: the mission
            heard `FATAL`; F3-F5: the manager's death was seen from its pidfd, the event
            the supervisor's process sentinel reports).
        recovered_after_s: from injection until it was recovered (F1: LiDAR 2 serving and
            the robot released; F2: the robot manager's `UPDATE`; F3-F5: the restarted
            manager answered from its restored catalog).
        robot_stopped_s: how long the robot stood still because of it (from odometry).
        note: what the recovery found (e.g. what the restarted ERM re-adopted).
    """

    id: str
    what: str
    injected_at_s: float
    detected_after_s: float | None
    recovered_after_s: float | None
    robot_stopped_s: float
    note: str = ""


@dataclasses.dataclass(frozen=True)
class MissionReport:
    """The outcome of a mission (written as `report.json`).

    Attributes:
        mission_time_s: from the start of the drive until the goal was reached, seconds.
        distance_m: distance the odometry measured.
        nominal_time_s: distance over speed: the drive without any stop.
        faults: one result per injected fault.
        leaked_processes: mission programs still alive after everything was unloaded.
        catalog_entries_left: catalog rows (resources and client records) left in all
            registrars after everything was unloaded.
        catalog_entries_by_registrar: the same, per registrar.
        trace: `(t, x)` odometry samples, seconds from the start of the drive and metres.
        stops: `(start, end)` of every interval the robot stood still, seconds.
    """

    mission_time_s: float
    distance_m: float
    nominal_time_s: float
    faults: tuple[FaultResult, ...]
    leaked_processes: int
    catalog_entries_left: int
    catalog_entries_by_registrar: dict[str, int]
    trace: tuple[tuple[float, float], ...]
    stops: tuple[tuple[float, float], ...]

    @property
    def ok(self) -> bool:
        """Whether every fault was recovered and nothing was left behind."""
        return (
            all(f.recovered_after_s is not None for f in self.faults)
            and self.leaked_processes == 0
            and self.catalog_entries_left == 0
        )

    def to_dict(self) -> dict[str, Any]:
        """The report as JSON-able data (`report.json`)."""
        return {
            "mission_time_s": round(self.mission_time_s, 3),
            "distance_m": round(self.distance_m, 3),
            "nominal_time_s": round(self.nominal_time_s, 3),
            "faults": [
                {
                    "id": f.id,
                    "what": f.what,
                    "injected_at_s": _round(f.injected_at_s),
                    "detected_after_s": _round(f.detected_after_s),
                    "recovered_after_s": _round(f.recovered_after_s),
                    "robot_stopped_s": _round(f.robot_stopped_s),
                    "note": f.note,
                }
                for f in self.faults
            ],
            "leaked_processes": self.leaked_processes,
            "catalog_entries_left": self.catalog_entries_left,
            "catalog_entries_by_registrar": self.catalog_entries_by_registrar,
            "thesis": THESIS,
            "stops": [[_round(a), _round(b)] for a, b in self.stops],
        }


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, 3)


# -- odometry ----------------------------------------------------------------------------


class Odometry:
    """Follows the driver's `odom.jsonl` (every sample the drivers ever published)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.samples: list[tuple[float, float, float]] = []  # (t, x, v), t monotonic
        self._offset = 0
        self._partial = b""

    @property
    def x(self) -> float:
        """The latest distance, in metres."""
        return self.samples[-1][1] if self.samples else 0.0

    def moving(self, now: float) -> bool:
        """Whether the distance grew at the latest sample, and that sample is recent."""
        if len(self.samples) < 2 or now - self.samples[-1][0] > MOVING_GAP:
            return False
        return self.samples[-1][1] > self.samples[-2][1]

    def read(self) -> None:
        """Take the samples appended since the last read."""
        try:
            with self.path.open("rb") as f:
                f.seek(self._offset)
                data = f.read()
        except FileNotFoundError:
            return
        self._offset += len(data)
        lines = (self._partial + data).split(b"\n")
        self._partial = lines.pop()
        for line in lines:
            with contextlib.suppress(ValueError, KeyError):
                sample = json.loads(line)
                self.samples.append((float(sample["t"]), float(sample["x"]), float(sample["v"])))

    def stops(self, start: float, end: float) -> list[tuple[float, float]]:
        """Intervals within `[start, end]` in which the distance did not grow (monotonic s).

        Between two consecutive samples the robot stood still if the distance did not
        grow. A driver that died publishes nothing, and its successor starts from the last
        distance, so the time without a driver counts as standing still too.
        """
        stops: list[tuple[float, float]] = []
        previous: tuple[float, float] | None = None
        for t, x, _ in self.samples:
            if t > end:
                break
            if previous is not None and t > start and x - previous[1] <= 1e-9:
                begin = max(previous[0], start)
                if stops and stops[-1][1] >= begin:
                    stops[-1] = (stops[-1][0], t)
                else:
                    stops.append((begin, t))
            previous = (t, x)
        return stops


# -- the mission -------------------------------------------------------------------------


@dataclasses.dataclass
class _Fault:
    id: str
    injected_at: float
    detected_at: float | None = None
    recovered_at: float | None = None
    early_update_at: float | None = None  # F2: an UPDATE that overtook its FATAL
    note: str = ""


@dataclasses.dataclass(frozen=True)
class _Event:
    kind: Literal["lidar", "robot"]
    query_id: str
    update: rr.StatusUpdate
    at: float


def _catalog_size(registrar: rr.ResourceRegistrar) -> int:
    """Rows in a registrar's catalog (run inside the manager, via `Supervisor.run_in`)."""
    view = catalog_snapshot(registrar)
    return len(view.resources) + len(view.clients)


def _served_names(registrar: rr.ResourceRegistrar) -> list[str]:
    """Names of the programs the ERM serves (run inside the ERM)."""
    queries = registrar.server_queries(managers.PROGRAM_SERVER)
    return sorted({q.response["name"] for q in queries})


def _alive(pid: int, created: int | None) -> bool:
    return created is not None and programs.start_time(pid) == created


def _sigkill(pid: int, created: int | None = None) -> int:
    """SIGKILL `pid` through a pidfd (checking its creation time); return the pidfd."""
    pidfd = os.pidfd_open(pid)
    if created is not None and programs.start_time(pid) != created:
        os.close(pidfd)
        raise MissionError(f"process {pid} is not the one the mission started")
    signal.pidfd_send_signal(pidfd, signal.SIGKILL)
    return pidfd


class Mission:
    """One run of the mission: the action of thesis figure 6.2, with faults injected.

    Args:
        config: what to do.
        out: directory for `report.json`, `mission.png`, the topics (`bus/`) and the
            managers' catalogs (`state/`); emptied of those at the start.
        say: called with each line of the story (from the mission's thread).
        progress: where the live progress line goes (a terminal), or `None`.
    """

    def __init__(
        self,
        config: MissionConfig,
        out: Path,
        *,
        say: Callable[[str], None] = lambda _: None,
        progress: TextIO | None = None,
    ) -> None:
        self.config = config
        self.out = out
        self.bus = out / "bus"
        self.state = out / "state"
        self._say = say
        self._progress = progress
        self._events: queue.SimpleQueue[_Event] = queue.SimpleQueue()
        self._faults: list[_Fault] = []
        self._lock = threading.Lock()
        self._odom = Odometry(self.bus / "odom.jsonl")
        self._t0 = time.monotonic()
        self._line = ""
        rng = random.Random(config.seed)  # noqa: S311 - jitter, not cryptography
        self._points = {
            f: config.fault_at[f] + rng.uniform(-0.02, 0.02) * min(1.0, config.fault_at[f])
            for f in config.faults
        }

    # -- output -----------------------------------------------------------------------

    def say(self, text: str) -> None:
        """One line of the story, stamped with the mission time."""
        line = f"[{time.monotonic() - self._t0:6.2f} s] {text}"
        if self._progress is not None and self._line:
            self._progress.write("\r" + " " * len(self._line) + "\r")
        self._say(line)
        if self._progress is not None and self._line:
            self._progress.write(self._line)
            self._progress.flush()

    def _show_progress(self, status: str) -> None:
        if self._progress is None:
            return
        x, goal = self._odom.x, self.config.distance_m
        filled = min(20, round(20 * x / goal))
        bar = "#" * filled + "." * (20 - filled)
        line = (
            f"\r{time.monotonic() - self._t0:6.2f} s  [{bar}] {x:6.2f}/{goal:.2f} m  "
            f"{'moving ' if self._odom.moving(time.monotonic()) else 'stopped'}  {status}"
        )
        pad = max(0, len(self._line) - len(line))
        self._line = line
        self._progress.write(line + " " * pad)
        self._progress.flush()

    # -- the run ----------------------------------------------------------------------

    def run(self) -> MissionReport:
        """Run the mission to the end, unload everything and report.

        Raises:
            MissionError: the mission could not be completed; everything was unloaded
                and stopped all the same.
        """
        for sub in (self.bus, self.state):
            shutil.rmtree(sub, ignore_errors=True)
            sub.mkdir(parents=True)
        cfg = self.config
        setups = managers.setups()
        specs = [
            ManagerSpec(name, setup=setups[name], isolation=cfg.isolation, restart="permanent")
            for name in ("erm", "cm", "rm")
        ]
        self.say(f"starting the managers erm, cm and rm ({cfg.isolation} isolation)")
        sup = Supervisor(
            specs, strategy="one_for_one", max_restarts=10, period=10.0, state_dir=self.state
        )
        entries: dict[str, int] = {}
        try:
            with sup:
                app = sup.registrar(
                    rr.RegistrarConfig(name="mission", call_timeout=cfg.call_timeout)
                )
                held: list[str] = []
                try:
                    start, arrived = self._mission(sup, app, held)
                finally:
                    entries = self._unload_all(sup, app, held)
        except MissionError:
            raise
        except rr.RrError as exc:
            raise MissionError(f"the mission failed: {exc}") from exc
        finally:
            self._finish_line()
            leaked = self._leaked()
            if leaked:
                self.say(f"{len(leaked)} process(es) were left behind: {leaked}; killed them")
        return self._report(start, arrived, leaked, entries)

    def _mission(
        self, sup: Supervisor, app: rr.ResourceRegistrar, held: list[str]
    ) -> tuple[float, float]:
        """Load the robot and LiDAR 1, drive; return when the drive started and ended."""
        cfg = self.config
        robot = app.call("rm", "robot", self._robot_request(), on_status=self._robot_cb)
        held.append(robot.id)
        self.say(
            f"robot loaded: driver pid {robot.response['driver_pid']}, "
            f"navigation pid {robot.response['navigation_pid']}"
        )
        lidar = app.call("cm", "lidar", self._lidar_request("lidar1"), on_status=self._lidar_cb)
        held.append(lidar.id)
        self.say(f"LiDAR 1 loaded: pid {lidar.response['pid']}")
        start = time.monotonic()
        self._goal(paused=False)
        self.say(f"driving {cfg.distance_m:g} m at {cfg.speed:g} m/s")
        arrived = self._drive(sup, app, held)
        self._finish_line()
        self.say(f"goal reached after {arrived - start:.2f} s")
        return start, arrived

    def _unload_all(
        self, sup: Supervisor, app: rr.ResourceRegistrar, held: list[str]
    ) -> dict[str, int]:
        """Stop the robot, unload what the mission holds, count what the catalogs keep."""
        self._goal(paused=True)
        for query_id in reversed(held):
            try:
                app.unload(query_id)
            except rr.RrError as exc:
                self.say(f"unloading {query_id[:8]} failed: {exc}")
        self.say("everything unloaded")
        entries = {"mission": _catalog_size(app)}
        for name in ("erm", "cm", "rm"):
            try:
                entries[name] = int(sup.run_in(name, _catalog_size))
            except rr.RrError as exc:
                self.say(f"could not read the catalog of {name}: {exc}")
                entries[name] = -1
        return entries

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

    def _drive(self, sup: Supervisor, app: rr.ResourceRegistrar, held: list[str]) -> float:
        """Drive to the goal, injecting the faults on the way; return the arrival time."""
        cfg = self.config
        pending = sorted(cfg.faults, key=lambda f: self._points[f])
        active: _Fault | None = None
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
                self._handle(event, active, app, held)
            with self._lock:
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
            ):
                active = self._inject(pending.pop(0), sup, app, held)
            if self._odom.x >= cfg.distance_m and not pending and active is None:
                return self._arrival_time()
            if time.monotonic() > deadline:
                raise MissionError(f"the goal was not reached in time (at {self._odom.x:.2f} m)")
            self._show_progress(
                f"{active.id}: {FAULT_WHAT[active.id]}" if active is not None else ""
            )

    def _arrival_time(self) -> float:
        for t, x, _ in self._odom.samples:
            if x >= self.config.distance_m:
                return t
        return time.monotonic()

    def _inject(
        self, fault: str, sup: Supervisor, app: rr.ResourceRegistrar, held: list[str]
    ) -> _Fault:
        """Inject `fault` for real: SIGKILL the LiDAR, the driver or a manager."""
        if fault in ("F1", "F2"):
            robot_q = next(q for q in app.client_queries() if q.server == "robot")
            lidar_q = next(q for q in app.client_queries() if q.server == "lidar")
            if fault == "F1":
                pid, created = lidar_q.response["pid"], lidar_q.response["start_time"]
            else:
                pid, created = robot_q.response["driver_pid"], robot_q.response["driver_start_time"]
            record = _Fault(fault, time.monotonic())
            with self._lock:
                self._faults.append(record)
            os.close(_sigkill(pid, created))
            record.injected_at = time.monotonic()
            self.say(f"{fault} injected: {FAULT_WHAT[fault]} (SIGKILL pid {pid})")
            return record
        name = MANAGER_OF[fault]
        info = sup.child(name)
        record = _Fault(fault, time.monotonic())
        with self._lock:
            self._faults.append(record)
        if info.pid is not None:
            pidfd = _sigkill(info.pid)
            record.injected_at = time.monotonic()
            self.say(f"{fault} injected: {FAULT_WHAT[fault]} (SIGKILL pid {info.pid})")
        else:  # a thread manager: make its registrar actor die
            from rr_actors.testing import crash  # noqa: PLC0415

            pidfd = None
            record.injected_at = time.monotonic()
            crash(sup.run_in(name, lambda registrar: registrar))
            self.say(f"{fault} injected: {FAULT_WHAT[fault]} (its registrar crashed)")
        threading.Thread(
            target=self._await_manager,
            args=(record, name, pidfd, sup, app, held),
            name=f"mission-{fault}",
            daemon=True,
        ).start()
        return record

    def _await_manager(
        self,
        record: _Fault,
        name: str,
        pidfd: int | None,
        sup: Supervisor,
        app: rr.ResourceRegistrar,
        held: list[str],
    ) -> None:
        """F3-F5: see the manager die, wait for its restart, check its restored catalog."""
        try:
            if pidfd is not None:
                select.select([pidfd], [], [], self.config.recovery_timeout)
                os.close(pidfd)
            detected = time.monotonic()
            with self._lock:
                record.detected_at = detected
            sup.wait_restarted(name, timeout=self.config.recovery_timeout)
            mine = app.fetch_queries(name, SERVER_OF[name])
            if name == "erm":
                note = "re-adopted " + ", ".join(sup.run_in(name, _served_names))
            else:
                restored = sorted({q.id[:8] for q in mine if q.id in held})
                note = f"restored the mission's queries {', '.join(restored)}"
            with self._lock:
                record.note = note
                record.recovered_at = time.monotonic()
            self.say(f"{record.id} recovered: {name} restarted and {note}")
        except rr.RrError as exc:
            self.say(f"{record.id}: {name} did not come back: {exc}")

    def _handle(
        self, event: _Event, active: _Fault | None, app: rr.ResourceRegistrar, held: list[str]
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
            self._substitute_lidar(app, held, event.query_id, record)
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
        self, app: rr.ResourceRegistrar, held: list[str], dead_id: str, record: _Fault | None
    ) -> None:
        """F1: stop the robot, release LiDAR 1, load LiDAR 2, drive on."""
        self._goal(paused=True)
        self.say("robot stopped; substituting LiDAR 2 for LiDAR 1")
        with contextlib.suppress(rr.UnknownQueryError):
            app.unload(dead_id)
        if dead_id in held:
            held.remove(dead_id)
        lidar = app.call("cm", "lidar", self._lidar_request("lidar2"), on_status=self._lidar_cb)
        held.append(lidar.id)
        self._goal(paused=False)
        if record is not None:
            record.recovered_at = time.monotonic()
            record.note = f"LiDAR 2 (pid {lidar.response['pid']}) replaced LiDAR 1"
        self.say(f"LiDAR 2 loaded (pid {lidar.response['pid']}); driving on")

    # -- the end ----------------------------------------------------------------------

    def _finish_line(self) -> None:
        """Clear the progress line for good."""
        if self._progress is not None and self._line:
            self._progress.write("\r" + " " * len(self._line) + "\r")
            self._progress.flush()
            self._line = ""

    def _leaked(self) -> list[int]:
        """Programs of this mission still alive (from their pid files); they get killed."""
        leaked = []
        for path in sorted((self.bus / "pids").glob("*.json")):
            with contextlib.suppress(OSError, ValueError, KeyError):
                record = json.loads(path.read_text())
                if _alive(record["pid"], record["start_time"]):
                    leaked.append(record["pid"])
                    with contextlib.suppress(OSError, MissionError):
                        os.close(_sigkill(record["pid"], record["start_time"]))
        return leaked

    def _report(
        self, start: float, arrived: float, leaked: list[int], entries: dict[str, int]
    ) -> MissionReport:
        self._odom.read()
        stops = self._odom.stops(start, arrived)
        results = []
        for fault in self._faults:
            end = fault.recovered_at if fault.recovered_at is not None else arrived
            stopped = sum(
                (
                    max(0.0, b - max(a, fault.injected_at))
                    for a, b in stops
                    if b > fault.injected_at and a <= end
                ),
                0.0,
            )
            results.append(
                FaultResult(
                    id=fault.id,
                    what=FAULT_WHAT[fault.id],
                    injected_at_s=fault.injected_at - start,
                    detected_after_s=None
                    if fault.detected_at is None
                    else max(0.0, fault.detected_at - fault.injected_at),
                    recovered_after_s=None
                    if fault.recovered_at is None
                    else fault.recovered_at - fault.injected_at,
                    robot_stopped_s=stopped,
                    note=fault.note,
                )
            )
        trace = tuple(
            (t - start, x) for t, x, _ in self._odom.samples if start <= t <= arrived + 0.5
        )
        return MissionReport(
            mission_time_s=arrived - start,
            distance_m=self._odom.x,
            nominal_time_s=self.config.nominal_time_s,
            faults=tuple(results),
            leaked_processes=len(leaked),
            catalog_entries_left=sum(max(0, n) for n in entries.values())
            + sum(1 for n in entries.values() if n < 0),
            catalog_entries_by_registrar=entries,
            trace=trace,
            stops=tuple((a - start, b - start) for a, b in stops),
        )


def run_mission(
    config: MissionConfig,
    out: str | os.PathLike[str],
    *,
    say: Callable[[str], None] = lambda _: None,
    progress: TextIO | None = None,
) -> MissionReport:
    """Run the mission and write `report.json` (and `mission.png` if matplotlib is there).

    Args:
        config: what to do.
        out: output directory (created).
        say: receives each line of the story, from the mission's thread.
        progress: a terminal for the live progress line, or `None`.

    Returns:
        The report.

    Raises:
        MissionError: the mission could not be completed (it still cleaned up).
    """
    path = Path(out)
    path.mkdir(parents=True, exist_ok=True)
    report = Mission(config, path, say=say, progress=progress).run()
    (path / "report.json").write_text(json.dumps(report.to_dict(), indent=2) + "\n")
    with contextlib.suppress(ImportError):
        from rr_actors.mission.plot import plot  # noqa: PLC0415

        plot(report, path / "mission.png")
    return report


def timeline(report: MissionReport) -> str:
    """The report as a table: one row per fault, then the totals."""
    rows = [
        ("fault", "what", "injected at", "detected after", "recovered after", "robot stopped"),
    ]

    def s(value: float | None) -> str:
        return "-" if value is None else f"{value:.3f} s"

    rows.extend(
        (
            f.id,
            f.what,
            s(f.injected_at_s),
            s(f.detected_after_s),
            s(f.recovered_after_s),
            s(f.robot_stopped_s),
        )
        for f in report.faults
    )
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = [
        "  ".join(
            c.ljust(w) if i < 2 else c.rjust(w)
            for i, (c, w) in enumerate(zip(r, widths, strict=True))
        )
        for r in rows
    ]
    lines.insert(1, "  ".join("-" * w for w in widths))
    lines.append("")
    lines.append(
        f"mission time {report.mission_time_s:.2f} s (no stop: {report.nominal_time_s:.2f} s), "
        f"distance {report.distance_m:.2f} m"
    )
    lines.append(
        f"leaked processes: {report.leaked_processes}; catalog entries left: "
        f"{report.catalog_entries_left}"
    )
    return "\n".join(lines)


# -- the command line --------------------------------------------------------------------


DESCRIPTION = (
    "The TeMoto thesis's fault-injected robot mission (chapter 6), on real processes: a "
    "robot drives a path while its LiDAR, its motor driver and each of its three managers "
    "are killed, and recovers from every fault."
)


def parser() -> argparse.ArgumentParser:
    """The `rr-actors demo` command line."""
    p = argparse.ArgumentParser(prog="rr-actors demo", description=DESCRIPTION)
    add_arguments(p)
    return p


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Add the demo's options to `p` (shared by `rr-actors demo` and this module's `main`)."""
    p.add_argument("--fast", action="store_true", help="a run of a few seconds (for CI)")
    faults = p.add_mutually_exclusive_group()
    faults.add_argument("--no-faults", action="store_true", help="drive without any fault")
    faults.add_argument(
        "--faults", default=None, help="comma-separated faults to inject (default F1,F2,F3,F4,F5)"
    )
    p.add_argument("--fault-at", default=None, metavar="F1=0.2,...", help="where (path fraction)")
    p.add_argument("--speed", type=float, default=None, help="m/s (default 0.5, fast 2.0)")
    p.add_argument("--distance", type=float, default=None, help="m (default 16, fast 6)")
    p.add_argument("--seed", type=int, default=0, help="seed of the LiDAR noise and jitter")
    p.add_argument("--out", default="rr-actors-demo", help="output directory")
    p.add_argument(
        "--isolation", choices=("process", "thread"), default="process", help=argparse.SUPPRESS
    )
    p.add_argument("--quiet", action="store_true", help="print only the timeline")


def config_from_args(args: argparse.Namespace) -> MissionConfig:
    """Build the `MissionConfig` the command line asks for.

    Raises:
        ConfigError: an option is invalid.
    """
    changes: dict[str, Any] = {"seed": args.seed, "isolation": args.isolation}
    if args.no_faults:
        changes["faults"] = ()
    elif args.faults:
        changes["faults"] = tuple(f.strip().upper() for f in args.faults.split(",") if f.strip())
    if args.speed is not None:
        changes["speed"] = args.speed
    if args.distance is not None:
        changes["distance_m"] = args.distance
    base = MissionConfig.fast() if args.fast else MissionConfig()
    if args.fault_at:
        points = dict(base.fault_at)
        for item in args.fault_at.split(","):
            key, _, value = item.partition("=")
            try:
                points[key.strip().upper()] = float(value)
            except ValueError:
                raise rr.ConfigError(f"--fault-at: {item!r} is not FAULT=FRACTION") from None
        changes["fault_at"] = points
    return dataclasses.replace(base, **changes)


def main(argv: Sequence[str] | None = None) -> int:
    """`rr-actors demo`: run the mission, print the timeline, write the report.

    Returns:
        0 when the mission completed, every fault was recovered and nothing was left
        behind; 1 otherwise; 2 for a bad command line.
    """
    return run(parser().parse_args(argv))


def run(args: argparse.Namespace) -> int:
    """Run the mission the parsed command line `args` asks for; returns the exit code."""
    try:
        config = config_from_args(args)
    except rr.ConfigError as exc:
        sys.stderr.write(f"rr-actors demo: {exc}\n")
        return 2
    out = Path(args.out)

    def say(line: str) -> None:
        if not args.quiet:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()

    progress = sys.stdout if sys.stdout.isatty() and not args.quiet else None
    try:
        report = run_mission(config, out, say=say, progress=progress)
    except MissionError as exc:
        sys.stderr.write(f"rr-actors demo: {exc}\n")
        return 1
    sys.stdout.write("\n" + timeline(report) + "\n\n")
    sys.stdout.write(f"report: {out / 'report.json'}\n")
    if (out / "mission.png").exists():
        sys.stdout.write(f"plot:   {out / 'mission.png'}\n")
    else:
        sys.stdout.write(
            "plot:   not drawn: matplotlib is not installed "
            "(pip install 'rr-actors[demo]' for mission.png)\n"
        )
    return 0 if report.ok else 1
