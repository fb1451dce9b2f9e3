"""One supervisor and its restart policy: its record, its mailbox, a child's end and what
comes of it, and starting and stopping its children.

After OTP's `supervisor.erl`, one module over one record (`restart/3`, `start_children`,
`do_restart`, `terminate_children`): each event runs on the node's thread, one at a
time, and every step ends by publishing the children's snapshots to the tree's waiters.

```
              ┌────────────────── Node (one mailbox, one thread) ──────────────────────┐
 start ─────► │ Starting    start_all, start_child, nested Nodes     (start_children)  │
 stop ──────► │ Restarts.cancel, then Stopping.stop_all          (terminate_children)  │
 watcher ───► │ Exited ──► Exits.on_exited: stale? note the exit                       │
   threads    │              └─► Restarts.after_exit: restart type, intensity,         │
              │                  strategy, backoff, give up               (restart/3)  │
 timer ─────► │ Restart ─► Restarts.on_restart ─► Starting.start_child   (do_restart)  │
              │ Stopping    stop_child, stop_all, forget (death watch)                 │
              │ Record: spec, tree, children (Child records), post, cast, publish      │
              └────────────────────────────────────────────────────────────────────────┘
```

It reads top down, each role calling only the roles below it and owning its own state:
`Node`; restarting (`Exits`, `Restarts` on `children.decide`, `RestartIntensity`); `Starting`;
`Stopping`; what they share (`Exited`, `Restart`, `Record`). A nested supervisor is a
`Node` too. How a restart runs through the layers: "How a restart flows" in
docs/explanation/architecture.md.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import logging
import os
import sys
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

from rr_actors import events
from rr_actors._core import runtime, wire
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.serial import SerialExecutor
from rr_actors._platform.base import bound_reached
from rr_actors._process.child import HOOKS, provider_names
from rr_actors._process.control import POOL_GAVE_UP_EXIT, POOL_HUNG_EXIT, Announce
from rr_actors._process.heartbeat import Hang, Heartbeat, Look
from rr_actors._process.manager import ManagerExit
from rr_actors._supervision.children import (
    Child,
    Decision,
    Level,
    NestedSupervisor,
    ProcessManager,
    Running,
    ThreadManager,
    decide,
    is_pool,
    pool_manager,
)
from rr_actors._supervision.tree import (
    Clock,
    Ending,
    Tree,
    announce_started,
    comes_back,
    consumer_down,
    death_watch_missed,
    lost_everything,
    ran_before,
)
from rr_actors.config import (
    Durability,
    ManagerSpec,
    RegistrarConfig,
    RestartType,
    SupervisorSpec,
    managers,
)
from rr_actors.config import Steps as ProtocolSteps
from rr_actors.errors import ConfigError, RrError, SupervisorGaveUpError

if TYPE_CHECKING:
    from rr_actors._registrar import ResourceRegistrar
    from rr_actors._transport.messenger import Address, Transport

logger = logging.getLogger("rr_actors")

T = TypeVar("T")


# -- the node: the record, its mailbox, the roles it wires ---------------------------------


class Node:
    """One supervisor of a tree (the root or a nested one): its record, mailbox and roles.

    `state_dir`: the parent's (its managers' default, unless `spec` names one);
    `on_gave_up`: called on this supervisor's thread when it gives up.
    """

    def __init__(
        self,
        spec: SupervisorSpec,
        tree: Tree,
        parent: Node | None = None,
        *,
        state_dir: str | os.PathLike[str] | None = None,
        on_gave_up: Callable[[SupervisorGaveUpError], None] | None = None,
    ) -> None:
        self.spec = spec
        self.tree = tree
        self._parent = parent
        self.children = [Child(child) for child in spec.children]
        # looked up, not walked: a restart costs the same among 1,000 as among 10 (issue 69)
        self.by_name = {child.name: child for child in self.children}
        self.nested = [c for c in self.children if isinstance(c.spec, SupervisorSpec)]
        self.restart_types = {c.name: c.spec.restart for c in self.children}
        self.has_pipes = spec.has_processes()
        self._changed: dict[int, Child] = {}  # id -> a child to publish (in start order)
        for child in self.children:  # a new incarnation: say how the last one ended
            last = tree.latest.get(child.name)
            child.last_exit = last.last_exit if last is not None else None
            child.published = child.info(tree.restarts.get(child.name, 0))
            self._changed[id(child)] = child
            child.on_change = self._note_change
        self._mailbox = SerialExecutor(f"rr-supervisor-{spec.name}")
        tree.add_mailbox(self._mailbox)
        self._running = False
        own = spec.state_dir if spec.state_dir is not None else state_dir
        self.stopping = Stopping(self)
        self.starting = Starting(self, self.stopping, state_dir=own, nest=self._nest)
        self.restarts = Restarts(self, self.starting, self.stopping, on_gave_up=on_gave_up)
        self.exits = Exits(self, self.restarts, self.stopping)

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def parent(self) -> Node | None:
        return self._parent

    @property
    def gave_up(self) -> SupervisorGaveUpError | None:
        return self.restarts.gave_up

    @property
    def giving_up(self) -> bool:
        """Whether it is stopping its children to give up (waiters conclude nothing)."""
        return self.restarts.giving_up

    def root(self) -> Node:
        node = self
        while node.parent is not None:
            node = node.parent
        return node

    # -- life cycle (any thread but its own) -------------------------------------------

    def start(self) -> None:
        """Start the mailbox thread and every child in order (`SupervisorGaveUpError`)."""
        self._running = True
        try:
            self._mailbox.call(functools.partial(self._then_publish, self.starting.start_all))
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
        parallel: bool = False,
    ) -> None:
        """Stop every child in reverse start order, then the mailbox thread (idempotent;
        `restarting`: the parent starts it again, its managers' callers retry; `parallel`:
        at once where no dependency orders them, `Stopping.stop_in_parallel`)."""
        if deadline is None and timeout is not None:
            deadline = runtime.monotonic() + timeout
        if not self._running:
            return
        self._running = False
        if not self._mailbox.closed:
            stop_all = functools.partial(
                self._stop_all, deadline, restarting=restarting, parallel=parallel
            )
            try:
                self._mailbox.call(functools.partial(self._then_publish, stop_all))
            except RrError:
                logger.exception("supervisor %s: stopping its children failed", self.name)
            self._mailbox.finish()
            self._mailbox.join(60.0)

    def _stop_all(self, deadline: float | None, *, restarting: bool, parallel: bool) -> None:
        self.restarts.cancel()
        self.stopping.stop_all(deadline, restarting=restarting, parallel=parallel)

    def _nest(
        self, spec: SupervisorSpec, on_gave_up: Callable[[SupervisorGaveUpError], None]
    ) -> Node:
        nested = Node(
            spec, self.tree, self, state_dir=self.starting.state_dir, on_gave_up=on_gave_up
        )
        nested.start()
        return nested

    # -- the mailbox -------------------------------------------------------------------

    def cast(self, fn: Callable[[], object]) -> None:
        """Run `fn` on this supervisor's thread after what is queued now."""
        self._mailbox.submit(functools.partial(self._then_publish, fn))

    def post(self, event: Exited | Restart) -> None:
        """Queue `event` for this supervisor's thread (any thread; returns at once)."""
        self._mailbox.submit(functools.partial(self._then_publish, self._handle, event))

    def _then_publish(self, fn: Callable[..., T], *args: object) -> T:
        try:
            return fn(*args)
        finally:
            self.publish()

    def _handle(self, event: Exited | Restart) -> None:
        if isinstance(event, Exited):
            self.exits.on_exited(event)
        else:
            self.restarts.on_restart(event)

    def _note_change(self, child: Child) -> None:
        self._changed[id(child)] = child

    def publish(self) -> None:
        """Publish the snapshots of the children that changed since the last publish, and
        wake every waiter of the tree (its cost is what changed, not the children's count:
        a tree of 1,000 starts and restarts at the pace of one of 10)."""
        tree = self.tree
        with tree.cond:
            changed, self._changed = self._changed, {}
            for child in changed.values():
                child.published = child.info(tree.restarts.get(child.name, 0))
                tree.latest[child.name] = child.published
            tree.changed()


