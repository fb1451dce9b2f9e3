"""The faults at a run's managers: their processes signalled, a thread manager crashed,
their resource processes killed, their loads made to fail.

```
 fire(fault, due) (the injector's thread, PREPARE_AHEAD before it is due): look up its target
   kill_manager ──► SIGKILL ─┐
   hang_manager ──► SIGSTOP ─┼─ a pidfd and the due time ──► trigger process (_trigger.py)
   kill_resource ─► SIGKILL ─┤                               sends it at the due time;
   cut_connections ► SIGUSR2 ┘  (the manager's handler       _sent: the reply recorded
                                 shuts its connections)
   hang_manager, after `for` ──► resume: SIGCONT (from here, through the kept pidfd)
   kill_resource, its process exited first (ESRCH) ──► aim again, at one running now
   kill_manager of a thread manager ──► its registrar crashes (at the due time, here)
   load_error ──► a thread: Supervisor.run_in(manager, arm_load_error): its next loads raise
```
"""

from __future__ import annotations

import contextlib
import errno
import functools
import logging
import os
import signal
import threading
import time
from typing import TYPE_CHECKING

import rr_actors as rr
from rr_actors_lab.experiments._instrument import CUT_SIGNAL, arm_load_error, catches_cut_signal
from rr_actors_lab.experiments._procs import resource_processes, start_time

if TYPE_CHECKING:
    from rr_actors_lab.experiments._agenda import Agenda, FaultLog
    from rr_actors_lab.experiments._trigger import Trigger
    from rr_actors_lab.experiments.plan import Plan
    from rr_actors_lab.experiments.schedule import ScheduledFault

__all__ = ["RUN_IN_TIMEOUT", "ManagerFaults"]

logger = logging.getLogger("rr_actors.experiments")

RUN_IN_TIMEOUT = 2.0
"""Seconds `load_error` waits for its manager to take the switch."""

KILL_RESOURCE_AIMS = 3
"""Resource processes a `kill_resource` aims at, at most: each one that exits before the kill
(its resource unloaded, or replaced by its manager) makes it aim at one there is now."""


def _no_aim(gone: tuple[tuple[int, int], ...]) -> str:
    """Why a `kill_resource` was not sent, `gone` the processes that exited before it."""
    if not gone:
        return "no resource process to kill"
    pids = ", ".join(str(pid) for pid, _ in gone)
    if len(gone) == KILL_RESOURCE_AIMS:
        return f"pids {pids} had each just exited (ESRCH): tried {len(gone)}, the most"
    return f"pid(s) {pids} had just exited (ESRCH), and no other resource process runs"


def _registrar_of(registrar: rr.ResourceRegistrar) -> rr.ResourceRegistrar:
    return registrar


