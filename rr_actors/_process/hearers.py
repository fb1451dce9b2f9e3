"""Which manager processes hear a registrar's (re)start: the parent's index of their monitors.

```
 manager process (child.py)            control pipe             this process (HEARERS)
   a registrar there monitors X ─► Monitoring((X,), at) ──────►  monitoring: X -> its handle;
     (`Membership.report`, `at` read                             told at once of X if X was
      before it recorded X)                                       announced at or after `at`
   a restored one, until its sweep ─► HearsAll(on, at) ────────►  hears_all: in or out of the
                                                                  set that hears every start
 a supervisor announces X (`announce_started`) ─► announce(X): the handles X's monitors name
   and those that hear every start ─► PeerStarted(X) on each pipe (its registrars filter too)
 a handle ends (`ManagerProcess.finish`) ─► forget(handle)
```

One per process, like the membership (Erlang's monitors are the runtime's). A report and
an announcement of the same name are ordered by one lock: a report read first puts its
process among those told; one read after is told every announcement of that name made at
or after its stamp. The clock is `runtime.monotonic` (CLOCK_MONOTONIC, one for every
process of a host). Repeats are allowed: a registrar hears a start twice, never none (rule
20). A handle that reports nothing (a simulated manager: `hears_all` at its start) is told
everything. What one process is told of a restart is a pipe write, 0.14 ms of its CPU: at
a thousand managers that was 140 ms of CPU per restart, spent by processes with no business.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Protocol

from rr_actors._core import runtime
from rr_actors._platform import forkserver

__all__ = ["HEARERS", "Hearer", "Hearers"]


class Hearer(Protocol):
    """A manager process's handle, as the index sees it (`ManagerProcess`)."""

    @property
    def name(self) -> str: ...

    @property
    def exited(self) -> runtime.Event: ...

    def tell_started(self, name: str) -> None: ...


class Hearers:
    """Who hears a start of each name: the handles whose processes reported monitoring it,
    and those that hear every start; when each name was last announced."""

    def __init__(self) -> None:
        self._lock = runtime.Lock()
        self._by_name: dict[str, dict[Hearer, None]] = {}  # name -> its monitors' handles
        self._names: dict[Hearer, set[str]] = {}  # handle -> the names it monitors
        self._everything: dict[Hearer, None] = {}
        self._announced: dict[str, float] = {}  # name -> when it was last announced

    def monitoring(self, hearer: Hearer, names: Iterable[str], at: float) -> None:
        """`hearer`'s process monitors `names` since `at` (monotonic seconds): it hears
        their starts from now on, and now those announced at or after `at`. Any thread."""
        with self._lock:
            if hearer.exited.is_set():  # (`forget` came first: nothing to keep)
                return
            late = []
            for name in names:
                self._by_name.setdefault(name, {})[hearer] = None
                self._names.setdefault(hearer, set()).add(name)
                if self._announced.get(name, -float("inf")) >= at:
                    late.append(name)
        for name in late:
            hearer.tell_started(name)

    def hears_all(self, hearer: Hearer, *, on: bool, at: float = -float("inf")) -> None:
        """`hearer` hears every start from now on (and now those announced at or after `at`),
        or (`on=False`) only those it monitors. Any thread."""
        with self._lock:
            if not on:
                self._everything.pop(hearer, None)
                return
            if hearer.exited.is_set():
                return
            self._everything[hearer] = None
            late = sorted(name for name, when in self._announced.items() if when >= at)
        for name in late:
            hearer.tell_started(name)

    def announce(self, name: str) -> list[Hearer]:
        """Registrar `name` (re)started: the handles to tell, by name (recorded as announced
        now, for reports still on their way)."""
        with self._lock:
            self._announced[name] = runtime.monotonic()
            told = {**self._by_name.get(name, {}), **self._everything}
        return sorted(told, key=lambda hearer: hearer.name)

    def forget(self, hearer: Hearer) -> None:
        """`hearer`'s process ended (after its `exited` was set)."""
        with self._lock:
            self._everything.pop(hearer, None)
            for name in self._names.pop(hearer, ()):
                monitors = self._by_name.get(name)
                if monitors is not None:
                    monitors.pop(hearer, None)
                    if not monitors:
                        del self._by_name[name]

    def forget_in_child(self) -> None:
        """In a forked child: the handles are the parent's."""
        self._lock = runtime.Lock()
        self._by_name.clear()
        self._names.clear()
        self._everything.clear()
        self._announced.clear()


HEARERS = runtime.process_state(Hearers(), Hearers)


forkserver.after_fork_in_child("the hearers of starts", HEARERS.forget_in_child)
