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

How manager processes start, and what both ends agree on besides: the multiprocessing
context comes from the platform (`rr_actors._platform`): with the tricks, a forkserver of
rr_actors' own that has preloaded rr_actors (whoever started CPython's); plainly, a
forkserver (or spawn) without preload. Both sides agree on the exit codes below and on
what a clean stop is.
"""

from __future__ import annotations

import dataclasses
import multiprocessing.context
from collections.abc import Sequence
from typing import Any

from rr_actors._core.directory import DIRECTORY
from rr_actors._platform import PLATFORM
from rr_actors._platform.base import PARENT_GONE_EXIT
from rr_actors._transport.messenger import Address
from rr_actors.config import RegistrarConfig
from rr_actors.errors import CatalogCorruptError, RegistrarStoppedError

__all__ = [
    "ACTOR_DIED_EXIT",
    "PARENT_GONE_EXIT",
    "PROCESS_PREFIX",
    "STOPPED_EXIT",
    "TITLE_PREFIX",
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
    "forker_pid",
    "mp_context",
    "preload",
    "start_forkserver",
    "stopped_cleanly",
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


# -- how manager processes start ---------------------------------------------------------------

ACTOR_DIED_EXIT = 71
"""The exit code of a manager process whose registrar actor died (a crash)."""

STOPPED_EXIT = 72
"""The exit code of a manager process whose registrar stopped cleanly (code in the manager
stopped it, or the supervisor's `Stop`): its one normal exit. A process that exits 0 (a
library's `exit(0)`, an `os._exit(0)` in a callback) ended without stopping its
registrar: nothing it held was let go, so it is judged a crash (`manager.describe`)."""

PROCESS_PREFIX = "rr-manager-"
"""The `multiprocessing` name of every manager process starts with it."""

TITLE_PREFIX = "rr-actors: "
"""The process title of a manager process (`ps`) is this prefix and the manager's name."""

_PRELOAD = (
    "rr_actors._process.child",
    "rr_actors._registrar",
    "rr_actors._transport",
    "rr_actors._store.sqlite",
    "hmac",  # the transport's authkey handshake imports it lazily
    "setproctitle",  # if installed (the forkserver skips what does not import)
)
"""What a forkserver imports once for every manager process it forks (a platform trick)."""

_preload_more: tuple[str, ...] = ()  # `preload`'s modules, after `_PRELOAD`


def mp_context() -> multiprocessing.context.BaseContext:
    """The multiprocessing context for manager processes: forkserver, else spawn."""
    preload = (*_PRELOAD, *_preload_more)
    return PLATFORM.manager_context(preload=preload, lean_prefix=PROCESS_PREFIX)


def preload(modules: Sequence[str]) -> None:
    """Have the forkserver import `modules` too, once, for every manager process it forks.

    What it buys: a manager whose setup lives in one of `modules` does not import it
    after each fork. It takes effect only if the forkserver of this process has not
    started yet (the preload is read when it starts), and only where there is one
    (`Platform.manager_context`). A module that raises `ImportError` there is skipped;
    one that raises anything else ends the forkserver, and every manager start fails
    with it. Keep to modules that import without side effects (no threads started).

    Args:
        modules: module names (`"package.module"`), added to those already asked for.
    """
    global _preload_more
    _preload_more = tuple(dict.fromkeys((*_preload_more, *modules)))


def start_forkserver() -> None:
    """Start the forkserver now (if manager processes use one), not at the first manager.

    The forkserver (and multiprocessing's resource tracker) are long-lived helper children
    of this process; tests that count child processes start them before counting.
    """
    ctx = mp_context()
    if ctx.get_start_method() == "forkserver" and forker_pid(ctx) is None:
        from multiprocessing import forkserver  # noqa: PLC0415

        forkserver.ensure_running()  # CPython's: the platform keeps none of its own


def forker_pid(ctx: multiprocessing.context.BaseContext) -> int | None:
    """The pid of the process that forks manager processes, if the platform can tell.

    Handed to the child so that it can tell whether that process died before the child
    asked to be killed with it (`Platform.die_with_parent`).
    """
    return PLATFORM.forker_pid(ctx)


def stopped_cleanly(name: str) -> bool:
    """Whether registrar `name` of this process, no longer running, was stopped by code.

    `False` if its actor died (a crash). The same test for both placements, so a
    `transient` manager whose registrar was stopped cleanly is not restarted in a
    thread or in a process alike.
    """
    return isinstance(DIRECTORY.gone_error(name), RegistrarStoppedError)
