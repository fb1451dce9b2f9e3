"""The control pipe's vocabulary: what a manager process and its parent tell each other.

```
 parent (ManagerProcess, SparePool)          control pipe          child (child.py)
   WarmUp() ────────────────────────────────────────────────────►  standby (a spare
                                                                     started unwarmed)
   Start(setup, config, address, forward) ──────────────────────►  standby (a spare only)
                                          ◄──────── Warm()           (a spare, once warm)
                                          ◄──────── Ready(pid) | Failed(traceback, corrupt)
   Ping(number) ────────────────────────────────────────────────►  registrar mailbox
                                          ◄──────── Pong(number, trouble)
   Probe(number)  (a late ping) ────────────────────────────────►  the control loop
                                          ◄──────── Progress(number, pinged, handled, queued)
   Forward(on) ─────────────────────────────────────────────────►  forward events or not
                                          ◄──────── Events(batch)   (while on)
   SyncEvents(token, timeout) ──────────────────────────────────►  send what is buffered
                                          ◄──────── EventsSynced(token)
   Stop(timeout, restarting) ───────────────────────────────────►  registrar.stop(); exit
```

Each message is a frozen dataclass; each end dispatches on its type through one table
(`child._HANDLERS`, `ManagerProcess._HANDLERS`). They are pickled by the pipe
(`multiprocessing.connection`), between processes of one machine and one installation.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from rr_actors._transport.base import Address
from rr_actors.config import RegistrarConfig
from rr_actors.errors import CatalogCorruptError

__all__ = [
    "Events",
    "EventsSynced",
    "Failed",
    "Forward",
    "FromChild",
    "FromParent",
    "Ping",
    "Pong",
    "Probe",
    "Progress",
    "Ready",
    "Start",
    "Stop",
    "SyncEvents",
    "Warm",
    "WarmUp",
]


# -- parent to child --------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, slots=True)
class Start:
    """Run this manager (to a spare idling in `standby`): `child.main`'s arguments.

    Attributes:
        setup: `wire.dumps(setup_function_or_None)` (cloudpickle).
        config: the registrar's configuration.
        address: the system to attach to, or `None` to run unattached.
        forward: forward the registrar's events from the start.
        tally: the file where it counts the events it builds (`rr_actors._process.tally`),
            or `None`.
    """

    setup: bytes
    config: RegistrarConfig
    address: Address | None
    forward: bool = False
    tally: str | None = None


@dataclasses.dataclass(frozen=True, slots=True)
class WarmUp:
    """Warm up now: to a spare started without its warm-up (ahead of a start in order)."""


@dataclasses.dataclass(frozen=True, slots=True)
class Ping:
    """The heartbeat: answer `Pong(number, ...)` once the registrar actor got to it."""

    number: int


@dataclasses.dataclass(frozen=True, slots=True)
class Probe:
    """Ping `number` is late: answer `Progress` at once, from the control loop (not
    through the registrar's mailbox, where the ping waits)."""

    number: int


@dataclasses.dataclass(frozen=True, slots=True)
class Forward:
    """Forward the registrar's events (`on`), or stop forwarding them."""

    on: bool


@dataclasses.dataclass(frozen=True, slots=True)
class SyncEvents:
    """Send what is buffered, then `EventsSynced(token)`, within `timeout` seconds."""

    token: int
    timeout: float


@dataclasses.dataclass(frozen=True, slots=True)
class Stop:
    """Stop the registrar within `timeout` seconds and exit.

    Attributes:
        timeout: seconds the registrar's clean stop may take.
        restarting: it is stopped to be restarted with its group: no tombstone, so its
            peers see it unavailable for now, not stopped for good.
    """

    timeout: float
    restarting: bool = False


# -- child to parent --------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, slots=True)
class Warm:
    """A spare has finished warming up."""


@dataclasses.dataclass(frozen=True, slots=True)
class Ready:
    """The manager serves: its catalog is restored and its setup ran."""

    pid: int


@dataclasses.dataclass(frozen=True, slots=True)
class Failed:
    """The manager could not start (its setup raised, say).

    Attributes:
        traceback: what it raised, with its traceback, as text.
        corrupt: what it raised if that was a `CatalogCorruptError` (its backup cannot
            be read), which the parent raises as it is: the recovery needs its `path`
            (`quarantine_backup`). Pickled by its `__reduce__` (two strings).
    """

    traceback: str
    corrupt: CatalogCorruptError | None = None


@dataclasses.dataclass(frozen=True, slots=True)
class Pong:
    """The answer to `Ping(number)`.

    Attributes:
        number: the ping's number.
        trouble: `None`, or for how long (seconds) and why the registrar's listener has
            been unable to accept connections.
    """

    number: int
    trouble: tuple[float, str] | None = None


@dataclasses.dataclass(frozen=True, slots=True)
class Progress:
    """The answer to `Probe(number)`: whether the registrar works through its mailbox.

    Attributes:
        number: the ping's number.
        pinged: messages its registrar actor had handled when ping `number` arrived.
        handled: messages it has handled now.
        queued: messages waiting in its mailbox now.
    """

    number: int
    pinged: int
    handled: int
    queued: int


@dataclasses.dataclass(frozen=True, slots=True)
class Events:
    """A batch of the registrar's events (`rr_actors.events` values), in order."""

    batch: list[Any]


@dataclasses.dataclass(frozen=True, slots=True)
class EventsSynced:
    """What was buffered when `SyncEvents(token)` arrived has been sent (before this)."""

    token: int


FromParent = WarmUp | Start | Ping | Probe | Forward | SyncEvents | Stop
"""What the parent sends down a control pipe."""

FromChild = Warm | Ready | Failed | Pong | Progress | Events | EventsSynced
"""What a manager process sends up its control pipe."""
