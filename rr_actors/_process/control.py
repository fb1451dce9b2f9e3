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
   Stop(timeout, restarting) ───────────────────────────────────►  registrar.stop()
                                          ◄──────── Stopped(code)   then it exits (code)
   PeerStarted(name) ───────────────────────────────────────────►  its registrars hear it
                                          ◄──────── Announce(name)  (a pool: one of its
                                                     managers restarted, tell the others)
                                          ◄──────── Monitoring(names, at) | HearsAll(on, at)
                                                    (whose starts its registrars hear:
                                                     only those are told, `hearers.py`)
   (EOF: the parent is gone) ───────────────────────────────────►  exit PARENT_GONE_EXIT
```

Each message is a frozen dataclass, pickled by the pipe; each end dispatches on its type
through one table. Both ends agree too on the exit codes, on what a clean stop is, and
on the multiprocessing context (the platform's: a forkserver, preloaded with the tricks).
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing.context
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any

from rr_actors._core.directory import DIRECTORY
from rr_actors._platform import PLATFORM, forkserver
from rr_actors._platform.base import PARENT_GONE_EXIT
from rr_actors._transport.messenger import Address
from rr_actors.config import RegistrarConfig
from rr_actors.errors import CatalogCorruptError, RegistrarStoppedError

__all__ = [
    "ACTOR_DIED_EXIT",
    "PARENT_GONE_EXIT",
    "POOL_GAVE_UP_EXIT",
    "POOL_HUNG_EXIT",
    "PROCESS_PREFIX",
    "STOPPED_EXIT",
    "TITLE_PREFIX",
    "Announce",
    "Events",
    "EventsSynced",
    "Failed",
    "Forward",
    "FromChild",
    "FromParent",
    "HearsAll",
    "Monitoring",
    "PeerStarted",
    "PeersStopped",
    "Ping",
    "Pong",
    "Probe",
    "Progress",
    "Ready",
    "Start",
    "Stop",
    "Stopped",
    "SyncEvents",
    "Warm",
    "WarmUp",
    "fork",
    "forker_pid",
    "mp_context",
    "preload",
    "start_forkserver",
    "stopped_cleanly",
]


# -- parent to child --------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, slots=True)
class Start:
    """Run this manager (to a spare idling in `standby`): `child.main`'s arguments."""

    setup: bytes
    config: RegistrarConfig
    address: Address | None
    forward: bool = False
    tally: str | None = None
    announced: bool = False  # (its supervisor announces its starts: `start_registrar`)


@dataclasses.dataclass(frozen=True, slots=True)
class WarmUp:
    """Warm up now: to a spare started without its warm-up (ahead of a start in order)."""


@dataclasses.dataclass(frozen=True, slots=True)
class Ping:
    """The heartbeat: answer `Pong(number, ...)` once the registrar actor got to it."""

    number: int


@dataclasses.dataclass(frozen=True, slots=True)
class Probe:
    """Ping `number` is late: answer `Progress` at once, from the control loop."""

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
    """Stop the registrar and exit within `timeout` seconds (`restarting`: no tombstone)."""

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
    """The manager could not start; `corrupt`: a `CatalogCorruptError` it raised, which
    the parent raises as it is (the recovery needs its `path`)."""

    traceback: str
    corrupt: CatalogCorruptError | None = None


@dataclasses.dataclass(frozen=True, slots=True)
class Pong:
    """The answer to `Ping(number)`; `trouble`: for how long (seconds) and why the
    registrar's listener has been unable to accept connections, if so."""

    number: int
    trouble: tuple[float, str] | None = None


@dataclasses.dataclass(frozen=True, slots=True)
class Progress:
    """The answer to `Probe(number)`: messages its registrar had handled when the ping
    arrived (`pinged`), has handled now, and that wait in its mailbox."""

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


@dataclasses.dataclass(frozen=True, slots=True)
class PeerStarted:
    """Registrar `name` (re)started: tell this manager's registrar (rule 20), on this pipe
    rather than by a connection from `name` to every manager process."""

    name: str


@dataclasses.dataclass(frozen=True, slots=True)
class PeersStopped:
    """Registrars `names` were stopped for good by the tree's stop (rule 12), `lost` killed in
    it (rule 19), told before this manager's own `Stop`: one notice per manager, not per pair."""

    names: tuple[str, ...]
    lost: tuple[str, ...] = ()


@dataclasses.dataclass(frozen=True, slots=True)
class Stopped:
    """Its registrar stopped (`Stop`): its catalog saved, its stop's events sent; what
    its dependents and providers need is done, and it exits with `code` next."""

    code: int


@dataclasses.dataclass(frozen=True, slots=True)
class Announce:
    """From a pool's process: its registrar `name` (re)started, and this process heard
    it; the parent tells the rest of the system (its `announce_started`), so that the
    pool's process links to no registrar it has no business with. `restarted`: the pool's
    own supervisor restarted it (the parent counts it in the child's `restarts`)."""

    name: str
    restarted: bool = False


@dataclasses.dataclass(frozen=True, slots=True)
class Monitoring:
    """A registrar of this process has business with registrars `names` now (Erlang's
    monitor): tell it their (re)starts, and those announced since `at` (monotonic
    seconds, read before it recorded them: a report that arrives late misses none)."""

    names: tuple[str, ...]
    at: float


@dataclasses.dataclass(frozen=True, slots=True)
class HearsAll:
    """A registrar of this process hears every (re)start (`on`: a restored one until its
    sweep has read every row), or none does any more; `at` as in `Monitoring`."""

    on: bool
    at: float


FromParent = (
    WarmUp | Start | Ping | Probe | Forward | SyncEvents | Stop | PeerStarted | PeersStopped
)
FromChild = (
    Warm
    | Ready
    | Failed
    | Pong
    | Progress
    | Events
    | EventsSynced
    | Announce
    | Monitoring
    | HearsAll
    | Stopped
)


# -- how manager processes start ---------------------------------------------------------------

ACTOR_DIED_EXIT = 71
"""The exit code of a manager process whose registrar actor died (a crash)."""

STOPPED_EXIT = 72
"""The exit code of a manager process whose registrar stopped cleanly: its one normal
exit (an exit 0 let nothing go: a crash)."""

POOL_GAVE_UP_EXIT = 73
"""The exit code of a pool's process (`SupervisorSpec(isolation="process")`) whose
supervisor gave up: OTP's `shutdown` of a nested supervisor, its parent decides."""

POOL_HUNG_EXIT = 74
"""The exit code of a pool's process with a hung thread manager (`PoolWatch`)."""

PROCESS_PREFIX = "rr-manager-"  # every manager process's `multiprocessing` name
TITLE_PREFIX = "rr-actors: "  # and its process title (`ps`), before the manager's name

_PRELOAD = (
    "rr_actors._process.child",
    "rr_actors._registrar",
    "rr_actors._transport",
    "rr_actors._store.saver",
    "hmac",  # the transport's authkey handshake imports it lazily
    "setproctitle",  # if installed (the forkserver skips what does not import)
)  # what a forkserver imports once for every manager process it forks

_preload_more: tuple[str, ...] = ()  # `preload`'s modules, after `_PRELOAD`


def mp_context() -> multiprocessing.context.BaseContext:
    """The multiprocessing context for manager processes: forkserver, else spawn."""
    preload = (*_PRELOAD, *_preload_more)
    return PLATFORM.manager_context(preload=preload, lean_prefix=PROCESS_PREFIX)


def preload(modules: Sequence[str]) -> None:
    """Have the forkserver import `modules` too, once, for every manager process it forks
    (only if it has not started yet). A module that raises anything but `ImportError`
    there ends the forkserver: keep to modules without side effects."""
    global _preload_more
    _preload_more = tuple(dict.fromkeys((*_preload_more, *modules)))


def fork(
    target: Callable[..., None],
    args: Callable[[Connection, int | None], tuple[Any, ...]],
    name: str,
    timeout: float,
) -> tuple[BaseProcess, Connection]:
    """Start a manager process running `target(*args(its pipe end, forker_pid))`; the
    process and the parent's end of its pipe (`TimeoutError`: not forked within `timeout`)."""
    ctx = mp_context()
    parent_conn, child_conn = ctx.Pipe(duplex=True)
    process = ctx.Process(  # type: ignore[attr-defined]
        target=target, args=args(child_conn, forker_pid(ctx)), name=name, daemon=True
    )
    try:
        forkserver.start_within(process, timeout)
    except BaseException:
        parent_conn.close()
        raise
    finally:
        child_conn.close()
    return process, parent_conn


READY_TIMEOUT = 120.0
"""Seconds `start_forkserver` waits for the forkserver's preload (a loaded machine's imports)."""

_ready_server: int | None = None  # the forkserver `start_forkserver` saw fork, by pid


def _nothing() -> None:
    """What the process `start_forkserver` forks runs: nothing."""


def start_forkserver() -> None:
    """Start the forkserver now (if manager processes use one), not at the first manager,
    and return once it forks: its preload imported (tests that count child processes start
    it before counting; a benchmark before its clock runs). Cheap once it has forked."""
    global _ready_server  # (one per process, like the server)
    ctx = mp_context()
    if ctx.get_start_method() != "forkserver":
        return
    pid = forker_pid(ctx)
    if pid is None:
        from multiprocessing import forkserver  # noqa: PLC0415

        forkserver.ensure_running()  # CPython's: the platform keeps none of its own
    elif pid != _ready_server:  # (a server imports its preload before its first fork)
        process, conn = fork(
            _nothing, lambda conn, forker: (), f"{PROCESS_PREFIX}ready", READY_TIMEOUT
        )
        conn.close()
        process.join(READY_TIMEOUT)
        with contextlib.suppress(ValueError):
            process.close()
        _ready_server = pid


def forker_pid(ctx: multiprocessing.context.BaseContext) -> int | None:
    """The pid of the process that forks manager processes, if the platform can tell."""
    return PLATFORM.forker_pid(ctx)


def stopped_cleanly(name: str) -> bool:
    """Whether registrar `name` of this process, no longer running, was stopped by code
    (not a crash): the same test for both placements."""
    return isinstance(DIRECTORY.gone_error(name), RegistrarStoppedError)
