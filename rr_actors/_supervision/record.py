"""What the roles of one supervisor share: its record, and its mailbox's two messages.

```
 Record (a node.Node): spec, tree, children (Child records), name, root()
                       post(Exited | Restart) ──► mailbox ──► Node dispatches to a role
                       cast(fn), publish()     (every step ends with a publish)
```

The roles (`starting.py`, `stopping.py`, `restarting.py`) hold the record, never each
other's fields; what one role needs of another it asks by a method.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

from rr_actors._core import runtime
from rr_actors._process.manager import ManagerExit
from rr_actors._supervision.children import Child, Level

if TYPE_CHECKING:
    from rr_actors._supervision.tree import Tree

__all__ = ["Exited", "Record", "Restart", "pid_of"]


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


class Record(Level, Protocol):
    """One supervisor as its roles see it (a `node.Node`): what it supervises, the tree it
    is part of, its children's records, and its mailbox."""

    tree: Tree

    @property
    def name(self) -> str:
        """The supervisor's name."""
        ...

    @property
    def parent(self) -> Record | None:
        """The supervisor above it (`None` for the root)."""
        ...

    def root(self) -> Level:
        """The tree's root supervisor."""
        ...

    def post(self, event: Exited | Restart) -> None:
        """Queue `event` for this supervisor's thread (any thread; returns at once)."""
        ...

    def cast(self, fn: Callable[[], object]) -> None:
        """Run `fn` on this supervisor's thread after what is queued now."""
        ...

    def publish(self) -> None:
        """Publish the children's snapshots and wake every waiter of the tree."""
        ...


def pid_of(child: Child) -> int:
    """The process a child runs in: its own (a process manager), else this one."""
    running = child.running
    pid = running.pid if running is not None else None
    return pid if pid is not None else runtime.getpid()