# -- restarting: a child's end and what comes of it (OTP's restart/3) ----------------------


class Exits:
    """Takes a child's reported end: drops a stale one, notes it, hands it to `Restarts`."""

    def __init__(self, record: Record, restarts: Restarts, stopping: Stopping) -> None:
        self.record = record
        self.restarts = restarts
        self.stopping = stopping

    def on_exited(self, event: Exited) -> None:
        record = self.record
        child = record.by_name.get(event.name)
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

    `after_exit`: what the exit decides (`children.decide`: restart types and strategies),
    then `RestartIntensity.add` (past it: `give_up`), then the group taken down and a
    `Restart` scheduled after the backoff; `on_restart` starts each child whose latest
    `Restart` it is (a failed start posts `Exited`, a crash). An exit is stale (dropped by
    `Exits`) when its incarnation is older, as after `Stopping.stop_child`, or this
    supervisor gave up; `cancel` makes every pending `Restart` stale (a new generation).
    The flow: "How a restart flows", docs/explanation/architecture.md.
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
        self.intensity = RestartIntensity(
            spec.max_restarts, spec.period, record.tree.clock, recent=record.tree.steps.recent
        )
        self.gave_up: SupervisorGaveUpError | None = None
        self.giving_up = False
        self._generation = 0
        self._timers: dict[int, runtime.Cancellable] = {}  # id(Restart) -> its backoff timer
        self._due: dict[str, Restart] = {}  # each child's latest scheduled Restart

    def after_exit(self, child: Child, exit: ManagerExit) -> None:
        """`child` ended on its own (`exit`): leave it down, restart it with its group, or
        give up."""
        record = self.record
        decision = decide(
            record.spec.strategy,
            record.restart_types,
            child.name,
            normal=exit.normal,
            group=record.tree.steps.group,  # (a copy passed in: `Supervisor(steps=)`)
        )
        if not decision.group:
            child.state = "exited"
            self.stopping.forget(child, dead=not exit.clean)
            return
        child.state = "restarting"
        mark(child)
        record.publish()
        if not self.intensity.add():
            self.give_up(child)
            return
        self._schedule(self._take_down(child, decision))

    def on_restart(self, event: Restart) -> None:
        record = self.record
        self._timers.pop(id(event), None)  # (it ran: nothing to cancel any more)
        if event.generation != self._generation or self.gave_up is not None:
            return
        for child in map(record.by_name.__getitem__, event.names):  # (in start order)
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

    def _take_down(self, crashed: Child, decision: Decision) -> tuple[str, ...]:
        """Stop the siblings `decision` takes down with `crashed` (reverse start order);
        the names to restart."""
        group = [self.record.by_name[name] for name in decision.group]  # (in start order)
        for other in reversed(group):
            if other is crashed:
                continue
            comes_back = other.name in decision.back
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
        """Stop every child in reverse start order, then report the give-up (OTP: shutdown);
        published once every child has stopped."""
        record, stopping = self.record, self.stopping
        spec = record.spec
        error = SupervisorGaveUpError(
            f"supervisor {record.name!r} gave up: more than {spec.max_restarts} restart(s) "
            f"within {spec.period:g} s (last: {crashed.name!r} {crashed.last_exit})"
        )
        logger.error("%s", error)
        if record.parent is None and record.tree.escalate is not None:
            record.tree.escalate(error)  # a pool's: its process ends, its parent decides
        self.giving_up = True
        self.cancel()
        if record.parent is None and record.tree.ending is None:  # its stops are final: each
            record.tree.ending = Ending.of(record.root(), record.tree.processes.system)  # (rule 12)
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

    def __init__(
        self,
        max_restarts: int,
        period: float,
        clock: Clock | None = None,
        *,
        recent: Callable[[tuple[float, ...], float, float], int] | None = None,
    ) -> None:
        self.max_restarts = max_restarts
        self.period = period
        self.clock = runtime.monotonic if clock is None else clock
        self.step = recent  # (a copy of the count passed in: `Supervisor(steps=)`)
        self._times: collections.deque[float] = collections.deque()

    def add(self) -> bool:
        """Count one restart now; return `False` if that exceeds the intensity (give up)."""
        now = self.clock()
        self._times.append(now)
        step = self.step
        if step is not None:  # (it sees every restart: it chooses those that count)
            return step(tuple(self._times), now, self.period) <= self.max_restarts
        while self._times and now - self._times[0] >= self.period:
            self._times.popleft()
        return len(self._times) <= self.max_restarts

    @property
    def recent(self) -> int:
        """Restarts counted within the current window (this one included, after `add`)."""
        return len(self._times)


