"""Simulated processes: a pid, its tasks, its own per-process state; killed or stopped.

```
 Scheduler.spawn(body, process=P) ─► a task of P (a thread started by a task of P is P's)
 a step to a task of Q ─► States.install(Q): P's singletons (every object registered
   with `runtime.process_state`) kept as P's, Q's put in
 Scheduler.end(P, exitcode) (SIGKILL: -9; an exit: its code)
   ├─ its tasks are never switched to again: no `finally` block runs
   ├─ the simulated locks they held of shared (carrier) objects are let go
   ├─ the files P holds (`runtime.hold`) closed: an open transaction rolls back
   ├─ `P.at_end` run (the kernel's part: the carrier closes P's links, ends what it served)
   └─ then `P.at_reaped` run (its parent hears: the manager's watcher)
 Scheduler.stop(P) (SIGSTOP): its tasks stay off the ready list until `cont(P)` (SIGCONT)
```

A kill drops a process's memory and keeps its files (SQLite backups) with exactly the
transactions that committed; the run's end closes the files of every live process.
"""

from __future__ import annotations

import contextlib
import operator
from collections.abc import Callable
from typing import Any

__all__ = ["Process", "States"]


class Process:
    """One simulated process (see the module's diagram)."""

    __slots__ = (
        "at_end",
        "at_reaped",
        "ended_at",
        "exitcode",
        "files",
        "name",
        "parent",
        "parked",
        "pid",
        "state",
        "stopped",
        "stopped_at",
        "tasks",
    )

    def __init__(self, pid: int, name: str, state: list[Any], parent: int | None = None) -> None:
        self.pid = pid
        self.name = name
        self.parent = parent  # the pid of the process that started it (`None`: the first)
        self.state = state  # its singletons' fields while another process's are in
        self.tasks: list[Any] = []  # its tasks (`Task`), ended or not
        self.exitcode: int | None = None  # set when it ended
        self.ended_at = 0.0  # (virtual seconds) when it ended, once it did
        self.stopped = False  # SIGSTOP: not scheduled until `cont`
        self.stopped_at = 0.0  # (virtual seconds) when it was stopped last
        self.parked: list[Any] = []  # its tasks made ready while it was stopped
        self.at_end: list[Callable[[], object]] = []  # run once, when it ends
        # run once, after every `at_end`: who waits on its end (a parent's sentinel,
        # `waitpid`) hears of it once the kernel let go of what it held (its name locks)
        self.at_reaped: list[Callable[[], object]] = []
        self.files: list[Any] = []  # what it holds open (`runtime.hold`), closed or not

    def close_files(self) -> None:
        """Close the files it holds (`runtime.hold`), as the kernel does at its death;
        one that fails to close (closed already, in use) is let go all the same."""
        files, self.files = self.files, []
        for file in files:
            with contextlib.suppress(Exception):
                file.close()

    @property
    def alive(self) -> bool:
        """Whether it has not ended (killed or exited)."""
        return self.exitcode is None

    def __repr__(self) -> str:
        return f"<simulated process {self.pid} {self.name!r}>"


def _fields(obj: object) -> list[str]:
    names = list(getattr(obj, "__dict__", ()))
    for kind in type(obj).__mro__:
        names.extend(
            name
            for name in getattr(kind, "__slots__", ())
            if name not in names and hasattr(obj, name)
        )
    return names


class States:
    """The objects registered with `runtime.process_state`, and whose state they hold.

    A `__dict__` object's dict is swapped whole at a switch; slotted ones and classes have
    their fields copied out and back in where they differ.

    Args:
        registered: `(obj, fresh)` pairs (`runtime.process_states()`).
    """

    def __init__(self, registered: tuple[tuple[object, Callable[[], object]], ...]) -> None:
        objects = [obj for obj, _ in registered]
        self._fresh = [fresh for _, fresh in registered]
        self._fields = [_fields(fresh()) for fresh in self._fresh]
        self._whole = [
            _swappable(obj, fresh(), names)
            for obj, fresh, names in zip(objects, self._fresh, self._fields, strict=True)
        ]
        self._getters = [operator.attrgetter(*names) for names in self._fields]
        self._swapped = [(i, obj) for i, obj in enumerate(objects) if self._whole[i]]
        self._copied = [
            (i, obj, self._fields[i], self._getters[i])
            for i, obj in enumerate(objects)
            if not self._whole[i]
        ]
        real = [
            obj.__dict__ if whole else _values(getter, names, obj)
            for obj, names, whole, getter in zip(
                objects, self._fields, self._whole, self._getters, strict=True
            )
        ]
        self._real = Process(0, "the real process", real)  # (put back by `close`)
        self._installed = self._real
        self.installed: Process = self._real  # the process whose state is in now

    def fresh(self) -> list[Any]:
        """The state of a process that starts: each object's fields as a new one has them
        (its `__dict__`, or a tuple of their values)."""
        state = []
        for fresh, names, whole, getter in zip(
            self._fresh, self._fields, self._whole, self._getters, strict=True
        ):
            made = fresh()
            state.append(made.__dict__ if whole else _values(getter, names, made))
        return state

    def install(self, process: Process) -> None:
        """Make the singletons `process`'s (those of the process in before kept as its)."""
        installed = self._installed
        if process is installed:
            return
        self._installed = self.installed = process
        state = process.state
        for i, obj in self._swapped:
            obj.__dict__ = state[i]  # (the process's own dict: no copy either way)
        for i, obj, names, getter in self._copied:
            now = installed.state[i] = _values(getter, names, obj)
            for name, value, old in zip(names, state[i], now):  # noqa: B905 - (same lengths)
                if value is old:  # (only those that differ: a class's attribute cache
                    continue  # is not reset for nothing)
                if value is _MISSING:
                    delattr(obj, name)
                else:
                    setattr(obj, name, value)

    def close(self) -> None:
        """Put back the real process's state (the run is over)."""
        self.install(self._real)


def _values(getter: Callable[[object], Any], names: list[str], obj: object) -> tuple[Any, ...]:
    """The values of fields `names` in `obj` (`getter`: `attrgetter(*names)`), `_MISSING`
    for one it has not."""
    try:
        values = getter(obj)
    except AttributeError:  # (the real object may lack one: rare, so slow)
        return tuple(getattr(obj, name, _MISSING) for name in names)
    return values if len(names) > 1 else (values,)


def _swappable(obj: object, made: object, names: list[str]) -> bool:
    """Whether `obj`'s state can be swapped as a whole `__dict__`: an instance (not a
    class) whose fields, and a fresh one's, are all in its `__dict__`, and nothing more."""
    if isinstance(obj, type) or not hasattr(obj, "__dict__"):
        return False
    return set(vars(obj)) <= set(names) and set(vars(made)) == set(names)


_MISSING: Any = object()
