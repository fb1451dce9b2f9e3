"""Restarting: a child's reported end, and what a supervisor does about it.

After OTP's `supervisor.erl` (`restart/3`, one clause per strategy): a child's end is
taken on the supervisor's thread; its restart type, the restart intensity and the
strategy decide whether it comes back, with which siblings, or whether the supervisor
gives up.

```
 ThreadManager watcher: its registrar actor stopped ──────────────────────────┐
 ManagerProcess watcher (_process/manager.py): the process ended; or no       │
   heartbeat answer within `hang_after` (hung) / unhealthy ─► killed ─────────┼─► Exited(name,
 a nested Node gave up (Starting: escalate) ──────────────────────────────────┤   incarnation,
 a restart failed to start (Restarts.on_restart) ─────────────────────────────┘   exit)
   ──► mailbox ──► Exits.on_exited: stale (an older incarnation, or this one gave up)? dropped
                   else: the exit noted (Stopping.note_exit: ChildExited)
 Restarts.after_exit(child, exit)
   ├─ its restart type (restarts_after): not restarted ─► exited ─► Stopping.forget
   ├─ RestartIntensity.add: more than max_restarts within period ─► give_up: every
   │    child stopped (reverse order), SupervisorGaveUp; on_gave_up (the parent: Exited)
   └─ take_down_with: the strategy's group (affected) stopped (reverse order); a
      sibling comes back unless temporary (restarts_with_group); marked
        ─► schedule: backoff ─► timer ── Restart(names, generation) ──► mailbox
 mailbox ─► Restarts.on_restart: Starting.start_child each whose latest Restart it is
            (a failure posts Exited: a crash)
 Node.stop / give_up ─► Restarts.cancel: a new generation, every pending Restart stale
```

An incarnation stopped on purpose was bumped by `Stopping.stop_child` first, so its
watcher's report is stale here. The decisions are pure: `RestartIntensity` (on the tree's
injectable clock) and `affected` here; a child's restart type read by `restarts_after` and
`restarts_with_group`, in `children.py`, below the roles, as the tree's lookups read it too.
`Exits` holds no state of its own: what it changes is the crashed child's record.
`Restarts` holds the intensity window, the generation and timers of pending restarts, and
whether (and why) this supervisor gave up.
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from rr_actors import events
from rr_actors._core import runtime
from rr_actors._core.timers import Cancellable
from rr_actors._process.manager import ManagerExit
from rr_actors._supervision.children import NestedSupervisor, restarts_after, restarts_with_group
from rr_actors._supervision.record import Exited, Restart, pid_of
from rr_actors._supervision.stopping import mark, registrar_names
from rr_actors._supervision.tree import Clock
from rr_actors.config import Strategy
from rr_actors.errors import SupervisorGaveUpError

if TYPE_CHECKING:
    from rr_actors._supervision.children import Child
    from rr_actors._supervision.record import Record
    from rr_actors._supervision.starting import Starting
    from rr_actors._supervision.stopping import Stopping

__all__ = ["Exits", "RestartIntensity", "Restarts", "affected"]

logger = logging.getLogger("rr_actors")


class Exits:
    """Takes a child's reported end: drops a stale one, notes it, hands it to `Restarts`.

    Args:
        record: the supervisor whose children it watches.
        restarts: decides what comes next (and knows whether this supervisor gave up).
        stopping: notes the exit (`ChildExited`).
    """

    def __init__(self, record: Record, restarts: Restarts, stopping: Stopping) -> None:
        self.record = record
        self.restarts = restarts
        self.stopping = stopping

    def on_exited(self, event: Exited) -> None:
        """Child `event.name`'s incarnation `event.incarnation` ended with `event.exit`."""
        record = self.record
        child = next((c for c in record.children if c.name == event.name), None)
        if child is None or child.incarnation != event.incarnation or self.restarts.gave_up:
            return  # a stale event: that incarnation was stopped on purpose
        if isinstance(child.running, NestedSupervisor):
            nested = child.running.node
            child.gave_up = nested.gave_up
            nested.stop()  # it gave up: end its mailbox thread
        pid = pid_of(child)
        child.running = None
        child.last_exit = event.exit.reason
        self.stopping.note_exit(child, pid, event.exit.reason, normal=event.exit.normal)
        logger.warning(
            "supervisor %s: child %s exited: %s", record.name, child.name, event.exit.reason
        )
        self.restarts.after_exit(child, event.exit)


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
        self._timers: dict[int, Cancellable] = {}  # id(Restart) -> its pending backoff timer
        self._due: dict[str, Restart] = {}  # each child's latest scheduled Restart

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
        self._timers.pop(id(event), None)  # (it ran: nothing to cancel any more)
        if event.generation != self._generation or self.gave_up is not None:
            return
        for child in record.children:
            if child.state != "restarting" or self._due.get(child.name) is not event:
                continue  # not in it, or a later Restart (its group's) brings it back
            try:
                self.starting.start_child(child)
            except BaseException as exc:  # (a setup's sys.exit() too, as at the first start)
                logger.exception("supervisor %s: restart of %s failed", record.name, child.name)
                child.running = None
                failed = ManagerExit(f"failed to start: {exc}", normal=False)
                record.post(Exited(child.name, child.incarnation, failed))
                return
            record.publish()

    def cancel(self) -> None:
        """Make every scheduled restart stale (new generation) and cancel its timer."""
        self._generation += 1
        for timer in self._timers.values():
            timer.cancel()
        self._timers.clear()
        self._due.clear()

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
        self._due.update(dict.fromkeys(names, event))  # an earlier one of theirs is stale
        if delay <= 0:
            record.post(event)
            return
        logger.info("supervisor %s: restarting %s in %.3f s", record.name, ", ".join(names), delay)
        tree.restart_due.update(dict.fromkeys(names, runtime.wall() + delay))  # (the observer's)
        record.publish()
        self._timers[id(event)] = tree.timer(delay, lambda: record.post(event))

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


# -- the pure decisions: no threads, no processes ----------------------------------------


class RestartIntensity:
    """OTP's restart intensity: at most `max_restarts` restarts within `period` seconds.

    Pure logic over an injectable clock (no threads).
    """

    def __init__(self, max_restarts: int, period: float, clock: Clock | None = None) -> None:
        self.max_restarts = max_restarts
        self.period = period
        self.clock = runtime.monotonic if clock is None else clock
        self._times: collections.deque[float] = collections.deque()

    def add(self) -> bool:
        """Count one restart now; return `False` if that exceeds the intensity (give up)."""
        now = self.clock()
        self._times.append(now)
        while self._times and now - self._times[0] >= self.period:
            self._times.popleft()
        return len(self._times) <= self.max_restarts

    @property
    def recent(self) -> int:
        """Restarts counted within the current window (this one included, after `add`)."""
        return len(self._times)


def affected(strategy: Strategy, names: Sequence[str], crashed: str) -> tuple[str, ...]:
    """The children a crash of `crashed` takes down with it, in start order, itself included.

    Args:
        strategy: `"one_for_one"` (itself), `"one_for_all"` (every child) or
            `"rest_for_one"` (itself and the children started after it).
        names: every child's name, in start order.
        crashed: the child that crashed.
    """
    if strategy == "one_for_one":
        return (crashed,)
    if strategy == "one_for_all":
        return tuple(names)
    return tuple(names[names.index(crashed) :])
