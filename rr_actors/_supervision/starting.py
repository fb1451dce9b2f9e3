"""Starting a supervisor's children: all of them in order, or one again after a crash.

```
 Node.start ─► start_all: each child in start order ─► start_child
                  └─ one fails: the started ones stop (reverse order) ─► SupervisorGaveUpError
 Restarts.on_restart ─► start_child
 start_child ─► a manager: ThreadManager (this process) or ProcessManager (a spare process),
                           its config (`<state_dir>/<name>.db` with the tree's state_dir)
              └ a supervisor: a nested Node (`nest`), which gives up by posting Exited
            ─► running; ChildStarted / ChildRestarted; abandoned ids given back;
               after a restart, the death watch it missed (and, with no backup, FATAL
               for what was held at it, and what it held released: lost_everything;
               also at the first start of one that ran on the state_dir before)
```

Each child is handed a watcher callback (run on its watcher thread) that posts its end
to the supervisor's mailbox as `Exited`, with the incarnation it started. Runs on the
supervisor's thread. Its own state: the state directory its managers' catalogs go to.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from typing import TYPE_CHECKING

from rr_actors import events
from rr_actors._core import runtime
from rr_actors._core.directory import DIRECTORY
from rr_actors._process.manager import ManagerExit
from rr_actors._supervision.children import (
    Child,
    Level,
    NestedSupervisor,
    ProcessManager,
    ThreadManager,
)
from rr_actors._supervision.record import Exited, pid_of
from rr_actors._supervision.retry import give_back_abandoned
from rr_actors._supervision.statedir import ran_before
from rr_actors._supervision.stopping import unmark
from rr_actors._supervision.tree import comes_back, death_watch_missed, lost_everything
from rr_actors.config import ManagerSpec, RegistrarConfig, SupervisorSpec
from rr_actors.errors import ConfigError, SupervisorGaveUpError

if TYPE_CHECKING:
    from rr_actors._supervision.record import Record
    from rr_actors._supervision.stopping import Stopping

__all__ = ["Nest", "Starting"]

logger = logging.getLogger("rr_actors")

Nest = Callable[[SupervisorSpec, Callable[[SupervisorGaveUpError], None]], Level]
"""`nest(spec, on_gave_up)`: start a supervisor below this one (a `node.Node`), which
calls `on_gave_up` (on its own thread) when it gives up."""


class Starting:
    """Starts children, in order at the supervisor's start, or one at a restart.

    Args:
        record: the supervisor whose children it starts.
        stopping: stops what started when a later child fails to start.
        state_dir: where its managers keep their catalogs (`None`: in memory, unless a
            manager's spec names a config).
        nest: starts a nested supervisor.
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
        """Start every child in order; if one fails, stop those started (reverse order).

        Raises:
            SupervisorGaveUpError: a child failed to start.
        """
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
                raise SupervisorGaveUpError(
                    f"supervisor {record.name!r}: child {child.name!r} failed to start: {exc}"
                ) from exc
            started.append(child)
            record.publish()

    def config(self, spec: ManagerSpec) -> RegistrarConfig:
        """The registrar config of manager `spec`: its own, else one from the state dir."""
        if spec.config is not None:
            return spec.config
        if self.state_dir is None:
            return RegistrarConfig(name=spec.name)
        return RegistrarConfig(
            name=spec.name,
            backup_path=os.path.join(os.fspath(self.state_dir), f"{spec.name}.db"),
            save_on_modify=True,
        )

    def start_child(self, child: Child) -> None:
        """Start one incarnation of `child`; raise what its start raised."""
        record = self.record
        child.incarnation += 1
        child.state = "starting"
        record.tree.restart_due.pop(child.name, None)
        if isinstance(child.spec, ManagerSpec):
            comes_back(child.name)  # no longer gone for good
        record.publish()
        spec, tree = child.spec, record.tree
        post = self._watch(child)
        if isinstance(spec, SupervisorSpec):
            child.running = self._start_nested(spec, child.incarnation)
            child.gave_up = None
        else:
            if spec.restart != "temporary":
                DIRECTORY.expect_restart(spec.name)  # death watch waits for us
            config = self.config(spec)
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
                        record.cast(processes.spares.refill)
        child.state = "running"
        unmark(child)  # it serves again
        restarted = child.name in tree.started
        tree.count_start(child.name)
        self._published_start(child, restarted=restarted)
        give_back_abandoned(tree, child.name)
        if not isinstance(spec, ManagerSpec):
            return
        if restarted:
            death_watch_missed(child.name)
        # (one with a backup reconciles with everyone itself when it is restored)
        if self.config(spec).backup_path is None and (restarted or self.ran_before(spec.name)):
            lost_everything(record.root(), child.name, tree.processes.system)

    def ran_before(self, name: str) -> bool:
        """Whether manager `name`, which keeps no backup, ran on this supervisor's state
        directory before (in a program killed since, say: the backups of the others may
        hold its last run's ids); marks it there (`statedir.ran_before`). A mark that
        cannot be written is a WARNING: the manager runs all the same."""
        if self.state_dir is None:
            return False
        try:
            return ran_before(self.state_dir, name)
        except ConfigError as exc:
            logger.warning("supervisor %s: %s", self.record.name, exc)
            return False

    def _watch(self, child: Child) -> Callable[[ManagerExit], None]:
        """What `child`'s watcher calls when this incarnation ends: post `Exited`."""
        post, name, incarnation = self.record.post, child.name, child.incarnation

        def exited(result: ManagerExit) -> None:
            post(Exited(name, incarnation, result))

        return exited

    def _published_start(self, child: Child, *, restarted: bool) -> None:
        """Publish `ChildStarted`, or `ChildRestarted` with the time it was down."""
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

    def _start_nested(self, spec: SupervisorSpec, incarnation: int) -> NestedSupervisor:
        post = self.record.post

        def escalate(error: SupervisorGaveUpError) -> None:
            # OTP: a supervisor that gives up exits with `shutdown`: normal for `transient`
            gave_up = ManagerExit(f"gave up: {error}", normal=True)
            post(Exited(spec.name, incarnation, gave_up))

        return NestedSupervisor(self.nest(spec, escalate))
