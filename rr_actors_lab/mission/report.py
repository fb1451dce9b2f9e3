"""Timing and the report: the odometry log, what happened at each fault, and the timeline.

    odom.jsonl ──► Odometry (samples, stops) ─┐
    FaultRecord (one per injected fault) ─────┼─► build_report() ─► MissionReport ─► report.json
    UnplannedRestart (restarts no fault made) ┘                          │
                                                                         └─► timeline_rows()

Times are `time.monotonic()` (system-wide on Linux, as the programs' `odom.jsonl`) until
the report, which counts on the *mission clock* (`MissionClock`: seconds since the start,
without `--step`'s pauses). The *mission time* (`MissionReport.mission_time_s`) is the
drive's duration on it, as the thesis counts it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

from rr_actors_lab.mission.config import FAULT_WHAT

__all__ = [
    "MOVING_GAP",
    "THESIS",
    "FaultRecord",
    "FaultResult",
    "MissionClock",
    "MissionReport",
    "Odometry",
    "TimelineRow",
    "UnplannedExit",
    "UnplannedRestart",
    "build_report",
    "timeline_rows",
]

THESIS = {
    "mission_time_s": {"without_faults": 32.0, "with_faults": 43.0},
    "robot_stopped_s": {"F1": 3.0, "F2": 5.0, "F3": 0.0, "F4": 0.0, "F5": 0.0},
}
"""The thesis's figures (section 6.2), for the side-by-side comparison."""

MOVING_GAP = 0.5
"""Seconds without an odometry sample after which the robot counts as stopped."""


class MissionClock:
    """Mission time: seconds since `start` (monotonic seconds), without `--step`'s pauses; a time
    inside a pause reads as the pause's start."""

    def __init__(self, start: float) -> None:
        self.start = start
        self.pauses: list[tuple[float, float]] = []  # (begin, end), monotonic, in order

    def add_pause(self, begin: float, end: float) -> None:
        """Leave `[begin, end]` (monotonic seconds) out of mission time."""
        self.pauses.append((begin, end))

    @property
    def paused_s(self) -> float:
        """The seconds left out, all pauses together."""
        return sum(end - begin for begin, end in self.pauses)

    def at(self, t: float) -> float:
        """The mission time of monotonic time `t`."""
        left_out = sum(max(0.0, min(end, t) - begin) for begin, end in self.pauses if begin < t)
        return t - self.start - left_out

    def now(self) -> float:
        """The mission time now."""
        return self.at(time.monotonic())


@dataclasses.dataclass(frozen=True)
class FaultResult:
    """What happened at one fault. Times are seconds; `injected_at_s` is mission time.

    Attributes:
        id: `"F1"` ... `"F5"`.
        what: a short description.
        injected_at_s: when the SIGKILL was sent (mission time).
        detected_after_s: from injection until the fault was seen (F1, F2: `FATAL` heard;
            F3-F5: the manager's death seen from its pidfd).
        recovered_after_s: from injection until it was recovered (F1: LiDAR 2 serving;
            F2: the robot manager's `UPDATE`; F3-F5: the restarted manager answered).
        robot_stopped_s: how long the robot stood still because of it (from odometry).
        note: what the recovery found (e.g. what the restarted ERM re-adopted).
        host: where it struck (`"robot"`, `"station"`, `"both"` for F6; one host: "").
        details: F6's figures, seconds after the cut (see `MissionReport.to_dict`).
    """

    id: str
    what: str
    injected_at_s: float
    detected_after_s: float | None
    recovered_after_s: float | None
    robot_stopped_s: float
    note: str = ""
    host: str = ""
    details: dict[str, Any] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class UnplannedRestart:
    """A manager exit that no injected fault caused (killed by hand, say), from the
    supervisor's `ChildExited` and `ChildRestarted`.

    Attributes:
        manager: the manager's name.
        seen_at_s: when the supervisor saw it exit (mission time).
        pid: the process that exited.
        restarted_after_s: how long its restart took, or `None` if it had not come back.
    """

    manager: str
    seen_at_s: float
    pid: int | None
    restarted_after_s: float | None = None


