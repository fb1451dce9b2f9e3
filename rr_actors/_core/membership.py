"""The membership of this process: which registrars are gone for good, which are back.

One per process (`MEMBERSHIP`), as Erlang's monitors are the runtime's and rmw_zenoh's
graph cache is the node's (`GraphCache::parse_put/parse_del`). Whoever learns that a
registrar will not come back says so here; every registrar of this process hears it
from here, as one event (`peer_lost`), and one that starts later hears it when it joins:

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
 a supervisor stopped X for good ─► stopped(X) ─► record, peer_stopped(X) (what X still
   holds here is stale: a stopped registrar holds nothing, rule 12)
```

How long a record lives: until `X` is heard of again: a registrar named `X` joins in this
process, its supervisor starts it again (`back`), or a carrier sees it reachable. A mark
says "this incarnation will not come back", and only a later incarnation can make it
false; until one is seen, every registrar that starts here must treat `X` as gone (a
restored catalog may still hold ids at `X` or of `X`). A record is a name and a string,
so keeping it for the life of the process costs nothing that matters.
"""

from __future__ import annotations

import logging
from typing import Protocol

from rr_actors._core import runtime
from rr_actors._platform import fork

__all__ = ["MEMBERSHIP", "Hearer", "Joined", "Membership"]

logger = logging.getLogger("rr_actors")


class Hearer(Protocol):
    """What hears the membership's events (a registrar's presence role, through its
    `Served` endpoint). Each call runs on the thread that reported the event and must
    return at once; calling it twice is harmless."""

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

    def peer_stopped(self, name: str) -> None:
        """Registrar `name` was stopped and nobody will start it again (its supervisor
        said so): it holds nothing (rule 12), so what it still holds here is stale."""
        ...


class Membership:
    """Who is gone for good, as this process knows it; the one sender of `peer_lost`."""

    def __init__(self) -> None:
        self._lock = runtime.Lock()
        self._gone: dict[str, bool] = {}  # name -> stopped (not lost)
        self._hearers: dict[str, Joined] = {}

    def join(self, hearer: Joined) -> dict[str, bool]:
        """Let `hearer` hear every event from now on; return the names gone for good now,
        each with whether it was stopped (`True`) rather than lost.

        Atomic with `lost` and `stopped`: a mark is either in what this returns or heard
        later. Its own name is back (a record of it is dropped).
        """
        with self._lock:
            self._hearers[hearer.name] = hearer
            self._gone.pop(hearer.name, None)
            return dict(self._gone)

    def leave(self, hearer: Joined) -> None:
        """`hearer` hears nothing more (its registrar ended); no-op if it was replaced."""
        with self._lock:
            if self._hearers.get(hearer.name) is hearer:
                del self._hearers[hearer.name]

    def lost(self, name: str, *, by: str, hearers: tuple[Hearer, ...] = ()) -> None:
        """Registrar `name` is gone for good: record it, then every hearer hears it.

        Args:
            name: the registrar that will not come back.
            by: who says so (logged at debug level).
            hearers: others to tell as well (a carrier's endpoints that did not join:
                one named like a joined hearer is that hearer, told once).
        """
        with self._lock:
            self._gone[name] = False
            targets: dict[str, Hearer] = {hearer.name: hearer for hearer in hearers}
            targets.update(self._hearers)
        logger.debug("membership: %s is gone for good (%s)", name, by)
        for hearer in targets.values():
            if hearer.name != name:
                try:
                    hearer.peer_lost(name)
                except Exception:
                    logger.exception("registrar %s: peer_lost(%s) failed", hearer.name, name)

    def stopped(self, name: str, *, by: str) -> None:
        """Registrar `name` was stopped and will not be started again: record it, then
        every registrar of this process hears it (`peer_stopped`). A record that it was
        lost stays (a lost one holds nothing here either)."""
        with self._lock:
            self._gone.setdefault(name, True)
            targets = list(self._hearers.values())
        logger.debug("membership: %s was stopped for good (%s)", name, by)
        for hearer in targets:
            if hearer.name != name:
                try:
                    hearer.peer_stopped(name)
                except Exception:
                    logger.exception("registrar %s: peer_stopped(%s) failed", hearer.name, name)

    def reachable(self, name: str, *, hearers: tuple[Hearer, ...] = ()) -> None:
        """Registrar `name` can be reached again (a healed link): forget any record of
        it, then every hearer (and `hearers`, as in `lost`) hears it."""
        with self._lock:
            self._gone.pop(name, None)
            targets: dict[str, Hearer] = {hearer.name: hearer for hearer in hearers}
            targets.update(self._hearers)
        for hearer in targets.values():
            if hearer.name != name:
                try:
                    hearer.peer_reachable(name)
                except Exception:
                    logger.exception("registrar %s: peer_reachable(%s) failed", hearer.name, name)

    def back(self, name: str) -> None:
        """Registrar `name` is served again (a new incarnation): forget any record of it."""
        with self._lock:
            self._gone.pop(name, None)

    def gone(self) -> dict[str, bool]:
        """The names gone for good now, each with whether it was stopped (not lost)."""
        with self._lock:
            return dict(self._gone)

    def forget_in_child(self) -> None:
        """In a forked child: the parent's registrars do not hear here, and its records
        are dropped too (a spare may serve long after the fork, when a name recorded
        then may be back: the child hears what it needs from its supervisor,
        `tell_gone`, and from its carrier)."""
        self._lock = runtime.Lock()
        self._hearers.clear()
        self._gone.clear()


MEMBERSHIP = runtime.process_state(Membership(), Membership)


fork.after_fork_in_child("the membership", MEMBERSHIP.forget_in_child)
