"""One supervisor of a tree: a small state record plus named steps on its mailbox thread.

After OTP's `supervisor.erl` (a state record, `restart/3` with one clause per strategy,
`do_*` helpers): the steps below run on the node's thread (a `SerialExecutor`), one event at a time,
and decide with the pure policy in `rr_actors._supervision.policy`.

```
 watcher thread ── Exited(name, incarnation, exit) ──► mailbox ──► on_exited
                                                                   ├─ not restarted: exited
                                                                   ├─ intensity exceeded: give_up
                                                                   └─ take the group down, schedule
 timer (backoff) ── Restart(names, generation) ─────► mailbox ──► on_restart: start_child ...
```

A nested supervisor is a `Node` too; when it gives up it tells its parent, which sees an
exited child (OTP: a supervisor that gives up exits with `shutdown`).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
import time
from collections.abc import Callable
from typing import TypeVar

from rr_actors import events
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.serial import SerialExecutor
from rr_actors._core.timers import Cancellable
from rr_actors._process.manager import ManagerExit
from rr_actors._supervision.children import (
    Child,
    NestedSupervisor,
    ProcessManager,
    ThreadManager,
)
from rr_actors._supervision.policy import (
    RestartIntensity,
    affected,
    restarts_after,
    restarts_with_group,
)
from rr_actors._supervision.retry import give_back_abandoned
from rr_actors._supervision.tree import (
    Tree,
    comes_back,
    consumer_down,
    death_watch_missed,
    lost_everything,
)
from rr_actors.config import ManagerSpec, RegistrarConfig, SupervisorSpec, managers
from rr_actors.errors import RrError, SupervisorGaveUpError

__all__ = ["Node"]

logger = logging.getLogger("rr_actors")

T = TypeVar("T")

_MIN_STOP = 1e-3  # seconds a child still gets to stop when an overall stop bound ran out


@dataclasses.dataclass(frozen=True)
class Exited:
    """Child `name`'s incarnation `incarnation` ended (posted by its watcher)."""

    name: str
    incarnation: int
    exit: ManagerExit


@dataclasses.dataclass(frozen=True)
class Restart:
    """Restart these children (posted at once, or by a backoff timer), unless stale."""

    names: tuple[str, ...]
    generation: int


def _pid_of(child: Child) -> int:
    """The process a child runs in: its own (a process manager), else this one."""
    running = child.running
    pid = running.pid if running is not None else None
    return pid if pid is not None else os.getpid()


def left(deadline: float | None) -> float | None:
    """Seconds left until `deadline` (at least 1 ms), or `None` without one."""
    if deadline is None:
        return None
    return max(deadline - time.monotonic(), _MIN_STOP)


