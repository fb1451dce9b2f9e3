"""The injector: fires a run's fault schedule at its times, for real, and records each one.

    schedule (timed) ─────────────► heap of (monotonic time, action) ◄── on_event: a trigger
                                          │                               matched (n-th event)
                            injector thread: wait for the earliest, fire it
                                          │
        kill_manager ──► SIGKILL through a pidfd (a thread manager: its registrar crashes)
        hang_manager ──► SIGSTOP through a pidfd ──► (after `for`) SIGCONT
        kill_resource ─► SIGKILL a child process of a manager (pid and creation time checked)
        cut_connections ► SIGUSR2: the manager's handler shuts its connections (_instrument.py)
        load_error ────► Supervisor.run_in(manager, arm_load_error): its next loads raise

Signals go through pidfds, which always mean the process that was looked up, never a
later one that reused its pid. A fault whose manager is not running when it is due is
recorded as skipped (the schedule stays the same for the same seed; what it meets may
not). The injector thread does nothing but wait and fire, so it is on time: the run
process also switches threads every millisecond (see `runner.py`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import heapq
import itertools
import logging
import os
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import rr_actors as rr
from rr_actors import events
from rr_actors.experiments._instrument import CUT_SIGNAL, arm_load_error, catches_cut_signal
from rr_actors.experiments.plan import Plan
from rr_actors.experiments.results import FaultRecord
from rr_actors.experiments.schedule import ScheduledFault

__all__ = ["Injector", "resource_processes"]

logger = logging.getLogger("rr_actors.experiments")

RUN_IN_TIMEOUT = 2.0
"""Seconds `load_error` waits for its manager to take the switch."""

PREPARE_AHEAD = 0.003
"""Seconds before a signal is due that the injector wakes to look up its target and open a
pidfd, so that at the due time only the signal itself is left to send."""

SPIN = 0.0003
"""The last seconds before a due signal are waited by spinning, not by a timed wait (whose
wake-up can come late by a scheduler tick)."""


def _registrar_of(registrar: rr.ResourceRegistrar) -> rr.ResourceRegistrar:
    return registrar


def _start_time(pid: int) -> int | None:
    """Creation time of `pid` in clock ticks (`/proc/<pid>/stat` field 22), `None` if gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()
    return None if fields[0] == "Z" else int(fields[19])


def _children(pid: int) -> list[int]:
    pids: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        with contextlib.suppress(OSError, ValueError):
            pids.extend(int(p) for p in (task / "children").read_text().split())
    return pids


def resource_processes(sup: rr.Supervisor, managers: list[str]) -> list[tuple[str, int, int]]:
    """The child processes of the running process managers among `managers`.

    Args:
        sup: the run's supervisor.
        managers: the managers to look at, in order.

    Returns:
        `(manager, pid, creation time)` sorted by manager order, creation time and pid
        (a stable order, so a seeded pick chooses alike in alike runs).
    """
    found: list[tuple[int, int, int, str]] = []
    for order, name in enumerate(managers):
        info = sup.child(name)
        if info.pid is None or info.state != "running":
            continue
        for child in _children(info.pid):
            created = _start_time(child)
            if created is not None:
                found.append((order, created, child, name))
    found.sort()
    return [(name, pid, created) for _, created, pid, name in found]


@dataclasses.dataclass(order=True)
class _Due:
    at: float  # monotonic
    seq: int
    action: Callable[[], None] = dataclasses.field(compare=False)