# -- starting: in start order, or one again (OTP's start_children, do_restart) -------------

Nest = Callable[[SupervisorSpec, Callable[[SupervisorGaveUpError], None]], Level]
"""`nest(spec, on_gave_up)`: start a supervisor below this one (a `Node`)."""


class Starting:
    """Starts children, in order at the supervisor's start, or one at a restart.

    ```
     start_child ─► a manager: ThreadManager or ProcessManager (a spare process), its
                    config (`<state_dir>/<name>.db`); a supervisor: a nested Node (`nest`)
                ─► running; ChildStarted / ChildRestarted; abandoned ids given back;
                   after a restart, the death watch it missed; without a backup,
                   lost_everything
    ```

    Each child's watcher posts its end as `Exited`, with the incarnation it started.
    `state_dir`: where its managers keep their catalogs (`None`: in memory).
    """

    def __init__(
        self,
        record: Record,
        stopping: Stopping,
        *,
        state_dir: str | os.PathLike[str] | None,
        nest: Nest,
    ) -> None:
        self.record = record
        self.stopping = stopping
        self.state_dir = state_dir
        self.nest = nest

    def start_all(self) -> None:
        """Start every child in order; if one fails, stop those started (reverse order) and
        raise `SupervisorGaveUpError`."""
        record = self.record
        started: list[Child] = []
        for child in record.children:
            try:
                self.start_child(child)
            except BaseException as exc:
                child.state = "stopped"
                child.last_exit = f"failed to start: {exc}"
                self.stopping.forget(child, dead=False)  # no restart is coming: no death-watch hold
                for done in reversed(started):
                    self.stopping.stop_child(done, final=True)
                bound = bound_reached(exc)
                if bound is not None:  # (one line naming it, not where it was hit)
                    raise SupervisorGaveUpError(
                        f"supervisor {record.name!r}: child {child.name!r} failed to start: "
                        f"this machine's limit of {bound} was reached "
                        f"({str(exc).splitlines()[0]}); {len(started)} children had started"
                    ) from exc
                raise SupervisorGaveUpError(
                    f"supervisor {record.name!r}: child {child.name!r} failed to start: {exc}"
                ) from exc
            started.append(child)
            record.publish()

    def config(self, spec: ManagerSpec) -> RegistrarConfig:
        """The registrar config of manager `spec`: its own, else one from the state dir
        (at the tree's durability at least, with its steps: `Tree.durable`)."""
        durability = self.record.tree.durability
        if spec.config is not None:
            return self.record.tree.durable(spec.config)
        if self.state_dir is None:
            return self.record.tree.durable(RegistrarConfig(name=spec.name, durability=durability))
        return self.record.tree.durable(
            RegistrarConfig(
                name=spec.name,
                backup_path=os.path.join(os.fspath(self.state_dir), f"{spec.name}.db"),
                save_on_modify=True,
                durability=durability,
            )
        )

    def start_child(self, child: Child) -> None:
        record = self.record
        child.incarnation += 1
        child.state = "starting"
        record.tree.restart_due.pop(child.name, None)
        if isinstance(child.spec, ManagerSpec):
            comes_back(child.name)  # no longer gone for good
        record.publish()
        spec, tree = child.spec, record.tree
        post = self._watch(child)
        restored = False  # whether it starts on a backup an earlier run left
        if isinstance(spec, SupervisorSpec):
            child.running = (
                self._start_pool(spec, post)  # (in a process of its own: `PoolSetup`)
                if is_pool(spec)
                else self._start_nested(spec, child.incarnation)
            )
            child.gave_up = None
        else:
            if spec.restart != "temporary":
                DIRECTORY.expect_restart(spec.name)  # death watch waits for us
            config = self.config(spec)
            restored = config.backup_path is not None and os.path.exists(config.backup_path)
            if spec.isolation == "thread":
                system = tree.processes.system
                child.running = ThreadManager(spec, config, system, post, tree.events)
            else:
                setup = tree.processes.setups[spec.name]
                child.running = self._start_process(spec, setup, config, post)
        child.state = "running"
        unmark(child)  # it serves again
        restarted = child.name in tree.started
        tree.count_start(child.name)
        self._published_start(child, restarted=restarted)
        tree.give_back_abandoned(child.name)
        if not isinstance(spec, ManagerSpec):
            return
        if restarted:
            death_watch_missed(child.name)
        self.tell_started(spec, restarted=restarted, restored=restored)

    def tell_started(self, spec: ManagerSpec, *, restarted: bool, restored: bool) -> None:
        """Manager `spec` serves: restarted, or on a backup an earlier run left, every
        registrar is told (rule 20); a first start on a fresh catalog tells only the
        registrars of the network beyond this tree (its name may have been served on
        another host, rule 22: their ids there are unknown to it)."""
        record = self.record
        network, upward = record.tree.processes.system, record.tree.upward
        if self.config(spec).backup_path is None:
            if restarted or self.ran_before(spec.name):
                lost_everything(record.root(), spec.name, network, upward=upward)
        elif restarted or restored:  # (what its backup lost; all of it if it is gone)
            announce_started(record.root(), spec.name, network, upward=upward)
        elif network is not None and upward is None:
            announce_started(record.root(), spec.name, network, beyond=record.tree.specs)

    def ran_before(self, name: str) -> bool:
        """`tree.ran_before` on this supervisor's state directory (a mark that cannot be
        written is a WARNING: the manager runs all the same)."""
        if self.state_dir is None:
            return False
        try:
            return ran_before(self.state_dir, name)
        except ConfigError as exc:
            logger.warning("supervisor %s: %s", self.record.name, exc)
            return False

    def _watch(self, child: Child) -> Callable[[ManagerExit], None]:
        post, name, incarnation = self.record.post, child.name, child.incarnation

        def exited(result: ManagerExit) -> None:
            post(Exited(name, incarnation, result))

        return exited

    def _published_start(self, child: Child, *, restarted: bool) -> None:
        record = self.record
        down_since = record.tree.down_since.pop(child.name, None)
        publisher = record.tree.events.publisher
        if not publisher.active:
            return
        pid = pid_of(child)
        if not restarted:
            publisher.publish(events.ChildStarted(record.name, child.name, pid))
            return
        restart_s = 0.0 if down_since is None else runtime.monotonic() - down_since
        publisher.publish(events.ChildRestarted(record.name, child.name, pid, restart_s))

    def _start_pool(
        self, spec: SupervisorSpec, post: Callable[[ManagerExit], None]
    ) -> ProcessManager:
        """Start pool `spec`'s process (`PoolSetup`); return once its managers serve."""
        record = self.record
        tree, processes = record.tree, record.tree.processes
        for name in registrar_names(spec):
            comes_back(name)  # no longer gone for good
        address = processes.system.address if processes.system is not None else None
        setup = pool_setup(spec, address, tree.durability, self.state_dir, tree.steps)
        config = tree.durable(RegistrarConfig(name=spec.name, durability=tree.durability))
        announced = functools.partial(self._pool_announced, spec.name)
        started = self._start_process(pool_manager(spec), setup, config, post, announced)
        self._pool_started(spec, restarted=spec.name in tree.started)
        return started

    def _start_process(
        self,
        spec: ManagerSpec,
        setup: Any,
        config: RegistrarConfig,
        post: Callable[[ManagerExit], None],
        on_announce: Callable[[str, bool], None] | None = None,
    ) -> ProcessManager:
        """Start manager (or pool) `spec`'s process from a spare; the spares are refilled
        after this start, however it went (on the supervisor's thread, once it is published)."""
        record = self.record
        processes = record.tree.processes
        address = processes.system.address if processes.system is not None else None
        try:
            return ProcessManager.start(
                spec,
                setup,
                config,
                address,
                post,
                processes.spares,
                record.tree.events,
                supervisor=record.name,
                on_announce=on_announce,
                hold=processes.hold if processes.held is not None else None,
            )
        finally:
            if processes.spares is not None:
                record.cast(processes.spares.refill)

    def _pool_announced(self, pool: str, name: str, restarted: bool = False) -> None:
        """Pool `pool`'s manager `name` (re)started (`Announce`, on the pool's watcher
        thread): the rest of the system hears it, from this supervisor's thread; a restart
        inside the pool (`restarted`) counts in its `restarts` here."""
        record = self.record

        def announce() -> None:
            tree = record.tree
            root = record.root()
            if restarted:
                with tree.cond:
                    tree.restarts[name] = tree.restarts.get(name, 0) + 1
                record.publish()  # (its snapshot reads the count: `wait_restarted` wakes)
            announce_started(root, name, tree.processes.system, origin=pool, upward=tree.upward)

        record.cast(announce)

    def _pool_started(self, spec: SupervisorSpec, *, restarted: bool) -> None:
        """Pool `spec` serves: count its managers' starts, and what a manager started does
        here (abandoned ids; after a restart, the death watch; without a backup,
        reconcile)."""
        tree = self.record.tree
        own = spec.state_dir if spec.state_dir is not None else self.state_dir
        for manager in managers(spec):
            tree.count_start(manager.name)
            tree.give_back_abandoned(manager.name)
            if not restarted:
                continue
            death_watch_missed(manager.name)
            backup = manager.config.backup_path if manager.config is not None else own
            if backup is None:
                lost_everything(self.record.root(), manager.name, tree.processes.system)

    def _start_nested(self, spec: SupervisorSpec, incarnation: int) -> NestedSupervisor:
        post = self.record.post

        def escalate(error: SupervisorGaveUpError) -> None:
            # OTP: a supervisor that gives up exits with `shutdown`: normal for `transient`
            gave_up = ManagerExit(f"gave up: {error}", normal=True)
            post(Exited(spec.name, incarnation, gave_up))

        return NestedSupervisor(self.nest(spec, escalate))