class Node:
    """One supervisor of a tree (the root or a nested one): its state and its steps.

    Args:
        spec: what it supervises and how.
        tree: what the whole tree shares.
        parent: the supervisor above it (`None` for the root).
    """

    def __init__(self, spec: SupervisorSpec, tree: Tree, parent: Node | None = None) -> None:
        self.spec = spec
        self.tree = tree
        self.parent = parent
        self.state_dir = spec.state_dir
        if self.state_dir is None and parent is not None:
            self.state_dir = parent.state_dir
        self.children = [Child(child) for child in spec.children]
        for child in self.children:  # a new incarnation: say how the last one ended
            last = tree.latest.get(child.name)
            child.last_exit = last.last_exit if last is not None else None
            child.published = child.info(tree.restarts.get(child.name, 0))
        self.intensity = RestartIntensity(spec.max_restarts, spec.period, tree.clock)
        self.gave_up: SupervisorGaveUpError | None = None
        self.giving_up = False
        self.on_gave_up: Callable[[SupervisorGaveUpError], None] | None = None
        self._mailbox = SerialExecutor(f"rr-supervisor-{spec.name}")
        self._generation = 0
        self._timers: list[Cancellable] = []
        self._running = False
        self._stopping_to_restart = False  # the parent stops this tree to start it again

    @property
    def name(self) -> str:
        """The supervisor's name."""
        return self.spec.name

    def root(self) -> Node:
        """The tree's root supervisor (this one, or the top of its parents)."""
        node = self
        while node.parent is not None:
            node = node.parent
        return node

    # -- life cycle (any thread but its own) -------------------------------------------

    def start(self) -> None:
        """Start the mailbox thread and every child in order.

        Raises:
            SupervisorGaveUpError: a child failed to start (the others were stopped).
        """
        self._running = True
        try:
            self._mailbox.call(functools.partial(self._then_publish, self._start_all))
        except BaseException:
            self._running = False
            self._mailbox.finish()
            self._mailbox.join(30.0)
            raise

    def stop(
        self,
        timeout: float | None = None,
        *,
        deadline: float | None = None,
        restarting: bool = False,
    ) -> None:
        """Stop every child in reverse start order, then the mailbox thread (idempotent).

        With `restarting`, the parent stops this supervisor to start it again (a group
        restart): its managers' callers meanwhile get `RegistrarUnavailableError`.
        """
        if deadline is None and timeout is not None:
            deadline = time.monotonic() + timeout
        if not self._running:
            return
        self._running = False
        if not self._mailbox.closed:
            stop_all = functools.partial(self._stop_all, deadline, restarting=restarting)
            try:
                self._mailbox.call(functools.partial(self._then_publish, stop_all))
            except RrError:
                logger.exception("supervisor %s: stopping its children failed", self.name)
            self._mailbox.finish()
            self._mailbox.join(60.0)

    def cast(self, fn: Callable[[], object]) -> None:
        """Run `fn` on this supervisor's thread after what is queued now."""
        self._mailbox.submit(functools.partial(self._then_publish, fn))

    # -- the mailbox -------------------------------------------------------------------

    def _post(self, event: object) -> None:
        """Queue `event` for this supervisor's thread (any thread; returns at once)."""
        self._mailbox.submit(functools.partial(self._then_publish, self._handle, event))

    def _then_publish(self, fn: Callable[..., T], *args: object) -> T:
        """Run `fn(*args)`, then `publish` (this supervisor's thread, one step at a time;
        what `fn` raises is logged by the thread, or raised to `call`'s caller)."""
        try:
            return fn(*args)
        finally:
            self.publish()

    def _handle(self, event: object) -> None:
        if isinstance(event, Exited):
            self._on_exited(event)
        elif isinstance(event, Restart):
            self._on_restart(event)

    def publish(self) -> None:
        """Publish the children's snapshots and wake every waiter of the tree."""
        tree = self.tree
        with tree.cond:
            for child in self.children:
                child.published = child.info(tree.restarts.get(child.name, 0))
                tree.latest[child.name] = child.published
            tree.changed()

    def _post_exit(self, child: Child) -> Callable[[ManagerExit], None]:
        name, incarnation = child.name, child.incarnation

        def post(result: ManagerExit) -> None:
            self._post(Exited(name, incarnation, result))

        return post

    # -- starting and stopping children (mailbox thread) --------------------------------

    def _config(self, spec: ManagerSpec) -> RegistrarConfig:
        if spec.config is not None:
            return spec.config
        if self.state_dir is None:
            return RegistrarConfig(name=spec.name)
        return RegistrarConfig(
            name=spec.name,
            backup_path=os.path.join(os.fspath(self.state_dir), f"{spec.name}.db"),
            save_on_modify=True,
        )

    def _start_child(self, child: Child) -> None:
        """Start one incarnation of `child`; raise what its start raised."""
        child.incarnation += 1
        child.state = "starting"
        self.tree.restart_due.pop(child.name, None)
        if isinstance(child.spec, ManagerSpec):
            comes_back(child.name)  # no longer gone for good
        self.publish()
        spec, tree = child.spec, self.tree
        post = self._post_exit(child)
        if isinstance(spec, SupervisorSpec):
            child.running = self._start_nested(spec, child.incarnation)
            child.gave_up = None
        else:
            if spec.restart != "temporary":
                DIRECTORY.expect_restart(spec.name)  # death watch waits for us
            config = self._config(spec)
            if spec.isolation == "thread":
                system = tree.processes.system
                child.running = ThreadManager(spec, config, system, post, tree.events)
            else:
                processes = tree.processes
                address = processes.system.address if processes.system is not None else None
                try:
                    child.running = ProcessManager.start(
                        spec,
                        processes.setups[spec.name],
                        config,
                        address,
                        post,
                        processes.spares,
                        tree.events,
                    )
                finally:
                    if processes.spares is not None:  # after this start was published
                        self.cast(processes.spares.refill)
        child.state = "running"
        self._unmark(child)  # it serves again
        restarted = child.name in tree.started
        tree.count_start(child.name)
        self._published_start(child, restarted=restarted)
        give_back_abandoned(tree, child.name)
        if restarted and isinstance(spec, ManagerSpec):
            death_watch_missed(child.name)
            if self._config(spec).backup_path is None:  # (one with a backup asks itself)
                lost_everything(self.root(), child.name, tree.processes.system)

    def _published_start(self, child: Child, *, restarted: bool) -> None:
        """Publish `ChildStarted`, or `ChildRestarted` with the time it was down."""
        down_since = self.tree.down_since.pop(child.name, None)
        publisher = self.tree.events.publisher
        if not publisher.active:
            return
        pid = _pid_of(child)
        if not restarted:
            publisher.publish(events.ChildStarted(self.name, child.name, pid))
            return
        restart_s = 0.0 if down_since is None else time.monotonic() - down_since
        publisher.publish(events.ChildRestarted(self.name, child.name, pid, restart_s))

    def _published_exit(self, child: Child, pid: int, reason: str) -> None:
        """Note when `child` went down, and publish `ChildExited`."""
        self.tree.down_since[child.name] = time.monotonic()
        publisher = self.tree.events.publisher
        if publisher.active:
            publisher.publish(events.ChildExited(self.name, child.name, pid, reason))

    def _start_nested(self, spec: SupervisorSpec, incarnation: int) -> NestedSupervisor:
        nested = Node(spec, self.tree, self)

        def escalate(error: SupervisorGaveUpError) -> None:
            # OTP: a supervisor that gives up exits with `shutdown`: normal for `transient`
            gave_up = ManagerExit(f"gave up: {error}", normal=True)
            self._post(Exited(spec.name, incarnation, gave_up))

        nested.on_gave_up = escalate
        nested.start()
        return NestedSupervisor(nested)

    def _start_all(self) -> None:
        started: list[Child] = []
        for child in self.children:
            try:
                self._start_child(child)
            except BaseException as exc:
                child.state = "stopped"
                child.last_exit = f"failed to start: {exc}"
                self._forget(child, dead=False)  # no restart is coming: no death-watch hold
                for done in reversed(started):
                    self._stop_child(done, final=True)
                raise SupervisorGaveUpError(
                    f"supervisor {self.name!r}: child {child.name!r} failed to start: {exc}"
                ) from exc
            started.append(child)
            self.publish()

    def _stop_child(
        self,
        child: Child,
        *,
        final: bool,
        deadline: float | None = None,
        restarting: bool = False,
    ) -> None:
        """Stop a running child (its spec's shutdown, bounded by `deadline`, then a kill).

        `restarting`: it is stopped to be started again (marked `DIRECTORY.mark_restarting`).
        """
        running = child.running
        if running is None:
            if final:
                dead = child.state == "restarting"  # it crashed and will not come back now
                if child.state != "exited":
                    child.state = "stopped"
                self._forget(child, dead=dead)
            return
        child.state = "stopping"
        child.incarnation += 1  # its watcher's exit event is now stale
        self.publish()
        limit = left(deadline)
        if isinstance(child.spec, ManagerSpec):
            limit = child.spec.shutdown if limit is None else min(limit, child.spec.shutdown)
        pid = _pid_of(child)
        result = running.stop(limit, restarting=restarting)
        child.running = None
        child.state = "stopped"
        child.last_exit = result.reason
        self._published_exit(child, pid, result.reason)
        if final:
            self._forget(child, dead=not result.clean)

    def _forget(self, child: Child, *, dead: bool) -> None:
        """The child will not come back: release what it held (death watch) if it died.

        Its callers get `RegistrarStoppedError` (or, if it died, `...UnavailableError`)
        from now on, unless the parent is stopping this whole supervisor to restart it.
        """
        if not self._stopping_to_restart:
            self._unmark(child)
        if isinstance(child.spec, ManagerSpec):
            DIRECTORY.expect_restart(child.name, expected=False)
            if dead:
                self._lose(child.name)
            elif not self._stopping_to_restart:  # stopped, and nobody starts it again
                consumer_down(self.root(), child.name, self.tree.processes.system, stopped=True)
        elif child.gave_up is not None:  # a nested supervisor gave up, and stays down:
            for name in _registrar_names(child.spec):  # nobody restarts its managers
                self._lose(name)

    def _lose(self, name: str) -> None:
        """Manager `name` is gone and nobody will restart it (death watch, rule 19):
        its consumers' ids are released, and the ids held at it are `FATAL`."""
        DIRECTORY.expect_restart(name, expected=False)
        consumer_down(self.root(), name, self.tree.processes.system)  # (recorded first:
        # a manager that starts meanwhile hears it then, `death_watch_missed`)

    @staticmethod
    def _mark(child: Child) -> None:
        """`child` (its managers, for a nested supervisor) is down and will be restarted:
        its callers get `RegistrarUnavailableError` (retry), not `RegistrarStoppedError`."""
        DIRECTORY.mark_restarting(_registrar_names(child.spec))

    @staticmethod
    def _unmark(child: Child) -> None:
        DIRECTORY.mark_restarting(_registrar_names(child.spec), restarting=False)

    def _cancel_restarts(self) -> None:
        """Make every scheduled restart stale (new generation) and cancel its timer."""
        self._generation += 1
        for timer in self._timers:
            timer.cancel()
        self._timers.clear()

    def _stop_all(self, deadline: float | None = None, *, restarting: bool = False) -> None:
        self._cancel_restarts()
        self._stopping_to_restart = restarting
        for child in reversed(self.children):
            self._stop_child(child, final=True, deadline=deadline, restarting=restarting)

    # -- crashes and restarts (mailbox thread) ------------------------------------------

    def _on_exited(self, event: Exited) -> None:
        child = next((c for c in self.children if c.name == event.name), None)
        if child is None or child.incarnation != event.incarnation or self.gave_up:
            return  # a stale event: that incarnation was stopped on purpose
        if isinstance(child.running, NestedSupervisor):
            nested = child.running.node
            child.gave_up = nested.gave_up
            nested.stop()  # it gave up: end its mailbox thread
        pid = _pid_of(child)
        child.running = None
        child.last_exit = event.exit.reason
        self._published_exit(child, pid, event.exit.reason)
        logger.warning(
            "supervisor %s: child %s exited: %s", self.name, child.name, event.exit.reason
        )
        if not restarts_after(child.spec.restart, normal=event.exit.normal):
            child.state = "exited"
            self._forget(child, dead=not event.exit.clean)
            return
        child.state = "restarting"
        self._mark(child)
        self.publish()
        if not self.intensity.add():
            self._give_up(child)
            return
        self._schedule(self._take_down_with(child))

    def _take_down_with(self, crashed: Child) -> tuple[str, ...]:
        """Stop the siblings the strategy restarts with `crashed`; the names to restart.

        Siblings stop in reverse start order. A `temporary` sibling is stopped for good;
        every other one comes back, a `transient` one that had exited normally too (OTP).
        """
        names = affected(self.spec.strategy, [c.name for c in self.children], crashed.name)
        group = [c for c in self.children if c.name in names]
        for other in reversed(group):
            if other is crashed:
                continue
            comes_back = restarts_with_group(other.spec.restart)
            if comes_back:  # down for a moment, not stopped: callers may retry
                self._mark(other)
            if other.running is not None:
                self._stop_child(other, final=not comes_back, restarting=comes_back)
                other.state = "restarting" if comes_back else "exited"
            elif other.state == "exited" and comes_back:
                other.state = "restarting"
        return tuple(c.name for c in group if c.state == "restarting")

    def _schedule(self, names: tuple[str, ...]) -> None:
        tree = self.tree
        delay = self.spec.backoff.delay(self.intensity.recent, tree.random)
        event = Restart(names, self._generation)
        if delay <= 0:
            self._post(event)
            return
        logger.info("supervisor %s: restarting %s in %.3f s", self.name, ", ".join(names), delay)
        tree.restart_due.update(dict.fromkeys(names, time.time() + delay))  # (the observer's)
        self.publish()
        self._timers.append(tree.timer(delay, lambda: self._post(event)))

    def _on_restart(self, event: Restart) -> None:
        if event.generation != self._generation or self.gave_up is not None:
            return
        for child in self.children:
            if child.name not in event.names or child.state != "restarting":
                continue
            try:
                self._start_child(child)
            except Exception as exc:
                logger.exception("supervisor %s: restart of %s failed", self.name, child.name)
                child.running = None
                failed = ManagerExit(f"failed to start: {exc}", normal=False)
                self._post(Exited(child.name, child.incarnation, failed))
                return
            self.publish()

    def _give_up(self, crashed: Child) -> None:
        """Stop every child in reverse start order, then report the give-up (OTP: shutdown).

        Waiters conclude nothing while it runs (`giving_up`); the give-up is published
        once every child has stopped.
        """
        error = SupervisorGaveUpError(
            f"supervisor {self.name!r} gave up: more than {self.spec.max_restarts} restart(s) "
            f"within {self.spec.period:g} s (last: {crashed.name!r} {crashed.last_exit})"
        )
        logger.error("%s", error)
        self.giving_up = True
        self._cancel_restarts()
        for child in reversed(self.children):
            if child is crashed or child.running is None:
                # (below the root, the parent decides: it may restart this supervisor)
                dead = child.state != "exited" and self.parent is None
                child.state = "stopped"
                self._forget(child, dead=dead)
            else:
                self._stop_child(child, final=True)
        if self.parent is None:  # nobody restarts this tree: every manager is lost
            for name in _registrar_names(self.spec):
                self._lose(name)
        for child in self.children:
            child.gave_up = child.gave_up or error
        self.gave_up = error  # after the children stopped: waiters then see a settled tree
        self.publish()
        publisher = self.tree.events.publisher
        if publisher.active:
            publisher.publish(
                events.SupervisorGaveUp(
                    self.name, str(error), self.spec.max_restarts, self.spec.period
                )
            )
        if self.on_gave_up is not None:
            self.on_gave_up(error)


def _registrar_names(spec: ManagerSpec | SupervisorSpec) -> list[str]:
    """The registrar names of a child: its own, or those of the managers below it."""
    if isinstance(spec, ManagerSpec):
        return [spec.name]
    return [manager.name for manager in managers(spec)]
