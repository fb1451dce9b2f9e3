"""How a supervision tree's events reach its subscribers, in the supervisor's process.

```
 supervisors (Node) ── ChildStarted/Exited/Restarted, SupervisorGaveUp ──► publish ──┐
 a process manager's heartbeat ── ManagerOverloaded ────────────────────► publish ──┤
 thread manager's registrar ── relay_to ─────────────────────────────────► deliver ──┤
 process manager's registrar ─► its process's hub ─► Forwarder ─► control pipe       ├─► tree
      ─► ManagerProcess watcher thread ─► EventRelay.deliver ────────────► deliver ──┘  publisher
                                                                                  ─► subscriptions
```

Each event is logged at INFO once, where it happened (a manager process logs its own);
the tree's publisher only logs the supervisors' events. Manager processes forward their
events only while the tree has a listener, so a tree nobody watches builds no event in
its manager processes (`watch_listeners` switches them on and off). The switch reaches
each process asynchronously: what a process made before it heard "off" may still arrive
after a new listener came, so a forwarded event older than the last switch on (by its
`at`: the switch's time is read from the clock events' `at` is, `hlc.CLOCK`, a skewed
one included) is dropped; a new listener hears what happens from the moment it
subscribed.
"""

from __future__ import annotations

from typing import Any

from rr_actors import events
from rr_actors._core import hlc, runtime
from rr_actors._core.bus import Publisher
from rr_actors._process.heartbeat import Late
from rr_actors._process.manager import ManagerProcess
from rr_actors._registrar.actor import EVENT_LOG

__all__ = ["SWITCH_TIMEOUT", "EventRelay"]

SWITCH_TIMEOUT = 2.0
"""Seconds a first subscriber waits, at most, for the manager processes to forward."""


class EventRelay:
    """A tree's publisher, and the switch of its manager processes' forwarding.

    Attributes:
        publisher: where the tree's events are published (`Supervisor.subscribe`).
    """

    def __init__(self) -> None:
        self.publisher: Publisher[events.Event] = events.publisher(EVENT_LOG)
        self._lock = runtime.Lock()
        self._listened = False
        self._since = 0.0  # `hlc.CLOCK.wall()` of the last switch on: older events are dropped
        self._processes: list[ManagerProcess] = []
        self.publisher.watch_listeners(self._switch)

    @property
    def forwarding(self) -> bool:
        """Whether manager processes should forward their events now (someone listens)."""
        return self._listened

    def attach(self, process: ManagerProcess, *, forwarding: bool) -> None:
        """Switch a manager process with the others from now on.

        `forwarding` is what it was started with; if the tree's listeners changed since,
        it is told at once, so no switch is missed.
        """
        with self._lock:
            self._processes = [p for p in self._processes if not p.exited.is_set()]
            self._processes.append(process)
            if self._listened != forwarding:
                process.forward_events(self._listened)

    def sync(self, timeout: float) -> bool:
        """Block until what every manager process forwarded before the call was delivered.

        Returns:
            Whether every one answered within `timeout` seconds.
        """
        deadline = runtime.monotonic() + timeout
        with self._lock:
            processes = [p for p in self._processes if not p.exited.is_set()]
        answered = True
        for process in processes:  # (every one, also after one did not answer)
            answered = process.sync_events(max(0.0, deadline - runtime.monotonic())) and answered
        return answered

    def deliver(self, batch: list[Any]) -> None:
        """Hand events a manager process forwarded to the tree's subscribers (watcher
        thread); one made before the last switch on was made while nobody listened."""
        since = self._since
        for event in batch:
            if getattr(event, "at", since) >= since:
                self.publisher.deliver(event)

    def overloaded(self, supervisor: str, manager: str, pid: int, late: Late) -> None:
        """Manager process `manager` of `supervisor` answered its heartbeat late, excused
        (its watcher thread): a `ManagerOverloaded`, published here, where it was seen
        (logged at INFO too; the heartbeat's WARNING said it first)."""
        if self.publisher.active:
            self.publisher.publish(
                events.ManagerOverloaded(
                    supervisor,
                    manager,
                    pid,
                    late.silent,
                    late.bound,
                    late.excused,
                    late.busy,
                    late.queued,
                )
            )

    def _switch(self, listened: bool) -> None:
        with self._lock:
            if listened and not self._listened:
                self._since = hlc.CLOCK.wall()  # (the clock events' `at` reads)
            self._listened = listened
            self._processes = [p for p in self._processes if not p.exited.is_set()]
            for process in self._processes:
                process.forward_events(listened)
        if listened:  # the new listener hears what happens from now on: they all switched
            self.sync(SWITCH_TIMEOUT)
