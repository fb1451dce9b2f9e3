"""The world the protocol runs in: real threads and clocks, or a simulation of them.

The protocol code (`_core`, `_catalog`, `_store`, `_supervision`, the registrar and the
messenger) never uses `threading`, `time`, `uuid`, `random` or `queue` itself: it asks
this module, the only one that knows whether a simulation runs.

```
 protocol code ── runtime.Lock() · runtime.monotonic() · runtime.Thread(...).start() ──┐
                                                                                        │
   real (the default): the stdlib's own objects and functions ◄──────────────────────────┤
   simulated, while `rr_actors.simulation` runs (`use(seams)`): its greenlet-aware      │
   objects, its virtual clock and its seeded randomness ◄────────────────────────────────┘
```

Each name is read where an object is made or a function called (`runtime.Lock()`,
`runtime.monotonic()`), never imported by value (`from ... import Lock` would keep the
real one: `tests/test_repository.py` refuses it). So in a real run `runtime.Lock` *is*
`threading.Lock`: the cost is the attribute read at construction, as `threading.Lock`'s
own, and nothing per operation.

Made here, the same in both worlds: query ids (`new_id`, from `urandom`) and one-shot
timers (`thread_timer`, a daemon `Timer`; a test injects its own `StartTimer`).

What is per process (the directory of registrars, the membership, the clock, pykka's
registry) is registered here with `process_state`, as `_platform.fork` registers what a
forked child lets go of: a simulation gives each simulated process its own. What is per
thread is made with `local()`: a simulation gives each simulated thread its own contents.
"""

from __future__ import annotations

import asyncio
import os
import queue
import random as _random
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any, Protocol, TypeVar

__all__ = [
    "SEAMS",
    "TIMEOUT_MAX",
    "Cancellable",
    "Condition",
    "Empty",
    "Event",
    "Full",
    "Lock",
    "RLock",
    "SimpleQueue",
    "StartTimer",
    "Thread",
    "Timer",
    "current_thread",
    "get_ident",
    "getpid",
    "getrandbits",
    "guards_files",
    "handles_signals",
    "hold",
    "local",
    "manager_process",
    "monotonic",
    "new_event_loop",
    "new_id",
    "process_state",
    "process_states",
    "queue_class",
    "random",
    "simulated",
    "sleep",
    "thread_locals",
    "thread_timer",
    "urandom",
    "use",
    "wall",
    "wall_ns",
]

T = TypeVar("T")
Q = TypeVar("Q", bound=queue.SimpleQueue[Any])
F = TypeVar("F")

# -- the seams: the stdlib's own, until a simulation replaces them ----------------------

Lock = threading.Lock
RLock = threading.RLock
Event = threading.Event
Condition = threading.Condition
SimpleQueue = queue.SimpleQueue
Thread = threading.Thread
Timer = threading.Timer

monotonic = time.monotonic
"""Seconds of a clock that never steps back: deadlines and durations."""
wall = time.time
"""Seconds since the epoch (as `time.time()`)."""
wall_ns = time.time_ns
"""Nanoseconds since the epoch (the hybrid clock's physical clock)."""
sleep = time.sleep
"""Never in protocol code (it waits on events, futures and timers); for workloads."""
urandom = os.urandom
"""`urandom(n)`: `n` random bytes (query ids, file tokens)."""
random = _random.random
getrandbits = _random.getrandbits
"""`getrandbits(k)`: an int of `k` random bits (a traced call's span id)."""
"""A float in `[0, 1)`: jitter and backoff."""
get_ident = threading.get_ident
current_thread = threading.current_thread
getpid = os.getpid
"""The pid of the calling thread's process (in a simulation, its simulated process's)."""
new_event_loop = asyncio.new_event_loop
"""A new asyncio event loop (in a simulation, one on the virtual clock whose wait is a
simulated thread's: `rr_actors.simulation._loop`)."""


def guards_files() -> bool:
    """Whether the files the protocol keeps (its catalog backups) need guarding against
    what happens to them outside it: another program deleting or replacing one, a log
    cut short by an OS crash. Always in a real run; a simulation's backups are its own
    (a private folder that none of its faults touches: it deletes, replaces and cuts
    short nothing), so there the store skips the checks that only that needs (a `stat`
    of the file and its `-wal` before each commit, the commit count beside the log)."""
    return True


def hold(file: F) -> F:
    """`file` (an open file of the calling process with a `close()` that may be called
    again: an `sqlite3.Connection`, a socket), registered as the process's: returned.

    In a real run nothing happens: the kernel closes a process's files when it dies. In a
    simulation, where a process's death is its tasks never running again in a process
    that lives on, the simulated process that called it closes `file` when it ends (a
    kill or an exit) or the run does, whichever comes first: not the garbage collector,
    which may never (a dropped task that would not end keeps its frames, and what else
    holds a run's objects, a traceback kept by a log handler, keeps them too).
    """
    return file


