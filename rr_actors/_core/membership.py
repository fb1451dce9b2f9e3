"""The membership of this process: which registrars are gone for good, which are back.

One per process (`MEMBERSHIP`), as Erlang's monitors are the runtime's. Whoever learns
that a registrar will not come back says so here; every registrar of this process hears
it, and one that starts later hears it when it joins, until a later incarnation is seen:

```
 a carrier's liveness (Messenger.lost) ─────────┐
 a death-watch mark of this process              ├─► lost(X) ─┐ record X gone for good,
   (_registrar/life.py: the death watch)         │            │ then every hearer:
 a death-watch mark from another process         │            ├─► peer_lost(X)
   (`ConsumerDown` on the wire, _registrar/life.py)           │   (the registrar's presence
                                                               │    role, rule 19)
 a registrar that starts ──► join(hearer) ──► the names gone for good now (it hears
                                              each as if it had heard the mark: Erlang's
                                              monitor of a dead process is 'DOWN' at once)
 a carrier: reachable again (Messenger.reachable) ─► reachable(X) ─► forget X, peer_reachable(X)
 X served again (a registrar named X starts here, a supervisor restarts it, a carrier
   sees it served) ─► back(X)
 a registrar here monitors X (`monitor`, `monitor_all`) ─► recorded; X new to this process:
   reported (`report`: a manager process's supervisor tells it only starts it monitors)
 a supervisor stopped X for good ─► stopped(X) ─► record, peers_stopped((X,)) (what X still
   holds here is stale: a stopped registrar holds nothing, rule 12); in the tree's stop,
   not to its managers still running here: each hears them all before its own stop
```
"""

from __future__ import annotations

import logging
from collections.abc import Container, Iterable
from typing import Protocol

from rr_actors._core import runtime
from rr_actors._platform import forkserver

logger = logging.getLogger("rr_actors")


class Hearer(Protocol):
    """What hears the membership's events (a registrar's presence role). Each call runs on the
    thread that reported the event, must return at once, and may come twice."""

    @property
    def name(self) -> str:
        """The registrar's name (it does not hear of itself)."""
        ...

    def peer_lost(self, name: str) -> None:
        """Registrar `name` is gone and nobody will restart it (rule 19)."""
        ...

    def peer_reachable(self, name: str) -> None:
        """Registrar `name` can be reached again after it could not be (rule 20)."""
        ...


class Joined(Hearer, Protocol):
    """A hearer that joined (a registrar of this process): it hears stops for good too."""

    def peers_stopped(self, names: tuple[str, ...]) -> None:
        """Registrars `names` were stopped for good: what they hold here is stale (rule 12)."""
        ...

    def peer_started(self, name: str) -> None:  # (one it monitors, rule 20)
        ...


class Report(Protocol):
    """Where this process reports whose starts its registrars hear (a manager process's
    control pipe to its supervisor, which tells it only those: `_process/hearers.py`).
    `at`: monotonic seconds, read before the change was recorded. Any thread."""

    def monitoring(self, names: tuple[str, ...], at: float) -> None: ...

    def hears_all(self, on: bool, at: float) -> None: ...


