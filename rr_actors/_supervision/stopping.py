"""Stopping a supervisor's children, and what a child that will not come back leaves behind.

```
 Node.stop ─► stop_all (reverse start order) ─┐
 Restarts: a group's siblings, a give-up ─────┼─► stop_child: its spec's shutdown (bounded by
 Starting: rolling back a failed start ───────┘   the deadline), then a kill ─► note_exit
                                                    └─ final? ─► forget
 forget ─► death watch (rule 19): a dead manager is lost (`lose`: its consumers' ids
           released, the ids held at it FATAL); one stopped for good is stale (rule 12)
 mark / unmark ─► DIRECTORY.mark_restarting: down for a moment, callers retry
```

Runs on the supervisor's thread (one step at a time). Its own state: whether the parent
stops this supervisor to start it again (`to_restart`), which keeps its managers marked
as restarting while they are down.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from rr_actors import events
from rr_actors._core import runtime
from rr_actors._core.directory import DIRECTORY
from rr_actors._supervision.record import pid_of
from rr_actors._supervision.tree import consumer_down
from rr_actors.config import ManagerSpec, SupervisorSpec, managers

if TYPE_CHECKING:
    from rr_actors._supervision.children import Child
    from rr_actors._supervision.record import Record

__all__ = ["Stopping", "left", "mark", "registrar_names", "unmark"]

_MIN_STOP = 1e-3  # seconds a child still gets to stop when an overall stop bound ran out


def left(deadline: float | None) -> float | None:
    """Seconds left until `deadline` (at least 1 ms), or `None` without one."""
    if deadline is None:
        return None
    return max(deadline - runtime.monotonic(), _MIN_STOP)


def registrar_names(spec: ManagerSpec | SupervisorSpec) -> list[str]:
    """The registrar names of a child: its own, or those of the managers below it."""
    if isinstance(spec, ManagerSpec):
        return [spec.name]
    return [manager.name for manager in managers(spec)]


def mark(child: Child) -> None:
    """`child` (its managers, for a nested supervisor) is down and will be restarted:
    its callers get `RegistrarUnavailableError` (retry), not `RegistrarStoppedError`."""
    DIRECTORY.mark_restarting(registrar_names(child.spec))


def unmark(child: Child) -> None:
    """`child` serves again, or is down for good: the restart mark goes."""
    DIRECTORY.mark_restarting(registrar_names(child.spec), restarting=False)


class Stopping:
    """Stops children, and releases what those that will not come back held.

    Args:
        record: the supervisor whose children it stops.
    """

    def __init__(self, record: Record) -> None:
        self.record = record
        self.to_restart = False  # the parent stops this tree to start it again

    def stop_all(self, deadline: float | None = None, *, restarting: bool = False) -> None:
        """Stop every child in reverse start order, each for good (`restarting`: the
        parent starts this supervisor again, its managers stay marked meanwhile)."""
        self.to_restart = restarting
        for child in reversed(self.record.children):
            self.stop_child(child, final=True, deadline=deadline, restarting=restarting)

    def stop_child(
        self,
        child: Child,
        *,
        final: bool,
        deadline: float | None = None,
        restarting: bool = False,
    ) -> None:
        """Stop a running child (its spec's shutdown, bounded by `deadline`, then a kill).

        `final`: it is not started again by this supervisor (`forget`). `restarting`: it
        is stopped to be started again (marked `DIRECTORY.mark_restarting`).
        """
        running = child.running
        if running is None:
            if final:
                child.incarnation += 1  # an exit still queued for it (a failed start) is stale
                dead = child.state == "restarting"  # it crashed and will not come back now
                if child.state != "exited":
                    child.state = "stopped"
                self.forget(child, dead=dead)
            return
        child.state = "stopping"
        child.incarnation += 1  # its watcher's exit event is now stale
        self.record.publish()
        limit = left(deadline)
        if isinstance(child.spec, ManagerSpec):
            limit = child.spec.shutdown if limit is None else min(limit, child.spec.shutdown)
        pid = pid_of(child)
        result = running.stop(limit, restarting=restarting)
        child.running = None
        child.state = "stopped"
        child.last_exit = result.reason
        self.note_exit(child, pid, result.reason, stopped=True)
        if final:
            self.forget(child, dead=not result.clean)

    def note_exit(
        self, child: Child, pid: int, reason: str, *, normal: bool = False, stopped: bool = False
    ) -> None:
        """Note when `child` went down, and publish `ChildExited`.

        `normal`: it ended normally; `stopped`: this supervisor stopped it (a shutdown,
        a sibling taken down): no exit the restart intensity counts.
        """
        tree = self.record.tree
        tree.down_since[child.name] = runtime.monotonic()
        publisher = tree.events.publisher
        if publisher.active:
            spec = self.record.spec
            publisher.publish(
                events.ChildExited(
                    self.record.name,
                    child.name,
                    pid,
                    reason,
                    child.spec.restart,
                    normal,
                    stopped,
                    spec.max_restarts,
                    spec.period,
                    spec.strategy,
                    tuple(c.name for c in self.record.children),
                )
            )

    def forget(self, child: Child, *, dead: bool) -> None:
        """The child will not come back: release what it held (death watch) if it died.

        Its callers get `RegistrarStoppedError` (or, if it died, `...UnavailableError`)
        from now on, unless the parent is stopping this whole supervisor to restart it.
        """
        if not self.to_restart:
            unmark(child)
        if isinstance(child.spec, ManagerSpec):
            DIRECTORY.expect_restart(child.name, expected=False)
            if dead:
                self.lose(child.name)
            elif not self.to_restart:  # stopped, and nobody starts it again
                record = self.record
                consumer_down(record.root(), child.name, record.tree.processes.system, stopped=True)
        elif child.gave_up is not None:  # a nested supervisor gave up, and stays down:
            for name in registrar_names(child.spec):  # nobody restarts its managers
                self.lose(name)

    def lose(self, name: str) -> None:
        """Manager `name` is gone and nobody will restart it (death watch, rule 19):
        its consumers' ids are released, and the ids held at it are `FATAL`."""
        DIRECTORY.expect_restart(name, expected=False)
        record = self.record
        consumer_down(record.root(), name, record.tree.processes.system)  # (recorded first:
        # a manager that starts meanwhile hears it then, `death_watch_missed`)