class ManagerFaults:
    """Fires the faults whose target is a manager (or its resource processes).

    Args:
        sup: the run's running supervisor.
        plan: the plan (its faults' `for`, `server`, `loads`, `message`).
        t0: the monotonic start of the run's workload (the schedule's time 0).
        agenda: the injector's thread (waits to a due time; a hung manager's resume).
        log: where each fault is recorded.
        trigger: the trigger process, which sends signals at their due times.
    """

    def __init__(
        self,
        sup: rr.Supervisor,
        plan: Plan,
        t0: float,
        *,
        agenda: Agenda,
        log: FaultLog,
        trigger: Trigger,
    ) -> None:
        self.sup = sup
        self.plan = plan
        self.t0 = t0
        self.agenda = agenda
        self.log = log
        self.trigger = trigger
        self.home = plan.hosts.home if plan.hosts is not None else None
        self.resumed: list[tuple[str, float]] = []
        """`(manager, time)` of each hung manager resumed while it was still alive."""
        self._lock = threading.Lock()
        self._hung: dict[int, tuple[str, int]] = {}  # pidfd -> (manager, pid)
        self._threads: list[threading.Thread] = []

    def fire(self, fault: ScheduledFault, scheduled: float) -> None:
        """Prepare `fault`, due at `scheduled` seconds from t0 (the injector's thread)."""
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
            self.log.record(
                fault,
                scheduled,
                None,
                f"{fault.target} was not running ({info.state})",
                skipped=True,
            )
            return
        if info.pid is None:  # a thread manager (validation allows only kills here)
            registrar = self.sup.run_in(fault.target, _registrar_of)
            self.agenda.wait_until(self.t0 + scheduled)
            injected = self._now()
            from rr_actors.testing import crash  # noqa: PLC0415

            crash(registrar)
            self.log.record(fault, scheduled, injected, f"crashed the registrar of {fault.target}")
            return
        self._signal(fault, scheduled, info.pid)

    def join(self, timeout: float) -> None:
        """Wait up to `timeout` seconds for each load error's thread."""
        for thread in self._threads:
            thread.join(timeout)

    def resume_all(self) -> None:
        """Resume every manager still hung (the run ended)."""
        with self._lock:
            hung = list(self._hung)
        for pidfd in hung:
            self._resume(pidfd)

    def _now(self) -> float:
        return time.monotonic() - self.t0

    def _signal(self, fault: ScheduledFault, scheduled: float, pid: int) -> None:
        """Hand manager process `pid`'s pidfd to the trigger process, which signals it."""
        try:
            pidfd = os.pidfd_open(pid)
        except ProcessLookupError:
            self.log.record(fault, scheduled, None, f"{fault.target} had just died", skipped=True)
            return
        if fault.kind == "cut_connections" and not catches_cut_signal(pid):
            os.close(pidfd)
            self.log.record(
                fault,
                scheduled,
                None,
                f"{fault.target} (pid {pid}) has no handler for {CUT_SIGNAL.name} yet",
                skipped=True,
            )
            return
        signum, what = {
            "kill_manager": (signal.SIGKILL, f"SIGKILL pid {pid}"),
            "hang_manager": (signal.SIGSTOP, f"SIGSTOP pid {pid}"),
            "cut_connections": (CUT_SIGNAL, f"cut pid {pid}'s connections"),
        }[fault.kind]
        keep = fault.kind == "hang_manager"  # its pidfd sends the SIGCONT later
        on_sent = functools.partial(
            self._sent, fault, scheduled, what, pidfd if keep else None, pid
        )
        self.trigger.send(self.t0 + scheduled, signum, pidfd, on_sent)
        if not keep:
            os.close(pidfd)

    def _sent(
        self,
        fault: ScheduledFault,
        scheduled: float,
        what: str,
        pidfd: int | None,
        pid: int,
        sent_at: float,
        code: int,
        *,
        target: str | None = None,
    ) -> None:
        """The trigger sent (or could not send) a fault's signal: record it (its thread)."""
        if code:
            if pidfd is not None:
                os.close(pidfd)
            why = "had just exited" if code == errno.ESRCH else "could not be signalled"
            self.log.record(
                fault,
                scheduled,
                None,
                f"pid {pid} {why} ({errno.errorcode.get(code, code)})",
                target=target,
                skipped=True,
            )
            return
        self.log.record(fault, scheduled, sent_at - self.t0, what, target=target)
        if pidfd is not None and fault.target is not None:  # a hang: resume it later
            for_s = self.plan.faults[fault.fault].for_s or 0.0
            with self._lock:
                self._hung[pidfd] = (fault.target, pid)
            self.agenda.push(sent_at + for_s, functools.partial(self._resume, pidfd))

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

    def _kill_resource(
        self, fault: ScheduledFault, scheduled: float, gone: tuple[tuple[int, int], ...] = ()
    ) -> None:
        """Aim `fault` at a resource process (picked by its seed among those of its manager(s)
        now, none of `gone`, `(pid, creation time)` each) and hand the trigger its pidfd."""
        managers = (
            [fault.target]
            if fault.target is not None
            else [
                m.name
                for m in self.plan.managers()
                if m.isolation == "process" and m.host in (None, self.home)
            ]
        )
        while True:
            candidates = [c for c in resource_processes(self.sup, managers) if c[1:] not in gone]
            if not candidates or len(gone) == KILL_RESOURCE_AIMS:
                self.log.record(fault, scheduled, None, _no_aim(gone), skipped=True)
                return
            name, pid, created = candidates[
                min(len(candidates) - 1, int(fault.pick * len(candidates)))
            ]
            try:
                pidfd = os.pidfd_open(pid)
            except ProcessLookupError:
                gone += ((pid, created),)
                continue
            if start_time(pid) == created:
                break
            os.close(pidfd)  # a zombie, or another process now
            gone += ((pid, created),)
        exited = "".join(f"; pid {p} had just exited" for p, _ in gone)
        what = f"SIGKILL pid {pid} (a process of {name}{exited})"
        on_sent = functools.partial(
            self._resource_sent, fault, scheduled, what, (*gone, (pid, created)), name
        )
        self.trigger.send(self.t0 + scheduled, signal.SIGKILL, pidfd, on_sent)
        os.close(pidfd)

    def _resource_sent(
        self,
        fault: ScheduledFault,
        scheduled: float,
        what: str,
        aimed: tuple[tuple[int, int], ...],
        name: str,
        sent_at: float,
        code: int,
    ) -> None:
        """A `kill_resource`'s reply (the trigger's reader thread): a process that exited before
        it (unloaded, or replaced by its manager) makes it aim again, at once (its time passed)."""
        if code == errno.ESRCH:
            try:
                self._kill_resource(fault, scheduled, aimed)
            except (OSError, rr.RrError) as exc:  # (the tree stopping, no descriptor left)
                self.log.record(fault, scheduled, None, f"aiming again: {exc}", skipped=True)
            return
        self._sent(fault, scheduled, what, None, aimed[-1][0], sent_at, code, target=name)

    def _load_error(self, fault: ScheduledFault, scheduled: float) -> None:
        assert fault.target is not None
        plan = self.plan.faults[fault.fault]
        arm = functools.partial(
            arm_load_error, fault.target, plan.server, plan.loads, plan.for_s, plan.message
        )
        self.agenda.wait_until(self.t0 + scheduled)
        try:
            self.sup.run_in(fault.target, arm, timeout=RUN_IN_TIMEOUT)
        except rr.RrError as exc:
            self.log.record(fault, scheduled, None, f"{fault.target}: {exc}", skipped=True)
            return
        what = f"for {plan.for_s:g} s" if plan.for_s is not None else f"{plan.loads} load(s)"
        server = f"/{plan.server}" if plan.server else ""
        self.log.record(
            fault, scheduled, self._now(), f"loads of {fault.target}{server} raise, {what}"
        )