def pool_setup(
    spec: SupervisorSpec,
    address: Address | None,
    durability: Durability,
    state_dir: str | os.PathLike[str] | None,
    steps: ProtocolSteps,
) -> bytes:
    """The pickled `setup` of pool `spec`'s registrar, with the tree's `steps`
    (`ConfigError`: one cannot pickle)."""
    own = spec.state_dir if spec.state_dir is not None else state_dir
    inner = dataclasses.replace(spec, isolation="thread", state_dir=own)
    try:
        return wire.dumps(PoolSetup(inner, address, durability, steps))
    except Exception as exc:
        raise ConfigError(f"a setup in pool {spec.name!r} is not picklable: {exc}") from exc


class PoolSetup:
    """`setup` of a pool's own registrar (Orleans' silo, in OTP's words), run in its process
    before it is ready: a supervisor of its thread managers, served on the parent's system,
    their events relayed to the process's hub. A `Stop` stops them first
    (`HOOKS.before_stop`); a give-up ends the process (`POOL_GAVE_UP_EXIT`): its parent
    decides (OTP's escalation). The parent's heartbeat watches the pool's registrar; the
    pool's `PoolWatch` each of its thread managers."""

    def __init__(
        self,
        spec: SupervisorSpec,
        address: Address | None,
        durability: Durability,
        steps: ProtocolSteps,
    ) -> None:
        self.spec, self.address, self.durability, self.steps = spec, address, durability, steps

    def __call__(self, registrar: ResourceRegistrar) -> None:
        network = self.address.attach() if self.address is not None else None
        tree = Tree(
            self.spec,
            clock=runtime.monotonic,
            network=network,
            durability=self.durability,
            steps=self.steps,  # (`Supervisor(steps=)`: the pool's supervisor and managers too)
        )
        tree.escalate = _pool_gave_up
        tree.upward = functools.partial(_tell_parent, tree)
        tree.processes.open(0, 0.0)  # (the system given: no spares, all threads)
        if HOOKS.hub is not None:
            tree.events.publisher.relay_to(HOOKS.hub)  # forwarded while the parent listens
        node = Node(self.spec, tree)
        node.start()
        names = [manager.name for manager in managers(self.spec)]
        watch = PoolWatch(node, self.spec.name)

        def stop(timeout: float, restarting: bool) -> None:
            with watch.lock:  # (a manager that stops is not hung)
                watch.closed.set()
            if restarting:  # with its group: no tombstones, its callers see "unavailable"
                DIRECTORY.mark_restarting(names)
            node.stop(timeout=0.8 * timeout, restarting=restarting)  # (the rest: its own)

        HOOKS.before_stop = stop


