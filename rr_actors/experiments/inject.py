"""The injector: fires a run's fault schedule at its times, for real, and records each one.

    schedule (timed) ─────────────► heap of (monotonic time, action) ◄── on_event: a trigger
                                          │                               matched (n-th event)
              injector thread: PREPARE_AHEAD before each fault, look up its target
                                          │
        kill_manager ──► SIGKILL ─┐
        hang_manager ──► SIGSTOP ─┼─ a pidfd and the due time ──► trigger process (_trigger.py)
        kill_resource ─► SIGKILL ─┤                               sends it at the due time;
        cut_connections ► SIGUSR2 ┘  (the manager's handler       the reply is recorded
                                      shuts its connections)
        hang_manager, after `for` ──► SIGCONT (from here)
        kill_manager of a thread manager ──► its registrar crashes (at the due time, here)
        load_error ────► Supervisor.run_in(manager, arm_load_error): its next loads raise

Signals go through pidfds, which always mean the process that was looked up, never a
later one that reused its pid. They leave from a separate single-threaded process so that
a busy run process (its clients hold the interpreter lock) does not make them late. A
fault whose manager is not running when it is prepared is recorded as skipped (the
schedule stays the same for the same seed; what it meets may not).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import functools
import heapq
import itertools
import logging
import os
import signal
import threading
import time
from collections.abc import Callable
from typing import Any

import rr_actors as rr
from rr_actors import events
from rr_actors.experiments._hosts import HostProcess
from rr_actors.experiments._instrument import CUT_SIGNAL, arm_load_error, catches_cut_signal
from rr_actors.experiments._netns import HostNetwork
from rr_actors.experiments._procs import resource_processes, start_time
from rr_actors.experiments._sender import Trigger
from rr_actors.experiments.plan import HOST_KINDS, Plan
from rr_actors.experiments.results import FaultRecord
from rr_actors.experiments.schedule import ScheduledFault

__all__ = ["Injector"]

logger = logging.getLogger("rr_actors.experiments")

RUN_IN_TIMEOUT = 2.0
"""Seconds `load_error` waits for its manager to take the switch."""

PREPARE_AHEAD = 0.02
"""Seconds before a fault is due that the injector looks up its target and, for a signal,
hands a pidfd to the trigger process, which sends it at the due time."""

SPIN = 0.0003
"""The last seconds before a fault fired from this process (a thread manager's crash, a
load error's switch) are waited by spinning, not by a timed wait."""


def _registrar_of(registrar: rr.ResourceRegistrar) -> rr.ResourceRegistrar:
    return registrar


@dataclasses.dataclass(order=True)
class _Due:
    at: float  # monotonic
    seq: int
    action: Callable[[], None] = dataclasses.field(compare=False)
    # A fault's firing (not a hung manager's resumption): `(fault, due time from t0)`.
    fires: tuple[ScheduledFault, float] | None = dataclasses.field(default=None, compare=False)


class Injector:
    """Fires one run's faults on its own thread; records every one in `records`.

    Args:
        sup: the run's running supervisor.
        plan: the plan (one compared value of it).
        schedule: the run's fault schedule.
        t0: the monotonic start of the run's workload (the schedule's time 0).
        wall_t0: the same instant on the wall clock (`time.time()`).
        hosts: with `[hosts]`, the namespaces and the other hosts' processes (what
            `cut`, `partition`, `freeze` and `kill_router` act on).
    """

    def __init__(
        self,
        sup: rr.Supervisor,
        plan: Plan,
        schedule: tuple[ScheduledFault, ...],
        *,
        t0: float,
        wall_t0: float,
        hosts: tuple[HostNetwork | None, dict[str, HostProcess]] = (None, {}),
    ) -> None:
        self.sup = sup
        self._network, self._host_processes = hosts
        self._home = plan.hosts.home if plan.hosts is not None else None
        self._healing: dict[int, Callable[[], None]] = {}  # id -> undo a cut, thaw a freeze
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
        self._trigger = Trigger()
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
        """Stop firing; resume every hung manager now; record what did not fire as skipped.

        Every scheduled fault ends up in `records`: a trigger that never came, and a
        triggered fault that came due after the run ended (its event happened in the run,
        its `delay` took it past the end), are recorded as skipped.

        Args:
            timeout: seconds to wait for each of the injector's threads and for the
                trigger process's last replies.
        """
        with self._cond:
            self._stopped = True
            self._cond.notify_all()
            unfired = [due.fires for due in self._heap if due.fires is not None]
            self._heap = []
        if self._thread.ident is not None:
            self._thread.join(timeout)
        for thread in self._threads:
            thread.join(timeout)
        self._trigger.close(timeout=timeout)
        with self._lock:
            hung = list(self._hung)
            healing, self._healing = list(self._healing.values()), {}
        for pidfd in hung:
            self._resume(pidfd)
        for undo in healing:  # links up again, frozen hosts thawed
            try:
                undo()
            except Exception:
                logger.exception("could not undo a fault between hosts")
        with self._lock:
            waiting, self._waiting = self._waiting, []
        for fault, _ in waiting:
            self._record(fault, None, None, "its trigger did not happen in the run", skipped=True)
        for fault, at in sorted(unfired, key=lambda fires: fires[1]):
            self._record(fault, at, None, "due after the run ended", skipped=True)

    def on_event(self, event: events.Event) -> None:
        """Look at one event of the run (from the subscriber thread); fire what it triggers."""
        if not self._waiting:  # no trigger left: the common case, without the lock
            return
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
        self._push(
            self.t0 + at - PREPARE_AHEAD, functools.partial(self._fire, fault, at), (fault, at)
        )

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

    def _push(
        self,
        at: float,
        action: Callable[[], None],
        fires: tuple[ScheduledFault, float] | None = None,
    ) -> None:
        with self._cond:
            stopped = self._stopped
            if not stopped:
                heapq.heappush(self._heap, _Due(at, next(self._seq), action, fires))
                self._cond.notify_all()
        if stopped and fires is not None:  # a trigger that matched as the run ended
            self._record(fires[0], fires[1], None, "due after the run ended", skipped=True)

    def _loop(self) -> None:
        try:
            self._fire_when_due()
        except Exception as exc:  # a bug, or a wait too long for `threading` (OverflowError)
            self._abandon(f"not fired: the injector failed ({exc!r})")
            logger.exception("the injector stopped")

    def _abandon(self, detail: str) -> None:
        """Record every fault still to come as skipped with `detail` (the loop failed)."""
        with self._lock:
            left, self._heap = sorted(self._heap), []
            waiting, self._waiting = self._waiting, []
        for due in left:  # a hang's resume is not a fault: stop() resumes every hung manager
            if due.fires is not None:
                fault, scheduled = due.fires
                self._record(fault, scheduled, None, detail, skipped=True)
        for fault, _ in waiting:
            self._record(fault, None, None, detail, skipped=True)

    def _fire_when_due(self) -> None:
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

    def _fire(self, fault: ScheduledFault, scheduled: float) -> None:  # noqa: PLR0911 - a case per kind
        if fault.kind in HOST_KINDS:
            self._between_hosts(fault, scheduled)
            return
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
        if fault.kind == "cut_connections" and not catches_cut_signal(info.pid):
            os.close(pidfd)
            self._record(
                fault,
                scheduled,
                None,
                f"{fault.target} (pid {info.pid}) has no handler for {CUT_SIGNAL.name} yet",
                skipped=True,
            )
            return
        signum, what = {
            "kill_manager": (signal.SIGKILL, f"SIGKILL pid {info.pid}"),
            "hang_manager": (signal.SIGSTOP, f"SIGSTOP pid {info.pid}"),
            "cut_connections": (CUT_SIGNAL, f"cut pid {info.pid}'s connections"),
        }[fault.kind]
        keep = fault.kind == "hang_manager"  # its pidfd sends the SIGCONT later
        on_sent = functools.partial(
            self._sent, fault, scheduled, what, pidfd if keep else None, info.pid
        )
        self._trigger.send(self.t0 + scheduled, signum, pidfd, on_sent)
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
            self._record(
                fault,
                scheduled,
                None,
                f"pid {pid} had just exited ({errno.errorcode.get(code, code)})",
                target=target,
                skipped=True,
            )
            return
        self._record(fault, scheduled, sent_at - self.t0, what, target=target)
        if pidfd is not None and fault.target is not None:  # a hang: resume it later
            for_s = self.plan.faults[fault.fault].for_s or 0.0
            with self._lock:
                self._hung[pidfd] = (fault.target, pid)
            self._push(sent_at + for_s, functools.partial(self._resume, pidfd))

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

    def _between_hosts(self, fault: ScheduledFault, scheduled: float) -> None:
        """A fault between hosts, fired from this thread at its due time: a link or links
        down (`ip link set ... down`), a host process stopped or killed; its undo (links
        up, SIGCONT) `for` seconds later, or at `stop`."""
        plan, network = self.plan.faults[fault.fault], self._network
        assert network is not None
        for_s = plan.for_s or 0.0
        undo: Callable[[], None] | None = None
        if fault.kind == "cut":
            assert plan.link is not None
            one, other = plan.link
            target, what = f"{one}-{other}", f"link {one}-{other} down for {for_s:g} s"
            self._until(scheduled)
            network.set_link(one, other, up=False)
            undo = functools.partial(network.set_link, one, other, up=True)
        elif fault.kind == "partition":
            side = plan.hosts
            target = "+".join(side)
            what = f"{target} cut from the other hosts for {for_s:g} s"
            self._until(scheduled)
            network.set_links(side, up=False)
            undo = functools.partial(network.set_links, side, up=True)
        else:
            assert fault.target is not None
            target, host = fault.target, self._host_processes[fault.target]
            pid = host.pid
            try:
                pidfd = os.pidfd_open(pid) if pid is not None else None
            except ProcessLookupError:
                pidfd = None
            if pidfd is None:
                self._record(fault, scheduled, None, f"host {target} was not running", skipped=True)
                return
            self._until(scheduled)
            try:
                if fault.kind == "freeze":
                    signal.pidfd_send_signal(pidfd, signal.SIGSTOP)
                    what = f"SIGSTOP host {target}'s router process (pid {pid}) for {for_s:g} s"
                    undo = functools.partial(self._thaw, pidfd)
                else:
                    signal.pidfd_send_signal(pidfd, signal.SIGKILL)
                    what = f"SIGKILL host {target}'s router process (pid {pid})"
            except ProcessLookupError:
                os.close(pidfd)
                self._record(fault, scheduled, None, f"host {target} had just exited", skipped=True)
                return
            if undo is None:
                os.close(pidfd)
        injected = self._now()
        self._record(fault, scheduled, injected, what, target=target)
        if undo is not None:
            key = next(self._seq)
            with self._lock:
                self._healing[key] = undo
            self._push(self.t0 + injected + for_s, functools.partial(self._heal, key))

    def _heal(self, key: int) -> None:
        with self._lock:
            undo = self._healing.pop(key, None)
        if undo is not None:
            undo()

    @staticmethod
    def _thaw(pidfd: int) -> None:
        try:
            with contextlib.suppress(ProcessLookupError):
                signal.pidfd_send_signal(pidfd, signal.SIGCONT)
        finally:
            os.close(pidfd)

    def _kill_resource(self, fault: ScheduledFault, scheduled: float) -> None:
        managers = (
            [fault.target]
            if fault.target is not None
            else [
                m.name
                for m in self.plan.managers()
                if m.isolation == "process" and m.host in (None, self._home)
            ]
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
        if start_time(pid) != created:
            os.close(pidfd)
            self._record(fault, scheduled, None, f"process {pid} had just exited", skipped=True)
            return
        on_sent = functools.partial(
            self._sent,
            fault,
            scheduled,
            f"SIGKILL pid {pid} (a process of {name})",
            None,
            pid,
            target=name,
        )
        self._trigger.send(self.t0 + scheduled, signal.SIGKILL, pidfd, on_sent)
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
