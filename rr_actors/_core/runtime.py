"""The world the protocol runs in: real threads and clocks, or a simulation of them.

The protocol code (`_core`, `_catalog`, `_store`, `_supervision`, the registrar and the messenger)
never uses `threading`, `time`, `uuid`, `random` or `queue` itself: it asks this module, the only
one that knows whether a simulation runs.

```
 protocol code ── runtime.Lock() · runtime.monotonic() · runtime.Thread(...).start() ──┐
                                                                                        │
   real (the default): the stdlib's own objects and functions ◄──────────────────────────┤
   simulated, while `rr_actors.simulation` runs (`use(seams)`): its greenlet-aware      │
   objects, its virtual clock and its seeded randomness ◄────────────────────────────────┘
```

Each name is read where it is used (`runtime.Lock()`), never imported by value
(`tests/test_repository.py` refuses it): in a real run `runtime.Lock` *is* `threading.Lock`, at the
cost of one attribute read. Per-process state is registered with `process_state`, per-thread state
made with `local()`: a simulation gives each simulated process and thread its own. (The protocol
steps a classroom exercise replaces are a value passed in: `rr_actors.config.Steps`.)
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
"""A float in `[0, 1)`: jitter and backoff."""
getrandbits = _random.getrandbits
"""`getrandbits(k)`: an int of `k` random bits (a traced call's span id)."""
get_ident = threading.get_ident
current_thread = threading.current_thread
getpid = os.getpid
"""The pid of the calling thread's process (in a simulation, its simulated process's)."""
new_event_loop = asyncio.new_event_loop
"""A new asyncio event loop (in a simulation, one on the virtual clock)."""


def guards_files() -> bool:
    """Whether the catalog backups need guarding against other programs and OS crashes (the
    checks before each commit): always in a real run, never for a simulation's own files."""
    return True


def hold(file: F) -> F:
    """`file` (closable twice), registered as the calling process's: in a simulation, closed when
    the simulated process or the run ends; nothing in a real run."""
    return file


manager_process: Any = None
"""`None` in a real run; in a simulation, what starts a simulated manager process."""


def queue_class(cls: type[Q]) -> type[Q]:
    """The class to make for `cls`, a `queue.SimpleQueue` subclass: `cls` in a real run; in a
    simulation, a subclass whose queue methods are the simulated queue's."""
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
    """A random UUID4 string from `urandom` (a simulation's seeded bytes), without a `uuid.UUID`."""
    h = urandom(16).hex()
    return f"{h[:8]}-{h[8:12]}-4{h[13:16]}-{_VARIANT[h[16]]}{h[17:20]}-{h[20:]}"


class Cancellable(Protocol):
    """A started timer (`threading.Timer` is one)."""

    def cancel(self) -> None: ...


StartTimer = Callable[[float, Callable[[], None]], Cancellable]
"""`start(delay, fn)`: run `fn()` once after `delay` seconds on some thread."""


def thread_timer(delay: float, fn: Callable[[], None]) -> Cancellable:
    """Run `fn()` on a daemon `Timer` thread after `delay` seconds (the default `StartTimer`)."""
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
    """Run the protocol on `seams` (every name of `SEAMS`; `ValueError` otherwise), or the real
    world again (`None`). For `rr_actors.simulation` only."""
    global _simulated  # (this module's one switch)
    if seams is not None and set(seams) != set(SEAMS):
        raise ValueError(f"a simulation replaces exactly {SEAMS}, not {tuple(seams)}")
    globals().update(REAL if seams is None else seams)
    _simulated = seams is not None


def simulated() -> bool:
    return _simulated


def handles_signals() -> bool:
    """Whether Python runs signal handlers on the calling thread: a real run's main thread."""
    return not _simulated and threading.current_thread() is threading.main_thread()


def local() -> threading.local:
    """A `threading.local` that a simulation keeps per simulated thread too (made at import)."""
    namespace = threading.local()
    _locals.append(namespace)
    return namespace


def thread_locals() -> tuple[threading.local, ...]:
    return tuple(_locals)


def process_state(obj: T, fresh: Callable[[], object]) -> T:
    """Register `obj` (at its module's import) as this process's state; returns it. A simulation
    gives each simulated process `fresh()`'s attributes; nothing in a real run."""
    _states.append((obj, fresh))
    return obj


def process_states() -> tuple[tuple[object, Callable[[], object]], ...]:
    return tuple(_states)
