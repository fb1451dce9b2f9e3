"""Restart decisions: the restart type, the intensity window, the strategy, the backoff.

After OTP's `supervisor.erl` (`restart/3`, one clause per strategy): decided with the pure
policy of `rr_actors._supervision.policy`, carried out on the supervisor's thread.

```
 Exits ─► after_exit(child, exit)
            ├─ not restarted (its restart type): exited ─► Stopping.forget
            ├─ intensity exceeded ─► give_up: every child stopped (reverse order),
            │                        SupervisorGaveUp; on_gave_up (the parent: Exited)
            └─ take_down_with: the strategy's group stopped (reverse order), marked
               ─► schedule: backoff ─► timer ── Restart(names, generation) ──► mailbox
 mailbox ─► on_restart: Starting.start_child each (a failure posts Exited: a crash)
 Node.stop / give_up ─► cancel: a new generation, every pending Restart stale
```

Its own state: the intensity window, the generation and timers of pending restarts,
and whether (and why) this supervisor gave up.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

from rr_actors import events
from rr_actors._core import runtime
from rr_actors._core.timers import Cancellable
from rr_actors._process.manager import ManagerExit
from rr_actors._supervision.policy import (
    RestartIntensity,
    affected,
    restarts_after,
    restarts_with_group,
)
from rr_actors._supervision.record import Exited, Restart
from rr_actors._supervision.stopping import mark, registrar_names
from rr_actors.errors import SupervisorGaveUpError

if TYPE_CHECKING:
    from rr_actors._supervision.children import Child
    from rr_actors._supervision.record import Record
    from rr_actors._supervision.starting import Starting
    from rr_actors._supervision.stopping import Stopping

__all__ = ["Restarts"]

logger = logging.getLogger("rr_actors")


class Restarts:
    """Decides whether and how a crashed child comes back, and gives up past the intensity.

    Args:
        record: the supervisor whose children it restarts.
        starting: starts them again.
        stopping: stops the siblings that go down with a crashed child.
        on_gave_up: called (on this supervisor's thread) when it gave up: a nested
            supervisor's parent posts itself an `Exited`.
    """

    def __init__(
        self,
        record: Record,
        starting: Starting,
        stopping: Stopping,
        *,
        on_gave_up: Callable[[SupervisorGaveUpError], None] | None = None,
    ) -> None:
        self.record = record
        self.starting = starting
        self.stopping = stopping
        self.on_gave_up = on_gave_up
        spec = record.spec
        self.intensity = RestartIntensity(spec.max_restarts, spec.period, record.tree.clock)
        self.gave_up: SupervisorGaveUpError | None = None
        self.giving_up = False
        self._generation = 0
        self._timers: list[Cancellable] = []

    def after_exit(self, child: Child, exit: ManagerExit) -> None:
        """`child` ended on its own (`exit`): leave it down, restart it, or give up."""
        if not restarts_after(child.spec.restart, normal=exit.normal):
            child.state = "exited"
            self.stopping.forget(child, dead=not exit.clean)
            return
        child.state = "restarting"
        mark(child)
        self.record.publish()
        if not self.intensity.add():
            self.give_up(child)
            return
        self._schedule(self._take_down_with(child))

    def on_restart(self, event: Restart) -> None:
        """Start the children `event` names again (unless it is stale)."""
        record = self.record
        if event.generation != self._generation or self.gave_up is not None:
            return
        for child in record.children:
            if child.name not in event.names or child.state != "restarting":
                continue
            try:
                self.starting.start_child(child)
            except Exception as exc:
                logger.exception("supervisor %s: restart of %s failed", record.name, child.name)
                child.running = None
                failed = ManagerExit(f"failed to start: {exc}", normal=False)
                record.post(Exited(child.name, child.incarnation, failed))
                return
            record.publish()

    def cancel(self) -> None:
        """Make every scheduled restart stale (new generation) and cancel its timer."""
        self._generation += 1
        for timer in self._timers:
            timer.cancel()
        self._timers.clear()

    def _take_down_with(self, crashed: Child) -> tuple[str, ...]:
        """Stop the siblings the strategy restarts with `crashed`; the names to restart.

        Siblings stop in reverse start order. A `temporary` sibling is stopped for good;
        every other one comes back, a `transient` one that had exited normally too (OTP).
        """
        children = self.record.children
        names = affected(self.record.spec.strategy, [c.name for c in children], crashed.name)
        group = [c for c in children if c.name in names]
        for other in reversed(group):
            if other is crashed:
                continue
            comes_back = restarts_with_group(other.spec.restart)
            if comes_back:  # down for a moment, not stopped: callers may retry
                mark(other)
            if other.running is not None:
                self.stopping.stop_child(other, final=not comes_back, restarting=comes_back)
                other.state = "restarting" if comes_back else "exited"
            elif other.state == "exited" and comes_back:
                other.state = "restarting"
        return tuple(c.name for c in group if c.state == "restarting")

    def _schedule(self, names: tuple[str, ...]) -> None:
        record = self.record
        tree = record.tree
        delay = record.spec.backoff.delay(self.intensity.recent, tree.random)
        event = Restart(names, self._generation)
        if delay <= 0:
            record.post(event)
            return
        logger.info("supervisor %s: restarting %s in %.3f s", record.name, ", ".join(names), delay)
        tree.restart_due.update(dict.fromkeys(names, runtime.wall() + delay))  # (the observer's)
        record.publish()
        self._timers.append(tree.timer(delay, lambda: record.post(event)))

    def give_up(self, crashed: Child) -> None:
        """Stop every child in reverse start order, then report the give-up (OTP: shutdown).

        Waiters conclude nothing while it runs (`giving_up`); the give-up is published
        once every child has stopped.
        """
        record, stopping = self.record, self.stopping
        spec = record.spec
        error = SupervisorGaveUpError(
            f"supervisor {record.name!r} gave up: more than {spec.max_restarts} restart(s) "
            f"within {spec.period:g} s (last: {crashed.name!r} {crashed.last_exit})"
        )
        logger.error("%s", error)
        self.giving_up = True
        self.cancel()
        for child in reversed(record.children):
            if child is crashed or child.running is None:
                # (below the root, the parent decides: it may restart this supervisor)
                dead = child.state != "exited" and record.parent is None
                child.state = "stopped"
                stopping.forget(child, dead=dead)
            else:
                stopping.stop_child(child, final=True)
        if record.parent is None:  # nobody restarts this tree: every manager is lost
            for name in registrar_names(spec):
                stopping.lose(name)
        for child in record.children:
            child.gave_up = child.gave_up or error
        self.gave_up = error  # after the children stopped: waiters then see a settled tree
        record.publish()
        publisher = record.tree.events.publisher
        if publisher.active:
            publisher.publish(
                events.SupervisorGaveUp(record.name, str(error), spec.max_restarts, spec.period)
            )
        if self.on_gave_up is not None:
            self.on_gave_up(error)
