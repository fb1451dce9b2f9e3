"""Which bound of the machine a failed start ran into, named in one line.

A tree too big for its machine first fails deep inside a start: a `fork` or a
`socketpair` in the supervisor's process (`OSError`), or a manager process that cannot
start a thread or open its backup (its traceback, relayed as text). `bound_reached`
finds the bound in that error, so that `Supervisor.start` says which one, with its
value and how to look at it, instead of where it was hit.
"""

from __future__ import annotations

import errno
import os
import resource
from collections.abc import Callable

_THREADS = "can't start new thread"
"""What CPython's `threading` says when the kernel refuses a thread (EAGAIN)."""


def _read(path: str) -> str:
    try:
        with open(path, encoding="ascii") as file:
            return file.read().strip()
    except OSError:
        return "?"


def _limit(kind: int) -> str:
    soft = resource.getrlimit(kind)[0]
    return "unlimited" if soft == resource.RLIM_INFINITY else str(soft)


def _open_files() -> str:
    return f"open files per process (RLIMIT_NOFILE {_limit(resource.RLIMIT_NOFILE)}: `ulimit -n`)"


def _threads() -> str:
    return (
        f"threads and processes (RLIMIT_NPROC {_limit(resource.RLIMIT_NPROC)}: `ulimit -u`; "
        f"kernel.threads-max {_read('/proc/sys/kernel/threads-max')}; "
        f"kernel.pid_max {_read('/proc/sys/kernel/pid_max')})"
    )


_BY_ERRNO: dict[int, Callable[[], str]] = {
    errno.EMFILE: _open_files,
    errno.ENFILE: lambda: (
        f"open files of the system (fs.file-max {_read('/proc/sys/fs/file-max')})"
    ),
    errno.EAGAIN: _threads,  # (from fork/clone: no process or thread could be made)
    errno.ENOMEM: lambda: "memory",
}

_BY_TEXT = (  # (a manager process's traceback, relayed as text)
    ("Too many open files in system", errno.ENFILE),
    ("Too many open files", errno.EMFILE),
    (_THREADS, errno.EAGAIN),
    ("Resource temporarily unavailable", errno.EAGAIN),
    ("Cannot allocate memory", errno.ENOMEM),
    ("MemoryError", errno.ENOMEM),
)


def bound_reached(error: BaseException) -> str | None:
    """The machine's bound `error` (or an error it was raised from) ran into, named with
    its value (`"open files per process (RLIMIT_NOFILE 1024: ..."`); `None` if none.

    A manager process that died while starting says nothing (a forkserver that could not
    hand it its descriptors, a thread refused before it could report): then this
    process's open files, and the system's threads, are compared with their bounds."""
    seen: set[int] = set()
    found: BaseException | None = error
    while found is not None and id(found) not in seen:
        seen.add(id(found))
        number = _errno_of(found)
        if number is not None:
            return _BY_ERRNO[number]()
        found = found.__cause__ or found.__context__
    return _near_a_bound()


NEAR = 0.9
"""How close to a bound counts as at it, when the error does not say (a share of it)."""


def _near_a_bound() -> str | None:
    soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    try:
        open_now = len(os.listdir("/proc/self/fd"))
        loadavg = _read("/proc/loadavg").split()
        threads_now = int(loadavg[3].split("/")[1])  # (every thread of the system)
        most = min(
            int(_read("/proc/sys/kernel/threads-max")), int(_read("/proc/sys/kernel/pid_max"))
        )
    except (OSError, ValueError, IndexError):  # (no /proc: nothing to compare)
        return None
    if soft != resource.RLIM_INFINITY and open_now >= NEAR * soft:
        return _open_files()
    if threads_now >= NEAR * most:
        return _threads()
    return None


def _errno_of(error: BaseException) -> int | None:
    if isinstance(error, OSError) and error.errno in _BY_ERRNO:
        return error.errno
    if isinstance(error, MemoryError):
        return errno.ENOMEM
    text = str(error)
    for phrase, number in _BY_TEXT:
        if phrase in text:
            return number
    return None


def first_line(error: BaseException) -> str:
    """`error`'s message up to its first line break (a relayed traceback is long)."""
    return str(error).split("\n", 1)[0].rstrip(":") or type(error).__name__


__all__ = ["bound_reached", "first_line"]
