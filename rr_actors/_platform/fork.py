"""What a process forked from one that runs rr_actors keeps, and what it must let go.

`os.fork()` copies the whole process but only the thread that forked: in the child the
registrars' actors, the carriers' reader, writer and accept threads, the worker pools and
the supervisors' threads are gone, while the objects that point at them (and the locks
those threads may have held at the fork) are still there. Left alone, a child that
starts a registrar and calls reaches its providers through the parent's connections,
whose answers the parent's reader threads take: every call times out.

So each layer that holds process-wide state registers here, at its import, how to let go
of it in a child; one `os.register_at_fork(after_in_child=...)` hook runs them in the
order they were registered, which is the import order: a layer is imported after the
layers below it, so the lowest layer resets first.

```
 os.fork() (or multiprocessing's "fork" start method)
   └─ in the child: _after_in_child ─► each reset, lowest layer first:
        _platform  the forkserver this process started is not the child's; nor are
                   the lock files it holds (`lockfile`: their copies closed)
        _core      the parent's actors are dead here; the directory forgets them; the
                   exit hook's list is emptied
        _transport the AF_UNIX systems stay joined (same runtime directory, same
                   authkey) but their listeners, connections and threads are dropped
                   (descriptors closed, never shut down: they are the parent's too);
                   a Zenoh session cannot be: the child is refused
```

A reset that finds something the child cannot use (a Zenoh session: its runtime's
threads are gone) calls `refuse`: from then on `check_usable` (run by
`ResourceRegistrar.start` and `Supervisor.start`) raises a `ConfigError` that says to
start the process with the `spawn` or `forkserver` method, never a silent timeout.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable

from rr_actors.errors import ConfigError

__all__ = ["after_fork_in_child", "check_usable", "forked_from", "refuse"]

logger = logging.getLogger("rr_actors")

_resets: list[tuple[str, Callable[[], None]]] = []
_refusals: list[str] = []
_parent: int | None = None  # the pid of the process this one was forked from
_forking: int | None = None  # this process's pid, noted just before it forks


def after_fork_in_child(what: str, reset: Callable[[], None]) -> None:
    """Have `reset()` run in every child forked from this process, on its only thread.

    Call it once per piece of state, at the import of the module that holds it. A reset
    must not wait for a lock a thread of the parent may have held (replace the lock),
    must not shut a socket down (the parent's copy would end too: close it), and must
    not stop or join anything (the threads are gone). What it raises refuses the child
    (`refuse`).

    Args:
        what: what it resets, for the refusal's message (`"the AF_UNIX carrier"`).
        reset: runs in the child right after the fork, before the child's own code.
    """
    _resets.append((what, reset))


def refuse(reason: str) -> None:
    """Say that this forked child cannot run rr_actors: `check_usable` raises from now on.

    Args:
        reason: what the parent had that the child cannot use, as the end of the sentence
            "the process it was forked from ..." (`"had opened a Zenoh session"`).
    """
    _refusals.append(reason)


def forked_from() -> int | None:
    """The pid of the process this one was forked from (after it ran rr_actors); `None`
    in a process that was not forked (spawned, or the forkserver's)."""
    return _parent


def check_usable(what: str) -> None:
    """Raise `ConfigError` if this process was forked from one it cannot inherit from.

    Args:
        what: what is being started (`"registrar 'erm'"`), for the message.

    Raises:
        ConfigError: the process it was forked from had state the child cannot use (a
            Zenoh session); the message names the `spawn` and `forkserver` methods.
    """
    if _refusals:
        raise ConfigError(
            f"cannot start {what}: this process was forked from process {_parent}, which "
            f"{'; and '.join(_refusals)}; a forked child cannot use that. Start the process "
            f"with the 'spawn' or 'forkserver' method instead "
            f"(multiprocessing.get_context('spawn') or get_context('forkserver'))"
        )


def _before() -> None:
    global _forking  # (one process-wide hook)
    _forking = os.getpid()


def _after_in_child() -> None:
    global _parent  # (one process-wide hook)
    _parent = _forking if _forking is not None else os.getppid()
    for what, reset in _resets:
        try:
            reset()
        except Exception as exc:  # noqa: BLE001 - the child is refused, not half reset
            refuse(f"left {what} in a state the child could not reset ({exc!r})")


os.register_at_fork(before=_before, after_in_child=_after_in_child)