@dataclasses.dataclass
class UnplannedExit:
    """What the mission records of an exit no fault caused, as the events arrive.

    Attributes:
        manager: the manager's name.
        seen_at: when the supervisor saw it exit (monotonic seconds).
        pid: the process that exited.
        restart_s: how long its restart took, once it came back.
    """

    manager: str
    seen_at: float
    pid: int | None
    restart_s: float | None = None


@dataclasses.dataclass(frozen=True)
class MissionReport:
    """The outcome of a mission (written as `report.json`); every time is mission time.

    Attributes:
        mission_time_s: from the start of the drive until the goal, seconds (as the thesis
            counts it; printed at the end).
        distance_m: distance the odometry measured.
        nominal_time_s: distance over speed: the drive without any stop.
        faults: one result per injected fault.
        leaked_processes: mission programs still alive after everything was unloaded.
        catalog_entries_left: catalog rows left in all registrars after the unloading.
        catalog_entries_by_registrar: the same, per registrar (-1: it could not be read).
        trace: `(t, x)` odometry samples, seconds and metres.
        stops: `(start, end)` of every interval the robot stood still.
        unplanned_restarts: manager restarts that no injected fault caused.
        drive_started_s: when the drive started (it ended at `+ mission_time_s`).
        pauses_s: when the mission paused for Enter (`--step`).
        paused_s: how long those pauses took together (left out of every time).
        hosts: across two hosts, each host's figures (managers, faults, restarts, F6 as it
            saw it); empty on one host.
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
    unplanned_restarts: tuple[UnplannedRestart, ...] = ()
    drive_started_s: float = 0.0
    pauses_s: tuple[float, ...] = ()
    paused_s: float = 0.0
    hosts: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)

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
            "drive_started_at_s": round(self.drive_started_s, 3),
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
                    **({"host": f.host} if f.host else {}),
                    **({"details": f.details} if f.details else {}),
                }
                for f in self.faults
            ],
            "unplanned_restarts": [
                {
                    "manager": r.manager,
                    "seen_at_s": _round(r.seen_at_s),
                    "pid": r.pid,
                    "restarted_after_s": _round(r.restarted_after_s),
                }
                for r in self.unplanned_restarts
            ],
            "leaked_processes": self.leaked_processes,
            "catalog_entries_left": self.catalog_entries_left,
            "catalog_entries_by_registrar": self.catalog_entries_by_registrar,
            "thesis": THESIS,
            "stops": [[_round(a), _round(b)] for a, b in self.stops],
            "paused_for_enter_s": round(self.paused_s, 3),
            "pauses_at_s": [round(t, 3) for t in self.pauses_s],
            **({"hosts": self.hosts} if self.hosts else {}),
        }


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, 3)


# -- the timeline --------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TimelineRow:
    """One row of the timeline table. Times are seconds; `None` shows as "-".

    Attributes:
        label: the fault's id (`"F1"` ...), or `"-"` for something no fault caused; across
            two hosts followed by the host (`"F4 station"`, `"F6 both"`).
        what: what happened, in a few words.
        at_s: when it was injected (or noticed), mission time.
        detected_after_s: from `at_s` until it was detected.
        recovered_after_s: from `at_s` until it was recovered.
        robot_stopped_s: how long the robot stood still because of it.
    """

    label: str
    what: str
    at_s: float
    detected_after_s: float | None
    recovered_after_s: float | None
    robot_stopped_s: float | None


SHORT_WHAT = {
    "F1": "LiDAR 1 disconnected",
    "F2": "motor driver failed",
    "F3": "manager erm killed",
    "F4": "manager cm killed",
    "F5": "manager rm killed",
    "F6": "WiFi cut",
}
"""Each fault in at most 20 columns, for the timeline (the report keeps `FAULT_WHAT`)."""

HOST_SHORT_WHAT = {
    "F1": "LiDAR 1 lost",
    "F2": "driver failed",
    "F3": "erm killed",
    "F4": "cm killed",
    "F5": "rm killed",
    "F6": "WiFi cut",
}
"""Shorter still across two hosts, where the fault's label names its host (`F4 station`)."""


