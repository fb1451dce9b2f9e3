"""How manager processes are started, and what both sides of one agree on.

The multiprocessing context comes from the platform (`rr_actors._platform`): with the
tricks, a forkserver of rr_actors' own that has preloaded rr_actors (whoever started
CPython's); plainly, a forkserver (or spawn)
without preload. Both sides agree on the exit codes below and on what a clean stop is.
"""

from __future__ import annotations

import multiprocessing.context

from rr_actors._core.directory import DIRECTORY
from rr_actors._platform import PLATFORM
from rr_actors._platform.portable import PARENT_GONE_EXIT
from rr_actors.errors import RegistrarStoppedError

__all__ = [
    "ACTOR_DIED_EXIT",
    "PARENT_GONE_EXIT",
    "PROCESS_PREFIX",
    "TITLE_PREFIX",
    "forker_pid",
    "mp_context",
    "start_forkserver",
    "stopped_cleanly",
]

ACTOR_DIED_EXIT = 71
"""The exit code of a manager process whose registrar actor died (a crash)."""

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


def mp_context() -> multiprocessing.context.BaseContext:
    """The multiprocessing context for manager processes: forkserver, else spawn."""
    return PLATFORM.manager_context(preload=_PRELOAD, lean_prefix=PROCESS_PREFIX)


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
