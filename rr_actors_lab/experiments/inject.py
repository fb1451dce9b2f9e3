"""The injector: fires a run's fault schedule at its times, for real, and records each one.

```
 schedule (timed) ──────────────► Agenda: a heap of (monotonic time, action) ◄── on_event:
   (PREPARE_AHEAD before each       (the "rr-injector" thread)                  Triggered:
    fault is due)                                  │                           the n-th
                                                   ▼                           matching event
                             _fire: look up its target, by kind
       ┌───────────────────────────────────────────┴──────────────────────┐
 ManagerFaults (_manager_faults.py)                       HostFaults (_host_faults.py)
   kill_manager, hang_manager, cut_connections,             cut, partition, freeze,
   kill_resource: a pidfd ─► the trigger process            kill_router: at the due time,
   (_trigger.py) signals at the due time;          from here; undone `for` later
   a thread manager's crash; load_error (Supervisor.run_in)
       └──────────────────── FaultLog: every fault fired or skipped ──────────────────┘
 stop ──► the agenda stops; hung managers resumed, faults between hosts undone; what never
          fired recorded as skipped
```

Signals go through pidfds (never a pid reused since the look-up), from a separate
single-threaded process so that a busy run process does not make them late. A fault whose
manager is not running when prepared is recorded as skipped.
"""

from __future__ import annotations

import contextlib
import functools
import logging
from collections.abc import Callable

import rr_actors as rr
from rr_actors import events
from rr_actors_lab.experiments._agenda import Agenda, FaultLog, Fires, Triggered
from rr_actors_lab.experiments._host_faults import HostFaults
from rr_actors_lab.experiments._hosts import HostProcess
from rr_actors_lab.experiments._manager_faults import ManagerFaults
from rr_actors_lab.experiments._netns import HostNetwork
from rr_actors_lab.experiments._trigger import Trigger
from rr_actors_lab.experiments.plan import HOST_KINDS, Plan
from rr_actors_lab.experiments.results import FaultRecord
from rr_actors_lab.experiments.schedule import ScheduledFault

__all__ = ["Injector", "Trigger"]

logger = logging.getLogger("rr_actors.experiments")

PREPARE_AHEAD = 0.02
"""Seconds before a fault is due that the injector looks up its target and, for a signal,
hands a pidfd to the trigger process, which sends it at the due time."""


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
        step_span: with `--trace`, what each fault's firing runs under, a trace each:
            `otel.Exporting.root_span` (`step_span(name, attributes=...)`).
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
        step_span: Callable[..., contextlib.AbstractContextManager[object]] | None = None,
    ) -> None:
        self.sup = sup
        self._step_span = step_span
        self.plan = plan
        self.t0 = t0
        self.wall_t0 = wall_t0
        self._log = FaultLog()
        self._agenda = Agenda(self._abandon)
        self._trigger = Trigger()
        self._managers = ManagerFaults(
            sup, plan, t0, agenda=self._agenda, log=self._log, trigger=self._trigger
        )
        network, processes = hosts
        self._hosts = HostFaults(plan, t0, network, processes, agenda=self._agenda, log=self._log)
        self._triggered = Triggered((f for f in schedule if f.at is None), wall_t0)
        for fault in schedule:
            if fault.at is not None:
                self._schedule(fault, fault.at)

    @property
    def records(self) -> list[FaultRecord]:
        """Every fault fired or skipped so far (appended by several threads)."""
        return self._log.records

    @property
    def resumed(self) -> list[tuple[str, float]]:
        """`(manager, time)` of each hung manager resumed while it was still alive."""
        return self._managers.resumed

    # -- life cycle -----------------------------------------------------------------------

    def start(self) -> None:
        """Start firing (the schedule's time 0 is `t0`, which may be in the past)."""
        self._agenda.start()

    def stop(self, *, timeout: float = 5.0) -> None:
        """Stop firing; resume every hung manager now; record what did not fire as skipped (so every
        scheduled fault ends up in `records`); `timeout`: seconds for each of the injector's
        threads and the trigger process's last replies."""
        unfired = self._agenda.stop(timeout)
        self._managers.join(timeout)
        self._trigger.close(timeout=timeout)
        self._managers.resume_all()
        self._hosts.heal_all()  # links up again, frozen hosts thawed
        for fault in self._triggered.take():
            self._log.record(
                fault, None, None, "its trigger did not happen in the run", skipped=True
            )
        for fault, at in sorted(unfired, key=lambda fires: fires[1]):
            self._log.record(fault, at, None, "due after the run ended", skipped=True)

    def on_event(self, event: events.Event) -> None:
        """Look at one event of the run (from the subscriber thread); fire what it triggers."""
        for fault, at in self._triggered.matched(event):
            self._schedule(fault, at)

    # -- the agenda's thread --------------------------------------------------------------

    def _schedule(self, fault: ScheduledFault, at: float) -> None:
        """Fire `fault` at `at` (seconds from `t0`), waking `PREPARE_AHEAD` earlier."""
        fire = functools.partial(self._fire, fault, at)
        if not self._agenda.push(self.t0 + at - PREPARE_AHEAD, fire, (fault, at)):
            # a trigger that matched as the run ended
            self._log.record(fault, at, None, "due after the run ended", skipped=True)

    def _fire(self, fault: ScheduledFault, scheduled: float) -> None:
        step: contextlib.AbstractContextManager[object] = contextlib.nullcontext()
        if self._step_span is not None:  # (--trace: the fault is a step, a trace of its own)
            target = fault.target or "every process"
            attributes = {"rr_actors.fault": fault.kind, "rr_actors.target": target}
            step = self._step_span(f"fault {fault.kind} {target}", attributes=attributes)
        with step:
            if fault.kind in HOST_KINDS:
                self._hosts.fire(fault, scheduled)
            else:
                self._managers.fire(fault, scheduled)

    def _abandon(self, exc: Exception, left: list[Fires]) -> None:
        """The agenda's loop failed: record every fault still to come as skipped."""
        detail = f"not fired: the injector failed ({exc!r})"
        for fault, scheduled in left:
            self._log.record(fault, scheduled, None, detail, skipped=True)
        for fault in self._triggered.take():
            self._log.record(fault, None, None, detail, skipped=True)
