"""The faults between a run's hosts (with `[hosts]`): links cut, hosts frozen or killed.

```
 fire(fault, due) (the injector's thread): waits to the due time, then
   cut ─────────► ip link set <one>-<other> down ─┐
   partition ───► the side's links down ──────────┼─► recorded; `for` seconds later the
   freeze ──────► SIGSTOP the host's router process ┘   undo (agenda) ─► links up / SIGCONT
   kill_router ─► SIGKILL the host's router process (no undo)
 Injector.stop ──► heal_all: every undo still pending, now
```
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import logging
import os
import signal
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rr_actors_lab.experiments._agenda import Agenda, FaultLog
    from rr_actors_lab.experiments._hosts import HostProcess
    from rr_actors_lab.experiments._netns import HostNetwork
    from rr_actors_lab.experiments.plan import Plan
    from rr_actors_lab.experiments.schedule import ScheduledFault

__all__ = ["HostFaults"]

logger = logging.getLogger("rr_actors.experiments")


class HostFaults:
    """Fires the faults between hosts, and undoes each after its `for` (or at the end).

    Args:
        plan: the plan (its faults' `link`, `hosts`, `for`).
        t0: the monotonic start of the run's workload (the schedule's time 0).
        network: the run's namespaces and links (`None` without `[hosts]`).
        processes: the other hosts' processes, by host name.
        agenda: the injector's thread (waits to a due time; runs the undo).
        log: where each fault is recorded.
    """

    def __init__(
        self,
        plan: Plan,
        t0: float,
        network: HostNetwork | None,
        processes: dict[str, HostProcess],
        *,
        agenda: Agenda,
        log: FaultLog,
    ) -> None:
        self.plan = plan
        self.t0 = t0
        self.network = network
        self.processes = processes
        self.agenda = agenda
        self.log = log
        self._lock = threading.Lock()
        self._keys = itertools.count()
        self._healing: dict[int, Callable[[], None]] = {}  # key -> undo a cut, thaw a freeze

    def fire(self, fault: ScheduledFault, scheduled: float) -> None:
        """Fire `fault` at `scheduled` seconds from t0 (the injector's thread): a link or
        links down (`ip link set ... down`), a host process stopped or killed; its undo
        (links up, SIGCONT) `for` seconds later, or at `heal_all`."""
        plan, network = self.plan.faults[fault.fault], self.network
        assert network is not None
        for_s = plan.for_s or 0.0
        undo: Callable[[], None] | None = None
        if fault.kind == "cut":
            assert plan.link is not None
            one, other = plan.link
            target, what = f"{one}-{other}", f"link {one}-{other} down for {for_s:g} s"
            self.agenda.wait_until(self.t0 + scheduled)
            network.set_link(one, other, up=False)
            undo = functools.partial(network.set_link, one, other, up=True)
        elif fault.kind == "partition":
            side = plan.hosts
            target = "+".join(side)
            what = f"{target} cut from the other hosts for {for_s:g} s"
            self.agenda.wait_until(self.t0 + scheduled)
            network.set_links(side, up=False)
            undo = functools.partial(network.set_links, side, up=True)
        else:
            assert fault.target is not None
            target, host = fault.target, self.processes[fault.target]
            pid = host.pid
            try:
                pidfd = os.pidfd_open(pid) if pid is not None else None
            except ProcessLookupError:
                pidfd = None
            if pidfd is None:
                self.log.record(
                    fault, scheduled, None, f"host {target} was not running", skipped=True
                )
                return
            self.agenda.wait_until(self.t0 + scheduled)
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
                self.log.record(
                    fault, scheduled, None, f"host {target} had just exited", skipped=True
                )
                return
            if undo is None:
                os.close(pidfd)
        injected = time.monotonic() - self.t0
        self.log.record(fault, scheduled, injected, what, target=target)
        if undo is not None:
            key = next(self._keys)
            with self._lock:
                self._healing[key] = undo
            self.agenda.push(self.t0 + injected + for_s, functools.partial(self._heal, key))

    def heal_all(self) -> None:
        """Undo every fault still in force: links up again, frozen hosts thawed."""
        with self._lock:
            healing, self._healing = list(self._healing.values()), {}
        for undo in healing:
            try:
                undo()
            except Exception:
                logger.exception("could not undo a fault between hosts")

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
