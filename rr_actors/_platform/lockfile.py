"""One owner of a path at a time: an exclusive advisory lock on a lock file, naming its pid;
and one owner of a file whatever its name (`claim_file`: a lock on the file itself).

```
 owner A: claim(lock file) ──► open (0600, close-on-exec), flock(EX, NB), write A's pid
 owner B: claim(lock file) ──► flock fails ──► HeldError(the pid A wrote) ──► B's ConfigError
 A: release(fd) ──► the file removed (still locked), then closed: the lock goes
 A's process dies however it dies ──► the kernel drops the lock (the file stays: no lock)
 B: a file removed between its open and its lock ──► opened again (a new owner's file)
 owner A: claim_file(db) ──► (dev, inode) not held here ──► open it read-only, flock(EX, NB)
 owner B: claim_file(a hard link to db) ──► the same inode: flock fails ──► HeldError(the
          pid /proc/locks names, or this pid if it is one of this process's own claims)
```

For a supervisor tree's state directory (`<state_dir>/.lock`) and a registrar's backup
(`<backup_path>.lock`, and the backup itself). A forked child closes its copies of the
held descriptors, so the lock stays the owner's. Without `fcntl` nothing is locked.
Why `flock`, and when a descriptor may be closed: docs/explanation/inside.md, "Lock files".
"""

from __future__ import annotations

import contextlib
import os
import sys

from rr_actors._platform import forkserver

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no lock (documented)
    fcntl = None  # type: ignore[assignment]

_held: dict[int, str] = {}  # the descriptors of the locks this process holds: their files
_held_files: dict[tuple[int, int], int] = {}  # claim_file's: (st_dev, st_ino) -> descriptor

FILE_LOCKS = fcntl is not None and sys.platform.startswith("linux")


class HeldError(Exception):
    """The lock file is locked by another owner; `holder` is the pid it wrote (`"unknown"`: not
    yet)."""

    def __init__(self, holder: str) -> None:
        super().__init__(holder)
        self.holder = holder


def claim(path: str | os.PathLike[str]) -> int:
    """Create `path` (0600), lock it and write this pid; the descriptor holds the lock until
    `release` or the process's end. `HeldError` if another owner holds it.
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
    """Release a `claim`: the lock file is removed while still held, then closed."""
    name = _held.pop(fd, None)
    if name is not None and _names(fd, name):  # (not another owner's, were ours deleted)
        with contextlib.suppress(OSError):
            os.unlink(name)
    with contextlib.suppress(OSError):
        os.close(fd)


def claim_file(path: str | os.PathLike[str]) -> int | None:
    """Lock the existing file at `path` itself (by any name), writing nothing; the read-only
    descriptor holds it until `release_file`. `None` where not taken (`FILE_LOCKS`: Linux);
    `HeldError` if another owner holds it.
    """
    if not FILE_LOCKS:
        return None
    st = os.stat(path)
    key = (st.st_dev, st.st_ino)
    if key in _held_files:  # (never opened here: closing it would drop SQLite's locks)
        raise HeldError(str(os.getpid()))
    fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    try:
        st = os.fstat(fd)
        key = (st.st_dev, st.st_ino)
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)  # (another process holds it: this one has no connection writing it)
        raise HeldError(_flock_holder(key)) from None
    _held_files[key] = fd
    return fd


def release_file(fd: int) -> None:
    """Release a `claim_file` (close its descriptor; the file stays), only once this process's
    connections to the file are closed: the close drops its POSIX locks on it.
    """
    for key, held in list(_held_files.items()):
        if held == fd:
            del _held_files[key]
    with contextlib.suppress(OSError):
        os.close(fd)


def _flock_holder(key: tuple[int, int]) -> str:
    """The pid holding a `flock` on the file `(st_dev, st_ino)`, from `/proc/locks`; else
    `"unknown"`."""
    dev, ino = key
    where = f"{os.major(dev):02x}:{os.minor(dev):02x}:{ino}"
    with contextlib.suppress(OSError), open("/proc/locks", encoding="ascii") as table:
        for line in table:
            fields = line.split()  # "1: FLOCK ADVISORY WRITE <pid> <maj>:<min>:<ino> 0 EOF"
            if len(fields) >= 6 and fields[1] == "FLOCK" and fields[5] == where:
                return fields[4]
    return "unknown"


def _names(fd: int, name: str) -> bool:
    try:
        return os.path.samestat(os.fstat(fd), os.stat(name))
    except OSError:
        return False


def _let_go_in_child() -> None:
    for fd in [*_held, *_held_files.values()]:
        with contextlib.suppress(OSError):
            os.close(fd)  # (not removed: the owner's; a child holds no POSIX lock to drop)
    _held.clear()
    _held_files.clear()


forkserver.after_fork_in_child("the lock files this process holds", _let_go_in_child)


def _holder(fd: int) -> str:
    with contextlib.suppress(OSError, ValueError):
        return str(int(os.pread(fd, 32, 0).decode().strip()))
    return "unknown"
