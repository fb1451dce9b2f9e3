"""Simulated processes: a pid, its tasks, its own per-process state; killed or stopped.

```
 Scheduler.spawn(body, process=P) ─► a task of P (a thread started by a task of P is P's)
 Scheduler._switch(task of Q) ─► States.install(Q): what P's singletons hold now is put
   away as P's, Q's is put in (DIRECTORY, MEMBERSHIP, CLOCK, pykka's registry, ...: every
   object registered with `runtime.process_state`)
 Scheduler.end(P, exitcode) (SIGKILL: -9; an exit: its code)
   ├─ its tasks are never switched to again: no `finally` block runs, as after a SIGKILL
   │  (dropped with the run's other tasks when the run is over)
   ├─ the simulated locks they held are let go (only the carrier's objects are shared
   │  between simulated processes: in a real run a dead process holds nothing of theirs)
   └─ `P.at_end` run (the kernel's part: the carrier closes P's links; its watcher hears)
 Scheduler.stop(P) (SIGSTOP): its tasks stay off the ready list until `cont(P)` (SIGCONT)
```

What a process keeps on its disk (SQLite backups: real files) is not its state here: a
kill drops its memory and keeps its files with exactly the transactions that committed.
"""

from __future__ import annotations

import operator
from collections.abc import Callable
from typing import Any

__all__ = ["Process", "States"]


class Process:
    """One simulated process (see the module's diagram)."""

    __slots__ = (
        "at_end",
        "exitcode",
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
        self.stopped = False  # SIGSTOP: not scheduled until `cont`
        self.stopped_at = 0.0  # (virtual seconds) when it was stopped last
        self.parked: list[Any] = []  # its tasks made ready while it was stopped
        self.at_end: list[Callable[[], object]] = []  # run once, when it ends

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

    An object whose fields all live in its `__dict__` (most) has a `__dict__` per
    process, swapped whole at a switch (one assignment, whatever its size; the one in use
    is the process's own, so nothing is read back); the others (slotted ones, a class)
    have their fields' values copied out (a tuple) and back in, where they differ.

    Args:
        registered: `(obj, fresh)` pairs (`runtime.process_states()`).
    """

    def __init__(self, registered: tuple[tuple[object, Callable[[], object]], ...]) -> None:
        self._objects = [obj for obj, _ in registered]
        self._fresh = [fresh for _, fresh in registered]
        self._fields = [_fields(fresh()) for fresh in self._fresh]
        self._whole = [
            _swappable(obj, fresh(), names)
            for obj, fresh, names in zip(self._objects, self._fresh, self._fields, strict=True)
        ]
        self._getters = [operator.attrgetter(*names) for names in self._fields]
        self._swapped = [(i, obj) for i, obj in enumerate(self._objects) if self._whole[i]]
        self._copied = [i for i, whole in enumerate(self._whole) if not whole]
        self._real = self._read()  # the real process's, put back by `close`
        self._installed: Process | None = None

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

    def _read(self) -> list[Any]:
        return [
            obj.__dict__ if whole else _values(getter, names, obj)
            for obj, names, whole, getter in zip(
                self._objects, self._fields, self._whole, self._getters, strict=True
            )
        ]

    def _write(self, state: list[Any], now: list[Any] | None = None) -> None:
        """Put `state` in (`now`: what the copied objects hold now: only the fields that
        differ are set, so a class's attribute cache is not reset for nothing)."""
        for i, obj in self._swapped:
            obj.__dict__ = state[i]  # (the process's own dict: no copy either way)
        for i in self._copied:
            obj, names, values = self._objects[i], self._fields[i], state[i]
            was = now[i] if now is not None else (_UNKNOWN,) * len(names)
            for name, value, old in zip(names, values, was, strict=True):
                if value is old:
                    continue
                if value is _MISSING:
                    if hasattr(obj, name):
                        delattr(obj, name)
                else:
                    setattr(obj, name, value)

    def install(self, process: Process) -> None:
        """Make the singletons `process`'s (those of the process in before kept as its)."""
        installed = self._installed
        if process is installed:
            return
        if installed is None:
            self._write(process.state)
        else:  # (a whole `__dict__` in its state is the one in use: only the others read)
            state = installed.state
            for i in self._copied:
                state[i] = _values(self._getters[i], self._fields[i], self._objects[i])
            self._write(process.state, state)
        self._installed = process

    def close(self) -> None:
        """Put back the real process's state (the run is over)."""
        if self._installed is not None:
            self._installed.state = self._read()
        self._write(self._real)
        self._installed = None


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
_UNKNOWN: Any = object()  # (what a field held before, not read: set it whatever it is)