def _tell_parent(tree: Tree, name: str) -> None:
    """A pool's manager `name` (re)started: its parent tells the rest of the system (and
    counts a restart inside the pool: `Tree.restarted_here`)."""
    if HOOKS.to_parent is not None:
        HOOKS.to_parent(Announce(name, name in tree.restarted_here))
    tree.restarted_here.discard(name)


class PoolWatch:
    """A pool's heartbeat of each running thread manager below `level`, judged as a process
    manager's (`Heartbeat`: its spec's `heartbeat`, `hang_after`; busy is not hung); on a
    thread of its own, logs the first hung and ends the pool's process (`POOL_HUNG_EXIT`)."""

    def __init__(self, level: Level, pool: str) -> None:
        self.level, self.pool, self.lock = level, pool, runtime.Lock()
        self.watched: dict[str, list[Any]] = {}  # name -> [registrar, beat, inbox, pinged]
        self.closed = runtime.Event()
        runtime.Thread(target=self._run, name="rr-pool-watch", daemon=True).start()

    def _run(self) -> None:
        while not self.closed.wait(min((w[1].step for w in self.watched.values()), default=0.05)):
            with self.lock:
                hung = None if self.closed.is_set() else self._tick(runtime.monotonic())
            if hung is not None:
                logger.error("pool %s: its manager %s is hung (%s): the pool exits", *hung)
                sys.stderr.flush()  # (what its managers committed stays, as after a SIGKILL)
                os._exit(POOL_HUNG_EXIT)  # (a thread cannot be killed: its parent restarts it)

    def _tick(self, now: float) -> tuple[str, str, str] | None:
        running = {name: m for name, m in _running(self.level) if m.spec.hang_after is not None}
        self.watched = {name: w for name, w in self.watched.items() if name in running}
        for name, manager in running.items():
            spec, registrar, watched = manager.spec, manager.registrar, self.watched.get(name)
            if watched is None or watched[0] is not registrar:  # (a new incarnation)
                period, bound = spec.heartbeat or 0.0, spec.hang_after or 0.0
                beat = Heartbeat(name, period, bound, None, now, probes=True)
                inbox = registrar._actor.ref.actor_inbox  # (its `handled` count: busy)
                watched = self.watched[name] = [registrar, beat, inbox, 0]
            if not registrar._actor.ref.is_alive():
                continue  # it died: its supervisor restarts it
            verdict, inbox = watched[1].tick(now), watched[2]
            if isinstance(verdict, Hang):
                return self.pool, name, verdict.reason()
            if isinstance(verdict, Look):
                watched[1].progress(verdict.number, watched[3], inbox.handled, inbox.qsize(), now)
            elif verdict is not None:
                watched[3] = inbox.handled
                registrar._actor.ping(_Answer(self.lock, watched[1], verdict))
                watched[1].sent(now)
        return None


