"""The death watch: what this process says when a registrar will not come back (rule 19).

Whoever knows that registrar `X` is gone for good says so here, and only here:

```
 a supervisor that gave up on X, or stopped ─┐
   it for good (_supervision/tree.py)        │    gone_for_good(X, also=names):
 the owner of an unsupervised manager process├─►  this process's membership records X
   (_process/remote.py)                      │    (`_core/membership.py`: every registrar
 X itself, dying with no restart expected    │    here hears `peer_lost`, and one that
   (lifecycle.py)                           ─┘    starts later hears it when it joins);
                                                  the wire mark, ConsumerDown(X), to each
                                                  of `also` in other processes / hosts,
                                                  whose membership records it in turn
 a supervisor whose manager Y restarted, of each X gone for good
   while Y was down (the supervisor's membership) ──────────────► tell_gone(Y, X)
 a supervisor whose manager X restarted empty ──► lost_everything(X, also=names)
                                                  ReconcileAsk(X) to all
```

The carriers say the same when whoever would say so is gone too (a host lost with its
supervisor): `rr_actors._transport.messenger.tell_lost`, into the same membership. Every
"lost" ends in the receiving registrar's presence role (`_registrar/presence.py`) as one
local message, `PeerLost`, which releases what `X` held there and reports `FATAL`
(then forgets) what was held at `X`. The layers above (`_process`, `_supervision`) call
these functions and never build a registrar message themselves.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

from rr_actors._core.directory import DIRECTORY
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._registrar.messages import ConsumerDown, ReconcileAsk
from rr_actors.errors import RrError

__all__ = ["back", "gone", "gone_for_good", "lost_everything", "tell_gone"]

logger = logging.getLogger("rr_actors")


def _mark(name: str, *, stopped: bool = False) -> ConsumerDown:
    """The mark "registrar `name` will not come back", as the wire carries it."""
    return ConsumerDown(name, stopped)


def gone_for_good(name: str, *, also: Iterable[str] = (), stopped: bool = False) -> None:
    """Registrar `name` is gone and nobody will restart it: this process's membership
    records it (every registrar here hears it, now or when it starts), and each of `also`
    of another process gets the mark. One that cannot be reached is skipped: a registrar
    that restarts hears it from its supervisor (`tell_gone`), one of another process
    from its own carrier or membership.

    With `stopped`, `name` was stopped cleanly (its supervisor stopped it for good): it
    holds nothing (rule 12), so what it still holds anywhere is released; what is held
    at it is left as a stop leaves it."""
    if stopped:
        MEMBERSHIP.stopped(name, by="its supervisor")
    else:
        MEMBERSHIP.lost(name, by="the death watch")
    here = {peer.name for peer in DIRECTORY.local_peers()}
    for target in sorted(set(also) - here - {name}):
        try:
            DIRECTORY.lookup(target).tell(_mark(name, stopped=stopped))
        except RrError:
            logger.debug("death watch: registrar %s unreachable", target)


def back(name: str) -> None:
    """Registrar `name` is started again (by its supervisor): it is no longer gone."""
    MEMBERSHIP.back(name)


def gone() -> dict[str, bool]:
    """The registrars this process knows are gone for good (its membership), each with
    whether it was stopped (not lost)."""
    return MEMBERSHIP.gone()


def tell_gone(target: str, name: str, *, stopped: bool = False) -> None:
    """Tell registrar `target` only that registrar `name` is gone for good (`stopped`:
    as `gone_for_good`).

    Raises:
        RrError: `target` cannot be reached.
    """
    DIRECTORY.lookup(target).tell(_mark(name, stopped=stopped))


def lost_everything(name: str, *, also: Iterable[str] = ()) -> None:
    """Registrar `name` restarted with an empty catalog: every registrar of this process,
    and those named in `also`, that holds ids there reconciles with it (rule 20)."""
    DIRECTORY.broadcast(ReconcileAsk(name, holds_yours=False), also=also, skip=name)
