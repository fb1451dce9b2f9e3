"""The death watch: what this process says when a registrar will not come back (rule 19).

Whoever knows that registrar `X` is gone for good says so here, and only here:

```
 a supervisor that gave up on X (_supervision/tree.py) ─┐
 the owner of an unsupervised manager process           ├─► gone_for_good(X, also=names)
   (_process/remote.py)                                 │     ConsumerDown of X to every
 X itself, dying with no restart expected (lifecycle.py)┘     registrar of this process
                                                              and to `also` (other
 a supervisor whose manager Y restarted, of each X that       processes, other hosts)
   died for good while Y was down ──────────────────────► tell_gone(Y, X)
 a supervisor whose manager X restarted empty ──────────► lost_everything(X, also=names)
                                                              ReconcileAsk(X) to all
```

The carriers say the same when whoever would say so is gone too (a host lost with its
supervisor): `Endpoint.peer_lost`, from one place, `rr_actors._transport.messenger`
(`tell_lost`). Both end in the receiving registrar's presence role
(`_registrar/presence.py`), which releases what `X` held there and reports `FATAL`
(then forgets) what was held at `X`. The layers above (`_process`, `_supervision`) call
these functions and never build a registrar message themselves.
"""

from __future__ import annotations

from collections.abc import Iterable

from rr_actors._core.directory import DIRECTORY
from rr_actors._registrar.messages import ConsumerDown, ReconcileAsk

__all__ = ["gone_for_good", "lost_everything", "tell_gone"]


def _mark(name: str) -> ConsumerDown:
    """The mark "registrar `name` will not come back", as the wire carries it."""
    return ConsumerDown(name)


def gone_for_good(name: str, *, also: Iterable[str] = ()) -> None:
    """Tell every registrar of this process, and those named in `also`, that registrar
    `name` is gone and nobody will restart it. One that cannot be reached is skipped."""
    DIRECTORY.broadcast(_mark(name), also=also, skip=name)


def tell_gone(target: str, name: str) -> None:
    """Tell registrar `target` only that registrar `name` is gone for good.

    Raises:
        RrError: `target` cannot be reached.
    """
    DIRECTORY.lookup(target).tell(_mark(name))


def lost_everything(name: str, *, also: Iterable[str] = ()) -> None:
    """Registrar `name` restarted with an empty catalog: every registrar of this process,
    and those named in `also`, that holds ids there reconciles with it (rule 20)."""
    DIRECTORY.broadcast(ReconcileAsk(name, holds_yours=False), also=also, skip=name)