def timeline_rows(report: MissionReport) -> list[TimelineRow]:
    """Turn what happened into the timeline's rows, in time order: every injected fault and
    every exit no fault caused (the one place that decides what the timeline shows)."""
    hosts = bool(report.hosts)  # two hosts: the label names where (and `what` is shorter)
    where = {m: h for h, figures in report.hosts.items() for m in figures["managers"]}
    rows = [
        TimelineRow(
            f"{f.id} {f.host}" if hosts else f.id,
            (HOST_SHORT_WHAT if hosts else SHORT_WHAT).get(f.id, f.what),
            f.injected_at_s,
            f.detected_after_s,
            f.recovered_after_s,
            f.robot_stopped_s,
        )
        for f in report.faults
    ]
    rows.extend(
        TimelineRow(
            f"- {where.get(r.manager, '')}".rstrip(),
            f"{r.manager} exited, no fault",
            r.seen_at_s,
            None,
            r.restarted_after_s,
            None,
        )
        for r in report.unplanned_restarts
    )
    return sorted(rows, key=lambda row: row.at_s)


# -- odometry ------------------------------------------------------------------------------


class Odometry:
    """Follows the driver's `odom.jsonl` (every sample the drivers ever published).

    Args:
        path: the log file; it may not exist yet.
    """

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

    def last_standing(self) -> float | None:
        """When the robot was last seen standing (monotonic seconds: distance not grown), if
        ever."""
        for previous, sample in zip(self.samples[-2::-1], self.samples[:0:-1], strict=True):
            if sample[1] - previous[1] <= 1e-9:
                return sample[0]
        return None

    def arrival(self, distance_m: float) -> float | None:
        """When the odometry first reached `distance_m` (monotonic seconds), if it did."""
        for t, x, _ in self.samples:
            if x >= distance_m:
                return t
        return None

    def stops(self, start: float, end: float) -> list[tuple[float, float]]:
        """Intervals within `[start, end]` (monotonic s) in which the distance did not grow (time
        without a driver counts as standing)."""
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


# -- building the report -------------------------------------------------------------------


@dataclasses.dataclass
class FaultRecord:
    """One injected fault while the mission runs (monotonic seconds; set by several threads).

    Attributes:
        id: `"F1"` ... `"F5"`.
        injected_at: when the SIGKILL was sent.
        detected_at: when the fault was seen, once it was.
        recovered_at: when it was recovered, once it was.
        early_update_at: F2 only: an `UPDATE` that overtook its `FATAL`.
        note: what the recovery found.
        host: where it struck (two hosts), else "".
        healed_at: F6: when the link was up again.
        robot_saw_at: F6: when the robot's host saw the station gone.
        robot_saw_back_at: F6: when it saw the station back.
        failed_calls: F6: how long each call that failed during the cut took, seconds.
    """

    id: str
    injected_at: float
    detected_at: float | None = None
    recovered_at: float | None = None
    early_update_at: float | None = None
    note: str = ""
    host: str = ""
    healed_at: float | None = None
    robot_saw_at: float | None = None
    robot_saw_back_at: float | None = None
    failed_calls: list[float] = dataclasses.field(default_factory=list)