class Injector:
    """Fires one run's faults on its own thread; records every one in `records`.

    Args:
        sup: the run's running supervisor.
        plan: the plan (one compared value of it).
        schedule: the run's fault schedule.
        t0: the monotonic start of the run's workload (the schedule's time 0).
        wall_t0: the same instant on the wall clock (`time.time()`).
    """

    def __init__(
        self,
        sup: rr.Supervisor,
        plan: Plan,
        schedule: tuple[ScheduledFault, ...],
        *,
        t0: float,
        wall_t0: float,
    ) -> None:
        self.sup = sup
        self.plan = plan
        self.t0 = t0
        self.wall_t0 = wall_t0
        self.records: list[FaultRecord] = []
        """Every fault fired or skipped so far (appended by several threads)."""
        self.resumed: list[tuple[str, float]] = []
        """`(manager, time)` of each hung manager resumed while it was still alive."""
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._heap: list[_Due] = []
        self._seq = itertools.count()
        self._stopped = False
        self._hung: dict[int, tuple[str, int]] = {}  # pidfd -> (manager, pid)
        self._waiting: list[list[Any]] = []  # [scheduled fault, matches seen]
        self._threads: list[threading.Thread] = []
        for fault in schedule:
            if fault.at is None:
                self._waiting.append([fault, 0])
            else:
                self._schedule(fault, fault.at)
        self._thread = threading.Thread(target=self._loop, name="rr-injector", daemon=True)

    # -- life cycle -----------------------------------------------------------------------

    def start(self) -> None:
        """Start firing (the schedule's time 0 is `t0`, which may be in the past)."""
        self._thread.start()

    def stop(self, *, timeout: float = 5.0) -> None:
        """Stop firing; resume every hung manager now; record triggers that never came."""
        with self._cond:
            self._stopped = True
            self._cond.notify_all()
        self._thread.join(timeout)
        for thread in self._threads:
            thread.join(timeout)
        with self._lock:
            hung = list(self._hung)
        for pidfd in hung:
            self._resume(pidfd)
        with self._lock:
            waiting, self._waiting = self._waiting, []
        for fault, _ in waiting:
            self._record(fault, None, None, "its trigger did not happen in the run", skipped=True)

    def on_event(self, event: events.Event) -> None:
        """Look at one event of the run (from the subscriber thread); fire what it triggers."""
        name = type(event).__name__
        due: list[tuple[ScheduledFault, float]] = []
        with self._lock:
            for entry in self._waiting:
                fault, seen = entry
                trigger = fault.trigger
                if trigger.event != name or any(
                    getattr(event, key, None) != value for key, value in trigger.match.items()
                ):
                    continue
                entry[1] = seen + 1
                if entry[1] == trigger.nth:
                    # The event's own time, not its arrival: events of manager processes
                    # arrive in batches, a little after they happened.
                    due.append((fault, event.at - self.wall_t0 + fault.delay))
            fired = {id(f) for f, _ in due}
            self._waiting = [e for e in self._waiting if id(e[0]) not in fired]
        for fault, at in due:
            self._schedule(fault, at)

    # -- the thread -----------------------------------------------------------------------

    def _schedule(self, fault: ScheduledFault, at: float) -> None:
        """Fire `fault` at `at` (seconds from `t0`), waking `PREPARE_AHEAD` earlier."""
        self._push(self.t0 + at - PREPARE_AHEAD, functools.partial(self._fire, fault, at))

    def _until(self, at: float) -> None:
        """Return at `at` (seconds from `t0`): a timed wait, then a short spin."""
        due = self.t0 + at
        while True:
            left = due - time.monotonic()
            if left <= 0:
                return
            if left > SPIN:
                with self._cond:
                    if self._stopped:
                        return
                    self._cond.wait(left - SPIN)

    def _push(self, at: float, action: Callable[[], None]) -> None:
        with self._cond:
            if self._stopped:
                return
            heapq.heappush(self._heap, _Due(at, next(self._seq), action))
            self._cond.notify_all()

    def _loop(self) -> None:
        while True:
            with self._cond:
                while not self._stopped:
                    if self._heap:
                        wait = self._heap[0].at - time.monotonic()
                        if wait <= 0:
                            break
                        self._cond.wait(wait)
                    else:
                        self._cond.wait()
                if self._stopped:
                    return
                due = heapq.heappop(self._heap)
            try:
                due.action()
            except Exception:
                logger.exception("the injector failed to fire a fault")

    # -- firing ---------------------------------------------------------------------------

    def _now(self) -> float:
        return time.monotonic() - self.t0

    def _record(
        self,
        fault: ScheduledFault,
        scheduled: float | None,
        injected: float | None,
        detail: str,
        *,
        target: str | None = None,
        skipped: bool = False,
    ) -> None:
        record = FaultRecord(
            fault=fault.fault,
            n=fault.n,
            kind=fault.kind,
            target=target if target is not None else fault.target,
            scheduled_s=scheduled,
            injected_s=injected,
            detail=detail,
            skipped=skipped,
        )
        with self._lock:
            self.records.append(record)
        logger.info("fault %s: %s", fault.kind, detail)

    def _fire(self, fault: ScheduledFault, scheduled: float) -> None:
        if fault.kind == "kill_resource":
            self._kill_resource(fault, scheduled)
            return
        if fault.kind == "load_error":
            thread = threading.Thread(
                target=self._load_error, args=(fault, scheduled), name="rr-inject-load", daemon=True
            )
            self._threads.append(thread)
            thread.start()
            return
        assert fault.target is not None
        info = self.sup.child(fault.target)
        if info.state != "running":
            self._record(
                fault,
                scheduled,
                None,
                f"{fault.target} was not running ({info.state})",
                skipped=True,
            )
            return
        if info.pid is None:  # a thread manager (validation allows only kills here)
            registrar = self.sup.run_in(fault.target, _registrar_of)
            self._until(scheduled)
            injected = self._now()
            from rr_actors.testing import crash  # noqa: PLC0415

            crash(registrar)
            self._record(fault, scheduled, injected, f"crashed the registrar of {fault.target}")
            return
        try:
            pidfd = os.pidfd_open(info.pid)
        except ProcessLookupError:
            self._record(fault, scheduled, None, f"{fault.target} had just died", skipped=True)
            return
        if fault.kind == "kill_manager":
            self._signal(fault, scheduled, pidfd, signal.SIGKILL, f"SIGKILL pid {info.pid}")
            os.close(pidfd)
        elif fault.kind == "hang_manager":
            if self._signal(fault, scheduled, pidfd, signal.SIGSTOP, f"SIGSTOP pid {info.pid}"):
                for_s = self.plan.faults[fault.fault].for_s or 0.0
                with self._lock:
                    self._hung[pidfd] = (fault.target, info.pid)
                self._push(time.monotonic() + for_s, functools.partial(self._resume, pidfd))
            else:
                os.close(pidfd)
        else:  # cut_connections
            if not catches_cut_signal(info.pid):
                os.close(pidfd)
                self._record(
                    fault,
                    scheduled,
                    None,
                    f"{fault.target} (pid {info.pid}) has no handler for {CUT_SIGNAL.name} yet",
                    skipped=True,
                )
                return
            self._signal(fault, scheduled, pidfd, CUT_SIGNAL, f"cut pid {info.pid}'s connections")
            os.close(pidfd)

    def _signal(
        self, fault: ScheduledFault, scheduled: float, pidfd: int, signum: int, what: str
    ) -> bool:
        self._until(scheduled)
        try:
            signal.pidfd_send_signal(pidfd, signum)
        except ProcessLookupError:
            self._record(fault, scheduled, None, f"{fault.target} had just died", skipped=True)
            return False
        self._record(fault, scheduled, self._now(), what)
        return True

    def _resume(self, pidfd: int) -> None:
        """SIGCONT a hung manager (if nobody killed it meanwhile)."""
        with self._lock:
            entry = self._hung.pop(pidfd, None)
        if entry is None:
            return
        name, pid = entry
        try:
            info = self.sup.child(name)
            with contextlib.suppress(ProcessLookupError):
                signal.pidfd_send_signal(pidfd, signal.SIGCONT)
                if info.pid == pid and info.state == "running":
                    with self._lock:
                        self.resumed.append((name, self._now()))
        finally:
            os.close(pidfd)

    def _kill_resource(self, fault: ScheduledFault, scheduled: float) -> None:
        managers = (
            [fault.target]
            if fault.target is not None
            else [m.name for m in self.plan.managers() if m.isolation == "process"]
        )
        candidates = resource_processes(self.sup, managers)
        if not candidates:
            self._record(fault, scheduled, None, "no resource process to kill", skipped=True)
            return
        name, pid, created = candidates[min(len(candidates) - 1, int(fault.pick * len(candidates)))]
        try:
            pidfd = os.pidfd_open(pid)
        except ProcessLookupError:
            self._record(fault, scheduled, None, f"process {pid} had just exited", skipped=True)
            return
        try:
            if _start_time(pid) != created:
                self._record(fault, scheduled, None, f"process {pid} had just exited", skipped=True)
                return
            self._until(scheduled)
            signal.pidfd_send_signal(pidfd, signal.SIGKILL)
            self._record(
                fault,
                scheduled,
                self._now(),
                f"SIGKILL pid {pid} (a process of {name})",
                target=name,
            )
        except ProcessLookupError:
            self._record(fault, scheduled, None, f"process {pid} had just exited", skipped=True)
        finally:
            os.close(pidfd)

    def _load_error(self, fault: ScheduledFault, scheduled: float) -> None:
        assert fault.target is not None
        plan = self.plan.faults[fault.fault]
        arm = functools.partial(
            arm_load_error, fault.target, plan.server, plan.loads, plan.for_s, plan.message
        )
        self._until(scheduled)
        try:
            self.sup.run_in(fault.target, arm, timeout=RUN_IN_TIMEOUT)
        except rr.RrError as exc:
            self._record(fault, scheduled, None, f"{fault.target}: {exc}", skipped=True)
            return
        what = f"for {plan.for_s:g} s" if plan.for_s is not None else f"{plan.loads} load(s)"
        server = f"/{plan.server}" if plan.server else ""
        self._record(
            fault, scheduled, self._now(), f"loads of {fault.target}{server} raise, {what}"
        )