class _Answer:
    """A ping's reply: its beat hears it (under the watch's lock; none if the actor died)."""

    def __init__(self, lock: Any, beat: Heartbeat, number: int) -> None:
        self.lock, self.beat, self.number = lock, beat, number

    def set_error(self, _: BaseException) -> None: ...

    def set_result(self, _: Any) -> None:
        with self.lock:
            self.beat.answered(self.number, runtime.monotonic())


def _running(level: Level) -> Iterator[tuple[str, ThreadManager]]:
    for child in list(level.children):
        if isinstance(child.running, ThreadManager) and child.state == "running":
            yield child.name, child.running
        elif isinstance(child.running, NestedSupervisor):
            yield from _running(child.running.node)


def _pool_gave_up(error: SupervisorGaveUpError) -> None:
    logger.error("%s: its process exits, its parent decides", error)
    sys.stderr.flush()  # (what its managers committed stays, as after a SIGKILL)
    os._exit(POOL_GAVE_UP_EXIT)


# -- stopping: in reverse order, and the death watch (OTP's terminate_children) ------------

_MIN_STOP = 1e-3  # seconds a child still gets to stop when an overall stop bound ran out


def left(deadline: float | None) -> float | None:
    """Seconds left until `deadline` (at least 1 ms)."""
    if deadline is None:
        return None
    return max(deadline - runtime.monotonic(), _MIN_STOP)


def registrar_names(spec: ManagerSpec | SupervisorSpec) -> list[str]:
    if isinstance(spec, ManagerSpec):
        return [spec.name]
    return [manager.name for manager in managers(spec)]


def mark(child: Child) -> None:
    """`child` is down and will be restarted: its callers get `RegistrarUnavailableError`."""
    DIRECTORY.mark_restarting(registrar_names(child.spec))


def unmark(child: Child) -> None:
    DIRECTORY.mark_restarting(registrar_names(child.spec), restarting=False)