def build_report(
    *,
    odometry: Odometry,
    clock: MissionClock,
    faults: list[FaultRecord],
    unplanned: list[UnplannedExit],
    start: float,
    arrived: float,
    nominal_time_s: float,
    leaked: list[int],
    entries: dict[str, int],
    host_of: dict[str, str] | None = None,
) -> MissionReport:
    """Turn the records of a run into its report, on the mission clock.

    Args:
        odometry: the run's odometry (read once more here).
        clock: the mission clock (its start, its pauses).
        faults: the injected faults.
        unplanned: each manager exit no fault caused.
        start: when the drive started (monotonic seconds).
        arrived: when the goal was reached (monotonic seconds).
        nominal_time_s: the drive's length without any stop, seconds.
        leaked: pids of programs that were still alive at the end.
        entries: catalog rows left per registrar (-1: it could not be read).
        host_of: across two hosts, the host of each manager and fault (`HOST_OF`).
    """
    odometry.read()
    at = clock.at
    # A stop during a pause lasts nothing on the mission clock: it is not a stop.
    stops = [(at(a), at(b)) for a, b in odometry.stops(start, arrived) if at(b) - at(a) > 1e-9]
    results = []
    for fault in faults:
        injected = at(fault.injected_at)
        end = at(fault.recovered_at if fault.recovered_at is not None else arrived)
        stopped = sum(
            (max(0.0, b - max(a, injected)) for a, b in stops if b > injected and a <= end),
            0.0,
        )
        results.append(
            FaultResult(
                id=fault.id,
                what=FAULT_WHAT[fault.id],
                injected_at_s=injected,
                detected_after_s=None
                if fault.detected_at is None
                else max(0.0, at(fault.detected_at) - injected),
                recovered_after_s=None
                if fault.recovered_at is None
                else at(fault.recovered_at) - injected,
                robot_stopped_s=stopped,
                note=fault.note,
                host=fault.host,
                details=_cut_details(fault) if fault.id == "F6" else {},
            )
        )
    trace = tuple((at(t), x) for t, x, _ in odometry.samples if start <= t <= arrived + 0.5)
    return MissionReport(
        mission_time_s=at(arrived) - at(start),
        distance_m=odometry.x,
        nominal_time_s=nominal_time_s,
        faults=tuple(results),
        leaked_processes=len(leaked),
        catalog_entries_left=sum(max(0, n) for n in entries.values())
        + sum(1 for n in entries.values() if n < 0),
        catalog_entries_by_registrar=entries,
        trace=trace,
        stops=tuple(stops),
        unplanned_restarts=tuple(
            UnplannedRestart(u.manager, at(u.seen_at), u.pid, u.restart_s) for u in unplanned
        ),
        drive_started_s=at(start),
        pauses_s=tuple(at(begin) for begin, _ in clock.pauses),
        paused_s=clock.paused_s,
        hosts=_per_host(results, unplanned, entries, host_of) if host_of else {},
    )


def _after(fault: FaultRecord, t: float | None) -> float | None:
    return None if t is None else round(t - fault.injected_at, 3)


def _cut_details(fault: FaultRecord) -> dict[str, Any]:
    """F6's figures: when each host saw the cut and the heal, and the calls that failed."""
    return {
        "station_saw_cut_after_s": _after(fault, fault.detected_at),
        "robot_saw_cut_after_s": _after(fault, fault.robot_saw_at),
        "link_up_after_s": _after(fault, fault.healed_at),
        "robot_saw_station_back_after_s": _after(fault, fault.robot_saw_back_at),
        "calls_failed_during_cut": len(fault.failed_calls),
        "slowest_failed_call_s": round(max(fault.failed_calls), 3) if fault.failed_calls else None,
    }


def _per_host(
    faults: list[FaultResult],
    unplanned: list[UnplannedExit],
    entries: dict[str, int],
    host_of: dict[str, str],
) -> dict[str, dict[str, Any]]:
    """Each host's figures for `report.json` (`MissionReport.hosts`)."""
    hosts: dict[str, dict[str, Any]] = {}
    for host in ("robot", "station"):
        mine = [f for f in faults if f.host in (host, "both")]
        managers = [m for m in ("erm", "cm", "rm") if host_of.get(m) == host]
        cut = next((f for f in faults if f.id == "F6"), None)
        hosts[host] = {
            "managers": managers,
            "faults": [f.id for f in mine],
            "manager_restarts": sum(1 for f in mine if f.id in ("F3", "F4", "F5"))
            + sum(1 for u in unplanned if u.manager in managers),
            "slowest_recovery_s": _round(
                max((f.recovered_after_s or 0.0 for f in mine), default=None)
            ),
            "catalog_entries_left": sum(
                max(0, n) for name, n in entries.items() if host_of.get(name) == host
            ),
        }
        if cut is not None:
            saw = "robot_saw_cut_after_s" if host == "robot" else "station_saw_cut_after_s"
            hosts[host]["saw_cut_after_s"] = cut.details.get(saw)
        if host == "robot" and cut is not None:
            hosts[host]["robot_stopped_at_cut_s"] = _round(cut.robot_stopped_s)
    return hosts
