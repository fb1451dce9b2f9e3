"""One owner of a path at a time: an exclusive advisory lock on a lock file, naming its pid.

```
 owner A: claim(lock file) ──► open (0600, close-on-exec), flock(EX, NB), write A's pid
 owner B: claim(lock file) ──► flock fails ──► HeldError(the pid A wrote) ──► B's ConfigError
 A: release(fd) ──► the file removed (still locked), then closed: the lock goes
 A's process dies however it dies ──► the kernel drops the lock (the file stays: no lock)
 B: a file removed between its open and its lock ──► opened again (a new owner's file)
```

Used for a supervisor tree's state directory (`<state_dir>/.lock`) and for a registrar's
backup (`<backup_path>.lock`): two owners of one would each take the other's records
for their own. `flock` locks an open file description, so a second claim conflicts
within one process too (a POSIX `lockf` lock would not: it is the process's, and
closing any descriptor of the file drops it), and the lock goes with the process's
end, a SIGKILL included. A lock file left by a dead process is not a lock. A child
forked from the owner would share the lock (the same open file): it closes its copies
of the held descriptors at once (`fork.after_fork_in_child`), so the lock stays the
owner's alone and goes when the owner lets go, whatever the child does. Without `fcntl`
(not POSIX) nothing is locked: the claim always succeeds (documented).
"""

from __future__ import annotations

import contextlib
import os

from rr_actors._platform import fork

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no lock (documented)
    fcntl = None  # type: ignore[assignment]

__all__ = ["HeldError", "claim", "release"]

_held: dict[int, str] = {}  # the descriptors of the locks this process holds: their files


class HeldError(Exception):
    """The lock file is locked by another owner; `holder` is the pid it wrote there
    (`"unknown"` if it has not yet)."""

    def __init__(self, holder: str) -> None:
        super().__init__(holder)
        self.holder = holder


def claim(path: str | os.PathLike[str]) -> int:
    """Create `path` if needed (mode 0600), lock it for this owner and write this pid.

    Returns:
        The open descriptor: the lock is held until `release(fd)` (or the process ends).

    Raises:
        HeldError: another owner (in this process or another) holds it.
        OSError: the file cannot be created or opened.
    """
    name = os.fspath(path)
    while True:
        fd = os.open(name, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        with contextlib.suppress(OSError):  # (whatever the umask; another user's stays)
            os.fchmod(fd, 0o600)
        if fcntl is None:
            return fd
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = _holder(fd)
            os.close(fd)
            raise HeldError(holder) from None
        if _names(fd, name):
            break
        os.close(fd)  # its owner removed it as it let go (`release`): claim the new one
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    _held[fd] = name
    return fd


def release(fd: int) -> None:
    """Release the lock `claim` returned: the lock file is removed while still held (the
    next owner makes a new one), then closed, which releases the lock."""
    name = _held.pop(fd, None)
    if name is not None and _names(fd, name):  # (not another owner's, were ours deleted)
        with contextlib.suppress(OSError):
            os.unlink(name)
    with contextlib.suppress(OSError):
        os.close(fd)


def _names(fd: int, name: str) -> bool:
    """Whether `name` still names the file open at `fd`."""
    try:
        return os.path.samestat(os.fstat(fd), os.stat(name))
    except OSError:
        return False


def _let_go_in_child() -> None:
    """In a forked child: close the copies of the owner's lock descriptors (the lock
    stays the owner's)."""
    for fd in _held:
        with contextlib.suppress(OSError):
            os.close(fd)  # (never removed: the file is the owner's)
    _held.clear()


fork.after_fork_in_child("the lock files this process holds", _let_go_in_child)


def _holder(fd: int) -> str:
    """The pid the holder wrote in the lock file (`"unknown"` if it has not yet)."""
    with contextlib.suppress(OSError, ValueError):
        return str(int(os.pread(fd, 32, 0).decode().strip()))
    return "unknown"
