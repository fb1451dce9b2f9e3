"""Finding every process an experiment started, wherever it ended up in the process tree.

Each run process is started with `RR_ACTORS_EXPERIMENT=<token>`, which every process it
starts inherits (forkserver, managers, their programs, re-parented or not); a scan of
`/proc/<pid>/environ` finds them all (Linux). Also the resource processes a fault may kill
(`resource_processes`), each with its creation time, so a reused pid is never taken.
"""

from __future__ import annotations

import contextlib
import os
import selectors
import signal
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import rr_actors as rr

__all__ = [
    "PRELOAD_VARIABLE",
    "TOKEN_VARIABLE",
    "children",
    "cmdline",
    "kill",
    "parent",
    "processes_with",
    "resource_processes",
    "start_time",
    "wait_gone",
]

TOKEN_VARIABLE = "RR_ACTORS_EXPERIMENT"  # noqa: S105 - a variable's name, not a secret
"""The environment variable that marks the processes of one run."""

PRELOAD_VARIABLE = "RR_ACTORS_PRELOAD"
"""The environment variable that names what a run's forkserver imports (`_preload.py`)."""


def processes_with(token: str, *, exclude: frozenset[int] = frozenset()) -> list[int]:
    """Pids of living processes whose environment has `RR_ACTORS_EXPERIMENT=<token>`.

    Args:
        token: the run's token.
        exclude: pids to leave out (the caller itself, say).
    """
    wanted = f"{TOKEN_VARIABLE}={token}".encode()
    found: list[int] = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) in exclude:
            continue
        try:
            environ = (entry / "environ").read_bytes()
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if state != "Z" and wanted in environ.split(b"\0"):
            found.append(int(entry.name))
    return sorted(found)


def cmdline(pid: int) -> str:
    """The command line of `pid` (arguments joined by spaces; `""` if gone)."""
    try:
        return (Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()).strip()
    except OSError:
        return ""


def parent(pid: int) -> int | None:
    """The parent pid of `pid` (`None` if gone)."""
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return None


def wait_gone(pids: list[int], timeout: float) -> list[int]:
    """Wait (through pidfds, no polling) until `pids` exited; return those still alive."""
    fds: dict[int, int] = {}
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            fds[os.pidfd_open(pid)] = pid
    deadline = time.monotonic() + timeout
    try:
        with selectors.DefaultSelector() as selector:  # (not select(): fds of 1024 and up)
            for fd in fds:
                selector.register(fd, selectors.EVENT_READ)
            while fds:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                for key, _ in selector.select(left):
                    selector.unregister(key.fd)
                    os.close(key.fd)
                    del fds[key.fd]
        return sorted(fds.values())
    finally:
        for fd in fds:
            os.close(fd)


def kill(pids: list[int]) -> None:
    """SIGKILL each of `pids` (through a pidfd; those already gone are skipped)."""
    for pid in pids:
        try:
            fd = os.pidfd_open(pid)
        except ProcessLookupError:
            continue
        try:
            with contextlib.suppress(ProcessLookupError):
                signal.pidfd_send_signal(fd, signal.SIGKILL)
        finally:
            os.close(fd)


def start_time(pid: int) -> int | None:
    """Creation time of `pid` in clock ticks (`/proc/<pid>/stat` field 22), `None` if gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()
    return None if fields[0] == "Z" else int(fields[19])


def children(pid: int) -> list[int]:
    """The pids of the children of `pid` (of every thread of it; `[]` if it is gone)."""
    pids: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        with contextlib.suppress(OSError, ValueError):
            pids.extend(int(p) for p in (task / "children").read_text().split())
    return pids


def resource_processes(sup: rr.Supervisor, managers: list[str]) -> list[tuple[str, int, int]]:
    """`(manager, pid, creation time)` of the child processes of the running process managers
    among `managers`, in manager order, then creation time and pid (a seeded pick is stable)."""
    found: list[tuple[int, int, int, str]] = []
    for order, name in enumerate(managers):
        info = sup.child(name)
        if info.pid is None or info.state != "running":
            continue
        for child in children(info.pid):
            created = start_time(child)
            if created is not None:
                found.append((order, created, child, name))
    found.sort()
    return [(name, pid, created) for _, created, pid, name in found]