class Stopping:
    """Stops children, and releases what those that will not come back held.

    ```
     stop_all, a group's siblings, a give-up, a failed start's rollback ─► stop_child: its
       spec's shutdown (bounded by the deadline), then a kill ─► note_exit; final? ─► forget
     forget ─► death watch (rule 19): a dead manager is lost (`lose`); one stopped for
               good is stale (rule 12)
    ```
    """

    def __init__(self, record: Record) -> None:
        self.record = record
        self.to_restart = False  # the parent stops this tree to start it again
        self.exiting: list[tuple[Child, Running]] | None = None  # the tree's stop: to reap

    def stop_all(
        self, deadline: float | None = None, *, restarting: bool = False, parallel: bool = False
    ) -> None:
        """Stop every child: in reverse start order, or (`parallel`) each once the children
        that depend on it stopped (`stop_in_parallel`). A process manager's stop ends when
        its registrar reports stopped (what the next stop needs); its exit overlaps the
        next stops, and is reaped at the end."""
        self.to_restart, self.exiting = restarting, []
        try:
            if parallel:
                self.stop_in_parallel(deadline, restarting=restarting)
                return
            for child in reversed(self.record.children):
                self.stop_child(child, final=True, deadline=deadline, restarting=restarting)
        finally:
            exiting, self.exiting = self.exiting, None
            for child, running in exiting:  # each exit, or a kill at its stop's bound
                killed = running.handle.reap() if isinstance(running, ProcessManager) else None
                if killed is not None:
                    child.last_exit = killed

    def stop_in_parallel(self, deadline: float | None, *, restarting: bool) -> None:
        """Stop the children at once, each once those that depend on it stopped: a child
        depends on another when one of its registrars holds a query at one of the other's
        (asked of each running manager; unknown: on every child started before it, OTP's
        order); a cycle is broken in reverse start order. The stops run on at most
        `STOP_WORKERS` threads, their bookkeeping on this supervisor's thread."""
        children, exiting = self.record.children, self.exiting
        assert exiting is not None  # (its exits are reaped by `stop_all`)
        for child in children:
            if child.running is None:
                self.stop_child(child, final=True, deadline=deadline, restarting=restarting)
        up = [i for i, child in enumerate(children) if child.running is not None]
        out: runtime.SimpleQueue[tuple[Any, Any]] = runtime.SimpleQueue()
        needs = self._needs(up, deadline, out)
        waiting = dict.fromkeys(up, 0)  # a child's dependents not stopped yet
        for i in up:
            for j in needs[i]:
                waiting[j] += 1
        ready, under_way = [i for i in reversed(up) if waiting[i] == 0], 0
        while waiting or under_way:
            if not ready and not under_way:  # a cycle
                ready = [max(waiting)]
            start, ready = ready[: STOP_WORKERS - under_way], ready[STOP_WORKERS - under_way :]
            begun = [(i, *self._begin_stop(children[i], deadline)) for i in start]
            for i, running, limit, pid in begun:  # (all marked stopping, then stopped)
                del waiting[i]
                _spawn(out, (i, pid, running), _stop, running, limit, restarting, True)
                under_way += 1
            (i, pid, running), result = out.get()
            under_way -= 1
            if not isinstance(result, ManagerExit):
                result = ManagerExit(f"stop failed: {result}", normal=False)
            self._end_stop(children[i], pid, result, final=True)
            exiting.append((children[i], running))
            for j in sorted(needs[i], reverse=True):
                waiting[j] -= 1
                if waiting[j] == 0:
                    ready.append(j)

    def _needs(
        self, up: list[int], deadline: float | None, out: runtime.SimpleQueue[tuple[Any, Any]]
    ) -> dict[int, set[int]]:
        """The running children (indices) each running child depends on."""
        children = self.record.children
        needs: dict[int, set[int]] = {i: set() for i in up}
        system, ask = self.record.tree.processes.system, min(left(deadline) or 5.0, 5.0)
        owner = {name: i for i in up for name, _ in _managers(children[i])}
        jobs = [(i, _providers, n, r, system, ask) for i in up for n, r in _managers(children[i])]
        held = []
        for n, job in enumerate(jobs):
            if n >= STOP_WORKERS:  # (at most that many asked at once)
                held.append(out.get())
            _spawn(out, *job)
        held += [out.get() for _ in range(len(jobs) - len(held))]
        for i, providers in held:
            if not isinstance(providers, set):  # unknown: OTP's order
                needs[i] |= {j for j in up if j < i}
            else:
                needs[i] |= {owner[n] for n in providers if owner.get(n, i) != i}
        return needs

    def stop_child(
        self,
        child: Child,
        *,
        final: bool,
        deadline: float | None = None,
        restarting: bool = False,
    ) -> None:
        """Stop a running child (`final`: not started again; `restarting`: it will be).

        In the whole tree's stop its exit is reaped at the end (`stop_all`). A child
        stopped alone (a restart's group, a give-up, a rollback) waits for its exit: a
        new incarnation must not overlap the old process, which holds its backup."""
        running = child.running
        if running is None:
            if final:
                child.incarnation += 1  # an exit still queued for it (a failed start) is stale
                dead = child.state == "restarting"  # it crashed and will not come back now
                if child.state != "exited":
                    child.state = "stopped"
                self.forget(child, dead=dead)
            return
        running, limit, pid = self._begin_stop(child, deadline)
        exiting = self.exiting
        result = _stop(running, limit, restarting, False, exiting is not None)
        self._end_stop(child, pid, result, final=final)
        if exiting is not None:
            exiting.append((child, running))

    def _begin_stop(
        self, child: Child, deadline: float | None
    ) -> tuple[Running, float | None, int]:
        """Mark a running child stopping; it, its stop's bound in seconds, its pid."""
        running = child.running
        assert running is not None
        ending = self.record.tree.ending
        told = ending and (ending.stopped or ending.lost)  # (the tree's stop: `consumer_down`)
        if told and ending and isinstance(running, (ProcessManager, ThreadManager)):
            running.tell_stopped(tuple(ending.stopped), tuple(ending.lost))
        child.state = "stopping"
        child.incarnation += 1  # its watcher's exit event is now stale
        self.record.publish()
        limit = left(deadline)
        if isinstance(child.spec, ManagerSpec):
            limit = child.spec.shutdown if limit is None else min(limit, child.spec.shutdown)
        return running, limit, pid_of(child)

    def _end_stop(self, child: Child, pid: int, result: ManagerExit, *, final: bool) -> None:
        child.running = None
        child.state = "stopped"
        child.last_exit = result.reason
        self.note_exit(child, pid, result.reason, stopped=True)
        if final:
            self.forget(child, dead=not result.clean)

    def note_exit(
        self, child: Child, pid: int, reason: str, *, normal: bool = False, stopped: bool = False
    ) -> None:
        """Note when `child` went down, and publish `ChildExited` (`stopped`: by this
        supervisor, not an exit the restart intensity counts)."""
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
        """The child will not come back: release what it held (death watch) if it died."""
        if not self.to_restart:
            unmark(child)
        if isinstance(child.spec, ManagerSpec):
            DIRECTORY.expect_restart(child.name, expected=False)
            if dead:
                self.lose(child.name)
            elif not self.to_restart:  # stopped, and nobody starts it again
                record = self.record
                system, ending = record.tree.processes.system, record.tree.ending
                consumer_down(record.root(), child.name, system, stopped=True, ending=ending)
        elif is_pool(child.spec) and dead:  # its process died, and nobody restarts it
            for name in registrar_names(child.spec):
                self.lose(name)
        elif child.gave_up is not None:  # a nested supervisor gave up, and stays down:
            for name in registrar_names(child.spec):  # nobody restarts its managers
                self.lose(name)

    def lose(self, name: str) -> None:
        """Manager `name` is gone and nobody will restart it (death watch, rule 19)."""
        DIRECTORY.expect_restart(name, expected=False)
        record, tree = self.record, self.record.tree
        consumer_down(record.root(), name, tree.processes.system, ending=tree.ending)  # (first:
        # a manager that starts meanwhile hears it then, `death_watch_missed`)


