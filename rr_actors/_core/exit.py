"""Stop what a program left running when its main thread ends.

A Zenoh session's threads are not daemons: one left open keeps the interpreter waiting. So that a
script that forgets `stop()` or `close()` still ends cleanly, every running supervisor, registrar
and network is listed here:

```
 main thread ends (returns, or an exception's traceback was printed)
   └─ threading._shutdown ─► stop_everything(): supervisors, newest first (each stops its
                              managers and the registrars it made), then the registrars
                              still running, newest first, then the networks still open;
                              all within EXIT_TIMEOUT s. A registrar holding ids at a
                              registrar or tree still to stop goes before it (`_in_order`)
      ─► the interpreter then joins non-daemon threads (Zenoh's end with their session)
         and runs atexit
```

A Ctrl-C that reaches the top of the main thread prints one line (`python -X dev`: the traceback).
"""

from __future__ import annotations

import itertools
import logging
import sys
from collections.abc import Callable, Collection
from types import TracebackType

from rr_actors._core import runtime
from rr_actors._platform import PLATFORM, forkserver

logger = logging.getLogger("rr_actors")

EXIT_TIMEOUT = 10.0
"""Seconds that stopping everything left running may take when the main thread ends."""

SUPERVISORS = 0
REGISTRARS = 1
NETWORKS = 2
"""Tiers: supervisors stop first (they stop what they started), then registrars, then networks."""

_MIN_STOP = 0.1  # seconds each stop still gets once EXIT_TIMEOUT ran out

_Names = Callable[[float], Collection[str]]
_Entry = tuple[int, str, Callable[[], bool], Callable[[float], None], Collection[str], _Names]

_HOLDS_TIMEOUT = 1.0  # seconds each registrar may take to say where it holds ids, at exit


class _Listed:
    """What this process lists to stop at its end (a simulated process: its own)."""

    def __init__(self) -> None:
        self.lock = runtime.Lock()
        self.entries: dict[int, _Entry] = {}
        self.numbers = itertools.count()
        self.prune_at = 64  # entries; doubled after each pruning, so adding stays O(1) amortised


_LISTED = runtime.process_state(_Listed(), _Listed)
_hooked = False


def _nowhere(_timeout: float) -> Collection[str]:
    return ()


def stop_at_exit(
    tier: int,
    what: str,
    alive: Callable[[], bool],
    stop: Callable[[float], None],
    *,
    provides: Collection[str] = (),
    holds: _Names = _nowhere,
) -> None:
    """Have `stop(timeout)` called when the main thread ends, if `alive()` (cheap, any thread) then.
    `tier` orders the stops (lower first); `what` names it; `provides`: the registrars it serves,
    `holds(timeout)`: those it holds ids at (asked at the end; raising: none). Dead entries are
    pruned when their number doubled."""
    global _hooked  # (the hook: once per process)
    listed = _LISTED
    with listed.lock:
        entries = listed.entries
        if len(entries) >= listed.prune_at:
            for number in [n for n, entry in entries.items() if not entry[2]()]:
                del entries[number]
            listed.prune_at = max(64, 2 * len(entries))
        entries[next(listed.numbers)] = (tier, what, alive, stop, provides, holds)
        if not _hooked:
            try:
                PLATFORM.at_main_thread_end(stop_everything)
            except RuntimeError:  # the interpreter is shutting down already
                return
            _hooked = True
            _one_line_interrupts()


def stop_everything(timeout: float = EXIT_TIMEOUT) -> None:
    """Stop every listed supervisor and registrar that still runs; newest first per tier.
    One holding ids at another goes first (its release reaches a running provider). A Ctrl-C
    skips the supervisors and registrars left, not the networks (their threads would hang)."""
    deadline = runtime.monotonic() + timeout
    with _LISTED.lock:
        entries = [
            entry for _, entry in sorted(_LISTED.entries.items(), key=lambda i: (i[1][0], -i[0]))
        ]
        _LISTED.entries.clear()
    interrupted = False
    try:
        entries = _in_order(entries, deadline)
    except KeyboardInterrupt:  # (asking where registrars hold ids): in tier order, then
        interrupted = True
    for tier, what, alive, stop, _provides, _holds in entries:
        if interrupted and tier < NETWORKS:
            continue
        try:
            if alive():
                logger.info("stopping %s: it was still running when the program ended", what)
                stop(max(_MIN_STOP, deadline - runtime.monotonic()))
        except KeyboardInterrupt:
            if interrupted:
                return
            interrupted = True
        except Exception:
            logger.exception("stopping what was left running at exit failed")


def _in_order(entries: list[_Entry], deadline: float) -> list[_Entry]:
    """`entries` with each that holds ids at another before it; a tree's managers (their tree
    stops them) and the networks last. In a cycle, the first in tier order goes first."""
    running = [entry for entry in entries if entry[0] < NETWORKS and entry[2]()]
    managed = {name for entry in running if entry[0] == SUPERVISORS for name in entry[4]}
    left = [e for e in running if e[0] == SUPERVISORS or not managed.intersection(e[4])]
    holds: list[set[str]] = []
    for tier, _what, _alive, _stop, provides, ask in left:
        names: set[str] = set()
        if tier != SUPERVISORS:
            timeout = min(_HOLDS_TIMEOUT, max(_MIN_STOP, deadline - runtime.monotonic()))
            try:
                names = set(ask(timeout)).difference(provides)
            except Exception:  # (stopped meanwhile, or stuck: it holds none)
                logger.debug("asking where a registrar holds ids at exit failed", exc_info=True)
        holds.append(names)
    ordered: list[_Entry] = []
    while left:
        at = next(
            (
                i
                for i, entry in enumerate(left)
                if not any(j != i and held.intersection(entry[4]) for j, held in enumerate(holds))
            ),
            0,
        )
        ordered.append(left.pop(at))
        holds.pop(at)
    rest = [entry for entry in entries if entry not in ordered]  # managers, networks
    return ordered + sorted(rest, key=lambda entry: entry[0] >= NETWORKS)


def _one_line_interrupts() -> None:
    previous = sys.excepthook

    def hook(
        kind: type[BaseException], exc: BaseException, traceback: TracebackType | None
    ) -> None:
        if kind is KeyboardInterrupt and not sys.flags.dev_mode:  # (not a subclass: its
            # message may say more, as `ExperimentInterruptedError`'s does)
            print("KeyboardInterrupt", file=sys.stderr, flush=True)  # noqa: T201 - as Python
            return
        previous(kind, exc, traceback)

    sys.excepthook = hook


def left_running() -> list[str]:
    with _LISTED.lock:
        return [entry[1] for _, entry in sorted(_LISTED.entries.items()) if entry[2]()]


def _forget_all() -> None:
    _LISTED.lock = runtime.Lock()  # a thread of the parent may have held it at the fork
    _LISTED.entries.clear()


forkserver.after_fork_in_child("the exit hook's list", _forget_all)