manager_process: Any = None
"""`None` in a real run (`rr_actors._process` forks manager processes); in a simulation,
what starts a simulated one instead (`ManagerProcess.start` hands over to it, with its
own arguments)."""


def queue_class(cls: type[Q]) -> type[Q]:
    """The class to make for `cls`, a subclass of `queue.SimpleQueue` (`LateQueue`):
    `cls` itself in a real run; in a simulation, a subclass of it whose queue methods
    (`put`, `get`, ...) are the simulated queue's, where `cls` does not define its own."""
    return cls


SEAMS = (
    "Lock",
    "RLock",
    "Event",
    "Condition",
    "SimpleQueue",
    "Thread",
    "Timer",
    "monotonic",
    "wall",
    "wall_ns",
    "sleep",
    "urandom",
    "random",
    "getrandbits",
    "get_ident",
    "current_thread",
    "getpid",
    "new_event_loop",
    "guards_files",
    "hold",
    "queue_class",
    "manager_process",
)
"""The names a simulation replaces (`use`); every other name here is the same in both."""

# -- the same in both worlds ------------------------------------------------------------

Empty = queue.Empty
Full = queue.Full
TIMEOUT_MAX = threading.TIMEOUT_MAX

_VARIANT = {digit: "89ab"[int(digit, 16) & 3] for digit in "0123456789abcdef"}
"""A random hex digit -> a variant digit (its two low bits kept, the high two set to 10)."""


def new_id() -> str:
    """A random UUID4 as a string (`str(uuid.uuid4())` gives the same form): the hex digits
    of 16 bytes from `urandom` (a simulation's seeded bytes), the version digit set to 4
    and the variant digit to one of `89ab` (RFC 4122), without building a `uuid.UUID`."""
    h = urandom(16).hex()
    return f"{h[:8]}-{h[8:12]}-4{h[13:16]}-{_VARIANT[h[16]]}{h[17:20]}-{h[20:]}"


class Cancellable(Protocol):
    """A started timer (`threading.Timer` is one)."""

    def cancel(self) -> None:
        """Stop the timer if it has not fired yet."""


StartTimer = Callable[[float, Callable[[], None]], Cancellable]
"""`start(delay, fn)`: run `fn()` once after `delay` seconds on some thread."""


def thread_timer(delay: float, fn: Callable[[], None]) -> Cancellable:
    """Run `fn()` on a daemon `Timer` thread after `delay` seconds (the default
    `StartTimer`)."""
    timer = Timer(delay, fn)
    timer.daemon = True
    timer.start()
    return timer


REAL = {name: globals()[name] for name in SEAMS}
"""The real seams (the stdlib's own objects), by name: what `use(None)` puts back."""
_simulated = False
_states: list[tuple[object, Callable[[], object]]] = []
_locals: list[threading.local] = []


def use(seams: Mapping[str, Any] | None) -> None:
    """Run the protocol on `seams` from now on (a value for every name of `SEAMS`), or on
    the real threads and clocks again (`None`). For `rr_actors.simulation` only: objects
    made before keep the world they were made in.

    Raises:
        ValueError: `seams` lacks a name of `SEAMS`, or has one that is not a seam.
    """
    global _simulated  # (this module's one switch)
    if seams is not None and set(seams) != set(SEAMS):
        raise ValueError(f"a simulation replaces exactly {SEAMS}, not {tuple(seams)}")
    globals().update(REAL if seams is None else seams)
    _simulated = seams is not None


def simulated() -> bool:
    """Whether a simulation runs now."""
    return _simulated


def handles_signals() -> bool:
    """Whether Python runs signal handlers on the calling thread (a `KeyboardInterrupt` is
    raised there): the main thread of a real run; never a simulated thread."""
    return not _simulated and threading.current_thread() is threading.main_thread()


def local() -> threading.local:
    """A thread-local namespace (`threading.local`) that a simulation keeps per simulated
    thread too (`thread_locals`). Made once, at import."""
    namespace = threading.local()
    _locals.append(namespace)
    return namespace


def thread_locals() -> tuple[threading.local, ...]:
    """Every namespace made by `local`, in the order made."""
    return tuple(_locals)


def process_state(obj: T, fresh: Callable[[], object]) -> T:
    """Register `obj` as state of this process; returns it.

    `fresh()` makes the state of a process that starts (an object whose attributes are
    `obj`'s): a simulation sets `obj`'s attributes to a fresh one's in each simulated
    process, and back when it ends. In a real run nothing happens: `obj` is the one
    process's own. Call it once, at the import of the module that holds `obj`.
    """
    _states.append((obj, fresh))
    return obj


def process_states() -> tuple[tuple[object, Callable[[], object]], ...]:
    """Every `(obj, fresh)` registered with `process_state`, in the order registered."""
    return tuple(_states)
