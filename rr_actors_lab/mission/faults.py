"""Injecting the faults for real, and following the managers through their restarts.

    fault_points(config): where each fault strikes, a fraction of the path (jittered by the seed)

    Drive.run ──inject(F1/F2)──► SIGKILL a program (pidfd; pid and creation time checked)
              ──inject(F3-F5)──► SIGKILL a manager ──► a thread waits for the supervisor's
                                                       `ChildExited` (detected), then for the
                                                       restart that follows, then for an
                                                       answer from its catalog (recovered)
              ──inject(F6)─────► the link down at both ends; a timer brings it up `cut_s`
                                 later (`healed`)
              ──notice_restarts()──► exits that no injected fault caused (by hand, say), with
                                     their `ChildRestarted.restart_s`
    RobotHost ──robot_saw()──► F6: when the robot's host saw the station go, and come back
    Mission (at the end) ──kill_left_behind(bus)──► programs still alive, SIGKILLed

Times come from the supervisor's events. Every wait for a restart names the restart count
it waits for, so a kill by hand cannot make it return early or miss its restart.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import random
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import rr_actors as rr
from rr_actors._supervision.retry import restart_after_failure
from rr_actors_lab.mission import managers, programs
from rr_actors_lab.mission.config import (
    FAULT_WHAT,
    HOST_OF,
    MANAGER_OF,
    MANAGERS,
    MissionConfig,
    MissionError,
)
from rr_actors_lab.mission.hosts import Trees
from rr_actors_lab.mission.netns import TwoHosts
from rr_actors_lab.mission.report import FaultRecord, UnplannedExit

__all__ = [
    "SERVER_OF",
    "Faults",
    "alive",
    "fault_points",
    "kill_left_behind",
    "retry_through_restarts",
    "sigkill",
]

T = TypeVar("T")

SERVER_OF = {"erm": managers.PROGRAM_SERVER, "cm": "lidar", "rm": "robot"}
"""The server of each manager that the mission (or its dependencies) uses."""


def alive(pid: int, created: int | None) -> bool:
    """Whether `pid` is still the process that was created at `created` (clock ticks)."""
    return created is not None and programs.start_time(pid) == created


def sigkill(pid: int, created: int | None = None) -> int:
    """SIGKILL `pid` through a pidfd (checking its creation time); return the pidfd.

    Raises:
        MissionError: `created` is given and `pid` is now another process.
        ProcessLookupError: there is no process `pid` any more.
    """
    pidfd = os.pidfd_open(pid)
    if created is not None and programs.start_time(pid) != created:
        os.close(pidfd)
        raise MissionError(f"process {pid} is not the one the mission started")
    signal.pidfd_send_signal(pidfd, signal.SIGKILL)
    return pidfd


def fault_points(config: MissionConfig) -> dict[str, float]:
    """Where each fault of `config` strikes, as a fraction of the path (jittered by the seed).

    The jitter is up to 2 % of the point either way, and never past the goal: a point
    jittered beyond 1.0 strikes at the goal (1.0). (Past it, the robot would never reach
    the point; the drive would wait for a fault that cannot come until "the goal was not
    reached in time": `--fault-at F5=0.99` with seed 0 was at 1.0036.)
    """
    rng = random.Random(config.seed)  # noqa: S311 - jitter, not cryptography
    return {
        f: min(1.0, config.fault_at[f] + rng.uniform(-0.02, 0.02) * min(1.0, config.fault_at[f]))
        for f in config.faults
    }


def kill_left_behind(bus: Path) -> list[int]:
    """Programs of this mission still alive (from their pid files); they get killed."""
    leaked = []
    for path in sorted((bus / "pids").glob("*.json")):
        with contextlib.suppress(OSError, ValueError, KeyError):
            record = json.loads(path.read_text())
            if alive(record["pid"], record["start_time"]):
                leaked.append(record["pid"])
                with contextlib.suppress(OSError, MissionError):
                    os.close(sigkill(record["pid"], record["start_time"]))
    return leaked


def retry_through_restarts(
    sup: rr.Supervisor | Trees, name: str, action: Callable[[], T], *, timeout: float
) -> T:
    """Run `action`; if manager `name` was down or died meanwhile, wait for its restart, retry.

    After an unavailable error it waits for the next restart only if `name` was killed since
    (`restart_after_failure`), else for the one under way; once per restart count. `name`
    down when asked is waited for until it runs with the restarts it had counted.

    Args:
        sup: the supervisor of `name` (or the mission's `Trees`).
        name: the manager `action` talks to.
        action: what to do (a call, an unload, a `run_in`).
        timeout: seconds for all attempts and waits together.

    Returns:
        What `action` returned.

    Raises:
        RegistrarUnavailableError: it still failed when `timeout` ran out, or `name` will
            not be restarted.
        CallTimeoutError: `name` was not restarted within `timeout`.
        SupervisorGaveUpError: the supervisor gave up on `name`.
    """
    deadline = time.monotonic() + timeout
    tried_again_at = -1
    while True:
        before = sup.child(name)  # the restart to wait for is the one after this snapshot
        try:
            return action()
        except rr.RegistrarUnavailableError:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise
            target = restart_after_failure(before, sup.child(name), tried_again_at)
            if target == before.restarts:
                tried_again_at = target
            sup.wait_restarted(name, timeout=remaining, restarts=target)


def _served_names(registrar: rr.ResourceRegistrar) -> list[str]:
    """Names of the programs the ERM serves (run inside the ERM)."""
    queries = registrar.server_queries(managers.PROGRAM_SERVER)
    return sorted({q.response["name"] for q in queries})


def _registrar(registrar: rr.ResourceRegistrar) -> rr.ResourceRegistrar:
    return registrar


def _monotonic(at: float) -> float:
    """An event's wall-clock `at` as a `time.monotonic()` reading."""
    return time.monotonic() - (time.time() - at)


class Faults:
    """The faults injected into one run, and the managers' restarts seen meanwhile.

    Args:
        sup: the managers' running supervision trees (one per host).
        app: the mission's registrar.
        recovery_timeout: seconds a manager fault may take to be recovered.
        say: tells one line of the story (called from several threads).
        link: the two hosts (F6 cuts the link between them), or `None` on one host.
        cut_s: F6: seconds the link stays down.
    """

    def __init__(
        self,
        sup: Trees,
        app: rr.ResourceRegistrar,
        *,
        recovery_timeout: float,
        say: Callable[[str], None],
        link: TwoHosts | None = None,
        cut_s: float = 3.0,
    ) -> None:
        self.sup = sup
        self.app = app
        self.recovery_timeout = recovery_timeout
        self.say = say
        self.link = link
        self.cut_s = cut_s
        self.healed = threading.Event()
        """Set once F6's link is up again."""
        self.lock = threading.Lock()
        """Guards the records: recovery threads, the event thread and the mission's."""
        self.records: list[FaultRecord] = []
        self.unplanned: list[UnplannedExit] = []
        """Every manager exit that no injected fault caused (killed by hand, say)."""
        self._injected = dict.fromkeys(MANAGERS, 0)  # injected exits not seen yet
        self._seen: dict[str, queue.SimpleQueue[float]] = {
            name: queue.SimpleQueue() for name in MANAGERS
        }  # when the supervisor saw the injected exits (monotonic)
        self._news: list[str] = []
        self._subscription = sup.subscribe(self._on_event)

    def close(self) -> None:
        """Stop following the supervisor's events."""
        self._subscription.close()

    def recovered(self, record: FaultRecord) -> bool:
        """Whether the fault of `record` was recovered (a recovery thread may have said so)."""
        with self.lock:
            return record.recovered_at is not None

    def robot_saw(self, kind: str, at: float) -> None:
        """F6: the robot's host saw the station go (`"lost"`) or come back (`"back"`) at `at`
        (monotonic seconds; on the `RobotHost`'s reader thread)."""
        with self.lock:
            cut = next((r for r in self.records if r.id == "F6"), None)
            if cut is None:
                return
            if kind == "lost" and cut.robot_saw_at is None:
                cut.robot_saw_at = at
            elif kind == "back" and cut.robot_saw_back_at is None:
                cut.robot_saw_back_at = at

    def ready(self) -> bool:
        """Whether every manager is running (a fault is injected only then)."""
        return all(self.sup.child(name).state == "running" for name in MANAGERS)

    def _on_event(self, event: rr.events.Event) -> None:
        """The supervisor's events (its subscriber thread): exits, and restarts' durations."""
        if isinstance(event, rr.events.ChildExited) and event.child in MANAGERS:
            if event.reason.startswith("shutdown"):  # stopped by the supervisor itself
                return
            with self.lock:
                if self._injected[event.child] > 0:  # ours
                    self._injected[event.child] -= 1
                    self._seen[event.child].put(_monotonic(event.at))
                    return
                self.unplanned.append(UnplannedExit(event.child, _monotonic(event.at), event.pid))
                self._news.append(
                    f"{event.child} exited ({event.reason}), but no fault of the mission killed it"
                )
        elif isinstance(event, rr.events.ChildRestarted) and event.child in MANAGERS:
            with self.lock:
                exit = next(
                    (u for u in self.unplanned if u.manager == event.child and u.restart_s is None),
                    None,
                )
                if exit is not None:
                    exit.restart_s = event.restart_s
                    self._news.append(f"{event.child} restarted after {event.restart_s:.3f} s")

    def notice_restarts(self) -> None:
        """Tell the story of the exits and restarts no injected fault caused, since the last
        look (on the mission's thread)."""
        with self.lock:
            news, self._news = self._news, []
        for line in news:
            self.say(line)

    def pids(self, fault: str) -> list[str]:
        """The processes `fault` involves, one line each (`rr-actors demo --step`)."""
        lines = [f"the mission (this process): pid {os.getpid()}"]
        for name in MANAGERS:
            info = self.sup.child(name)
            mark = "  <- SIGKILL" if MANAGER_OF.get(fault) == name else ""
            lines.append(f"{name}: {info.state}, pid {info.pid}, {info.restarts} restart(s){mark}")
        programs_of = {"lidar": ("lidar", "pid", "F1"), "robot": ("driver", "driver_pid", "F2")}
        for query in self.app.client_queries():
            entry = programs_of.get(query.server)
            if entry is None or not isinstance(query.response, dict):
                continue
            what, key, kills = entry
            mark = "  <- SIGKILL" if fault == kills else ""
            pid = query.response[key]
            lines.append(f"{what} program (erm runs it for {query.serving_rr}): pid {pid}{mark}")
            if query.server == "robot":
                pid = query.response["navigation_pid"]
                lines.append(f"navigation program (erm runs it for rm): pid {pid}")
        return lines

    def inject(self, fault: str) -> FaultRecord | None:
        """Inject `fault` for real: SIGKILL the LiDAR, the driver or a manager.

        Returns:
            The fault's record, or `None` if it cannot be injected now (its manager just
            died by other means): the caller tries again later.

        Raises:
            MissionError: the process to kill is not the one the mission started.
        """
        if fault in ("F1", "F2"):
            return self._inject_program(fault)
        if fault == "F6":
            return self._inject_cut()
        return self._inject_manager(fault)

    def _host(self, fault: str) -> str:
        return HOST_OF[fault] if self.link is not None else ""

    def _inject_cut(self) -> FaultRecord:
        """F6: take the link between the hosts down, and up again `cut_s` later."""
        if self.link is None:
            raise MissionError("F6 (the WiFi cut) needs two hosts")
        link = self.link
        record = FaultRecord("F6", time.monotonic(), host=self._host("F6"))
        with self.lock:
            self.records.append(record)
        link.cut()
        record.injected_at = time.monotonic()
        self.say(
            f"F6 injected: {FAULT_WHAT['F6']} (ip link set down at both ends, for {self.cut_s:g} s)"
        )

        def heal() -> None:
            try:
                link.heal()
            except OSError as exc:
                self.say(f"F6: the link could not be brought up again: {exc}")
                return
            record.healed_at = time.monotonic()
            self.healed.set()
            self.say("F6: the link is up again")

        timer = threading.Timer(self.cut_s, heal)
        timer.name = "mission-F6-heal"
        timer.daemon = True
        timer.start()
        return record

    def _inject_program(self, fault: str) -> FaultRecord:
        queries = self.app.client_queries()
        if fault == "F1":
            lidar = next(q for q in queries if q.server == "lidar").response
            pid, created = lidar["pid"], lidar["start_time"]
        else:
            robot = next(q for q in queries if q.server == "robot").response
            pid, created = robot["driver_pid"], robot["driver_start_time"]
        record = FaultRecord(fault, time.monotonic(), host=self._host(fault))
        with self.lock:
            self.records.append(record)
        os.close(sigkill(pid, created))
        record.injected_at = time.monotonic()
        self.say(f"{fault} injected: {FAULT_WHAT[fault]} (SIGKILL pid {pid})")
        return record

    def _inject_manager(self, fault: str) -> FaultRecord | None:
        name = MANAGER_OF[fault]
        info = self.sup.child(name)
        if info.state != "running":
            return None
        pidfd: int | None = None
        if info.pid is not None:
            try:
                pidfd = os.pidfd_open(info.pid)
            except ProcessLookupError:  # it died just now, by other means
                return None
        record = FaultRecord(fault, time.monotonic(), host=self._host(fault))
        with self.lock:
            self.records.append(record)
            self._injected[name] += 1  # its exit is ours, not an unplanned one
        if pidfd is not None:
            signal.pidfd_send_signal(pidfd, signal.SIGKILL)
            record.injected_at = time.monotonic()
            os.close(pidfd)
            self.say(f"{fault} injected: {FAULT_WHAT[fault]} (SIGKILL pid {info.pid})")
        else:  # a thread manager: make its registrar actor die
            from rr_actors.testing import crash  # noqa: PLC0415

            record.injected_at = time.monotonic()
            crash(self.sup.run_in(name, _registrar))
            self.say(f"{fault} injected: {FAULT_WHAT[fault]} (its registrar crashed)")
        threading.Thread(
            target=self._await_manager,
            args=(record, name, info.restarts),
            name=f"mission-{fault}",
            daemon=True,
        ).start()
        return record

    def _await_manager(self, record: FaultRecord, name: str, restarts_before: int) -> None:
        """F3-F5: see the supervisor see the exit, wait for the restart, check the catalog."""
        deadline = record.injected_at + self.recovery_timeout
        try:
            try:
                seen = self._seen[name].get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise rr.CallTimeoutError(f"the exit of {name} was not seen") from None
            with self.lock:
                record.detected_at = seen
            target = restarts_before + 1  # the restart that follows our kill, not an earlier one
            tried_again_at = -1
            while True:
                info = self.sup.wait_restarted(
                    name, timeout=max(0.0, deadline - time.monotonic()), restarts=target
                )
                try:
                    note = self._restored(name)
                    break
                except rr.RegistrarUnavailableError:
                    target = restart_after_failure(info, self.sup.child(name), tried_again_at)
                    if target == info.restarts:
                        tried_again_at = target
            with self.lock:
                record.note = note
                record.recovered_at = time.monotonic()
            self.say(f"{record.id} recovered: {name} restarted and {note}")
        except rr.RrError as exc:
            self.say(f"{record.id}: {name} did not come back: {exc}")

    def _restored(self, name: str) -> str:
        """Ask the restarted manager what it restored; a short note for the report."""
        mine = self.app.fetch_queries(name, SERVER_OF[name])
        if name == "erm":
            served: Any = self.sup.run_in(name, _served_names)
            return "re-adopted " + ", ".join(served)
        held = {q.id for q in self.app.client_queries()}
        restored = sorted({q.id[:8] for q in mine if q.id in held})
        queries = "query" if len(restored) == 1 else "queries"
        return f"restored the mission's {queries} {', '.join(restored)}"