class Membership:
    """Who is gone for good, as this process knows it; the one sender of `peer_lost`."""

    report: Report | None = None  # (set in a manager process: `child.py`)

    def __init__(self) -> None:
        self._lock = runtime.Lock()
        self._gone: dict[str, bool] = {}  # name -> stopped (not lost)
        self._hearers: dict[str, Joined] = {}
        self._watchers: dict[str, set[str]] = {}  # name -> who monitors it (by name)
        self._everything: set[str] = set()  # who hears every start (`monitor_all`)

    def join(self, hearer: Joined, watching: Iterable[str] = ()) -> dict[str, bool]:
        """Let `hearer` hear every event and the starts of `watching` from now on; return the
        names gone for good now. Atomic with `lost`, `stopped`; its own name is back."""
        with self._lock:
            self._hearers[hearer.name] = hearer
            self._gone.pop(hearer.name, None)
            self.monitor(hearer.name, *watching)
            return dict(self._gone)

    def leave(self, hearer: Joined) -> None:
        """`hearer` hears nothing more (its registrar ended); no-op if it was replaced."""
        with self._lock:
            if self._hearers.get(hearer.name) is hearer:
                del self._hearers[hearer.name]

    def monitor(self, watcher: str, *targets: str) -> None:
        """Registrar `watcher` has business with `targets`: it hears their (re)starts.
        A target new to this process is reported (`report`), stamped before it is recorded."""
        new: list[str] = []
        at: float | None = None
        for target in targets:
            if watcher != target and watcher not in self._watchers.get(target, ()):
                if self.report is not None and target not in self._watchers:
                    at = runtime.monotonic() if at is None else at  # (before it is recorded)
                    new.append(target)
                self._watchers.setdefault(target, set()).add(watcher)  # (a GIL-atomic step)
        report = self.report
        if new and report is not None and at is not None:
            report.monitoring(tuple(new), at)

    def monitor_all(self, watcher: str, *, on: bool) -> None:
        """Registrar `watcher` hears every start (`on`) or only those it monitors; whether
        any registrar here hears every start is reported when that changes."""
        if self.report is None:  # (nothing to report: nothing to order, a GIL-atomic step)
            (self._everything.add if on else self._everything.discard)(watcher)
            return
        with self._lock:
            before, at = bool(self._everything), runtime.monotonic()
            (self._everything.add if on else self._everything.discard)(watcher)
            report = self.report
            if report is not None and before != bool(self._everything):
                report.hears_all(not before, at)  # (under the lock: reports in order)

    def started(self, name: str, *, skip: Container[str] = frozenset()) -> None:
        """Registrar `name` (re)started: each joined hearer that monitors it (not `skip`) hears."""
        watchers = sorted(self._watchers.get(name, set()) | self._everything)
        targets = [h for w in watchers if w not in skip and (h := self._hearers.get(w)) is not None]
        _tell(targets, "peer_started", name)

    def lost(self, name: str, *, by: str, hearers: tuple[Hearer, ...] = ()) -> None:
        """Registrar `name` is gone for good (`by` says who says so): record it, then every hearer
        and `hearers` (one named like a joined hearer is told once) hears it."""
        with self._lock:
            self._gone[name] = False
            targets: dict[str, Hearer] = {hearer.name: hearer for hearer in hearers}
            targets.update(self._hearers)
        logger.debug("membership: %s is gone for good (%s)", name, by)
        _tell(targets.values(), "peer_lost", name)

    def stopped(self, name: str, *, by: str, later: Container[str] = frozenset()) -> None:
        """Registrar `name` was stopped for good: record it (a record that it was lost stays), then
        every joined hearer hears it, unless its stop is recorded already: each hearer heard
        that one, or hears it as it joins (each registrar here that gets the mark from
        another process reports it, so N registrars told would be N x N tells). Hearers
        named in `later` are not told: their supervisor tells each of them once, before its
        own stop, every stop of the tree's stop so far (N x N tells again, otherwise)."""
        self.stopped_all((name,), by=by, later=later)

    def stopped_all(
        self, names: Iterable[str], *, by: str, later: Container[str] = frozenset()
    ) -> None:
        """`stopped` of each of `names`: each hearer told those not recorded yet at once."""
        with self._lock:
            new = tuple(dict.fromkeys(n for n in names if self._gone.get(n) is not True))
            self._gone.update({name: self._gone.get(name, True) for name in new})
            targets = [h for n, h in self._hearers.items() if n not in later]
        if not new:
            return
        logger.debug("membership: %s stopped for good (%s)", ", ".join(new), by)
        for hearer in targets:
            told = tuple(n for n in new if n != hearer.name)
            if told:
                try:
                    hearer.peers_stopped(told)
                except Exception:
                    logger.exception("registrar %s: peers_stopped%s failed", hearer.name, told)

    def reachable(self, name: str, *, hearers: tuple[Hearer, ...] = ()) -> None:
        """Registrar `name` can be reached again: forget its record, then every hearer hears it."""
        with self._lock:
            self._gone.pop(name, None)
            targets: dict[str, Hearer] = {hearer.name: hearer for hearer in hearers}
            targets.update(self._hearers)
        _tell(targets.values(), "peer_reachable", name)

    def back(self, name: str) -> None:
        with self._lock:
            self._gone.pop(name, None)

    def gone(self) -> dict[str, bool]:
        with self._lock:
            return dict(self._gone)

    def forget_in_child(self) -> None:
        """In a forked child: no hearers, no records (a spare may serve long after the fork: it
        hears from its supervisor and its carrier)."""
        self._lock = runtime.Lock()
        self._hearers.clear()
        self._gone.clear()
        self._watchers.clear()
        self._everything.clear()
        self.report = None  # (the pipe is its parent's)


def _tell(hearers: Iterable[Hearer], what: str, name: str) -> None:
    for hearer in hearers:
        if hearer.name != name:
            try:
                getattr(hearer, what)(name)
            except Exception:
                logger.exception("registrar %s: %s(%s) failed", hearer.name, what, name)


MEMBERSHIP = runtime.process_state(Membership(), Membership)


forkserver.after_fork_in_child("the membership", MEMBERSHIP.forget_in_child)