STOP_WORKERS = 16
"""Threads a parallel stop (`Supervisor.stop(parallel=True)`) runs at once, at most."""


def _managers(child: Child) -> list[tuple[str, Running]]:
    """The running managers of `child` (itself, or those below a nested supervisor)."""
    running = child.running
    if isinstance(running, NestedSupervisor):
        return [found for below in list(running.node.children) for found in _managers(below)]
    return [] if running is None else [(child.name, running)]


def _providers(name: str, running: Running, system: Transport | None, timeout: float) -> Any:
    """The registrars manager `name` holds a query at (`None`: it could not be asked)."""
    try:
        if isinstance(running, ThreadManager):
            return provider_names(running.registrar)
        if isinstance(running, ProcessManager) and system is not None:
            return system.run(name, provider_names, timeout=timeout)
    except Exception as exc:  # noqa: BLE001 - unknown: it keeps OTP's order instead
        logger.info("parallel stop: the queries of %s are unknown (%s)", name, exc)
    return None


def _spawn(out: runtime.SimpleQueue[tuple[Any, Any]], key: Any, fn: Any, *args: Any) -> None:
    """Run `fn(*args)` on a thread of its own, then put `(key, what it returned or raised)`."""

    def run() -> None:
        try:
            result = fn(*args)
        except BaseException as exc:  # (told, never lost: the supervisor waits for it)
            logger.exception("parallel stop: %s failed", getattr(fn, "__name__", fn))
            result = exc
        out.put((key, result))

    runtime.Thread(target=run, name="rr-stop", daemon=True).start()


def _stop(
    running: Running, limit: float | None, again: bool, parallel: bool, whole: bool = True
) -> ManagerExit:
    """`whole` (the tree's stop): a process manager's until its registrar reports stopped."""
    if isinstance(running, NestedSupervisor):
        return running.stop(limit, restarting=again, parallel=parallel)
    if isinstance(running, ProcessManager) and whole:
        return running.stop(limit, restarting=again, wait_exit=False)
    return running.stop(limit, restarting=again)


# -- what the roles share: the mailbox's two messages, the record --------------------------


@dataclasses.dataclass(frozen=True)
class Exited:
    name: str
    incarnation: int
    exit: ManagerExit


@dataclasses.dataclass(frozen=True)
class Restart:
    """Restart these children (posted at once, or by a backoff timer), unless stale."""

    names: tuple[str, ...]
    generation: int


class Record(Level, Protocol):
    """One supervisor as its roles see it (a `Node`)."""

    tree: Tree
    restart_types: dict[str, RestartType]  # each child's, in start order

    @property
    def name(self) -> str: ...

    @property
    def parent(self) -> Record | None: ...

    def root(self) -> Level: ...

    def post(self, event: Exited | Restart) -> None: ...

    def cast(self, fn: Callable[[], object]) -> None: ...

    def publish(self) -> None: ...


def pid_of(child: Child) -> int:
    running = child.running
    pid = running.pid if running is not None else None
    return pid if pid is not None else runtime.getpid()
