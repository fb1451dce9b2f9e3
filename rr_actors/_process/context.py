"""How manager processes are started, and what both sides of one agree on.

The multiprocessing context comes from the platform (`rr_actors._platform`): with the
tricks, a forkserver of rr_actors' own that has preloaded rr_actors (whoever started
CPython's); plainly, a forkserver (or spawn)
without preload. Both sides agree on the exit codes below and on what a clean stop is.
"""

from __future__ import annotations

import multiprocessing.context
from collections.abc import Sequence

from rr_actors._core.directory import DIRECTORY
from rr_actors._platform import PLATFORM
from rr_actors._platform.portable import PARENT_GONE_EXIT
from rr_actors.errors import RegistrarStoppedError

__all__ = [
    "ACTOR_DIED_EXIT",
    "PARENT_GONE_EXIT",
    "PROCESS_PREFIX",
    "STOPPED_EXIT",
    "TITLE_PREFIX",
    "forker_pid",
    "mp_context",
    "preload",
    "start_forkserver",
    "stopped_cleanly",
]

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
