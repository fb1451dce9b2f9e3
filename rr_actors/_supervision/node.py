"""One supervisor of a tree: a small state record, its mailbox, and the roles it wires.

After OTP's `supervisor.erl` (a state record, `restart/3` with one clause per strategy,
`do_*` helpers): each event runs on the node's thread (a `SerialExecutor`), one at a
time, and every step ends by publishing the children's snapshots to the tree's waiters.

```
              ┌────────────── Node (one mailbox, one thread; node.py) ─────────────────┐
 start ─────► │ Starting    start_all, start_child, nested Nodes      (starting.py)    │
 stop ──────► │ Restarts.cancel, then Stopping.stop_all                                │
 watcher ───► │ Exited ──► Exits.on_exited: stale? note the exit                       │
   threads    │              └─► Restarts.after_exit: restart type, intensity,         │
              │                  strategy, backoff, give up            (restarting.py) │
 timer ─────► │ Restart ─► Restarts.on_restart ─► Starting.start_child                 │
              │ Stopping    stop_child, stop_all, forget (death watch)  (stopping.py)  │
              │ Record: spec, tree, children (Child records), post, publish (record.py)│
              └────────────────────────────────────────────────────────────────────────┘
```

The roles call only the roles below them (restarting ─► starting ─► stopping).
A nested supervisor is a `Node` too; when it gives up it tells its parent, which sees an
exited child (OTP: a supervisor that gives up exits with `shutdown`).
"""

from __future__ import annotations

import functools
import logging
import os
from collections.abc import Callable
from typing import TypeVar

from rr_actors._core import runtime
from rr_actors._core.serial import SerialExecutor
from rr_actors._supervision.children import Child
from rr_actors._supervision.record import Exited, Restart
from rr_actors._supervision.restarting import Exits, Restarts
from rr_actors._supervision.starting import Starting
from rr_actors._supervision.stopping import Stopping
from rr_actors._supervision.tree import Tree
from rr_actors.config import SupervisorSpec
from rr_actors.errors import RrError, SupervisorGaveUpError

__all__ = ["Node"]

logger = logging.getLogger("rr_actors")

T = TypeVar("T")


class Node:
    """One supervisor of a tree (the root or a nested one): its record, mailbox and roles.

    Args:
        spec: what it supervises and how.
        tree: what the whole tree shares.
        parent: the supervisor above it (`None` for the root).
        state_dir: the parent's state directory (its managers' default, unless `spec`
            names one).
        on_gave_up: called (on this supervisor's thread) when it gives up.
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
        for child in self.children:  # a new incarnation: say how the last one ended
            last = tree.latest.get(child.name)
            child.last_exit = last.last_exit if last is not None else None
            child.published = child.info(tree.restarts.get(child.name, 0))
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
        """The supervisor's name."""
        return self.spec.name

    @property
    def parent(self) -> Node | None:
        """The supervisor above it (`None` for the root)."""
        return self._parent

    @property
    def gave_up(self) -> SupervisorGaveUpError | None:
        """Why it gave up (`None` while it has not)."""
        return self.restarts.gave_up

    @property
    def giving_up(self) -> bool:
        """Whether it is stopping its children to give up (waiters conclude nothing)."""
        return self.restarts.giving_up

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
    ) -> None:
        """Stop every child in reverse start order, then the mailbox thread (idempotent).

        With `restarting`, the parent stops this supervisor to start it again (a group
        restart): its managers' callers meanwhile get `RegistrarUnavailableError`.
        """
        if deadline is None and timeout is not None:
            deadline = runtime.monotonic() + timeout
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

    def _stop_all(self, deadline: float | None, *, restarting: bool) -> None:
        self.restarts.cancel()
        self.stopping.stop_all(deadline, restarting=restarting)

    def _nest(
        self, spec: SupervisorSpec, on_gave_up: Callable[[SupervisorGaveUpError], None]
    ) -> Node:
        """Start a supervisor below this one (this thread waits until it started)."""
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
        """Run `fn(*args)`, then `publish` (this supervisor's thread, one step at a time;
        what `fn` raises is logged by the thread, or raised to `call`'s caller)."""
        try:
            return fn(*args)
        finally:
            self.publish()

    def _handle(self, event: Exited | Restart) -> None:
        if isinstance(event, Exited):
            self.exits.on_exited(event)
        else:
            self.restarts.on_restart(event)

    def publish(self) -> None:
        """Publish the children's snapshots and wake every waiter of the tree."""
        tree = self.tree
        with tree.cond:
            for child in self.children:
                child.published = child.info(tree.restarts.get(child.name, 0))
                tree.latest[child.name] = child.published
            tree.changed()
