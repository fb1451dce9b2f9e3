"""One supervisor tree per state directory: an advisory lock on `<state_dir>/.lock`.

Two trees sharing a state directory would share their managers' backups: after a restart
each would hold the other's consumer ids. The first tree to start takes an exclusive
`flock` on `<state_dir>/.lock` and writes its pid there; a second one (in this process or
another) gets `ConfigError` naming that pid. The kernel releases the lock when its file
is closed: at the tree's stop, or when its process dies, however it dies. A stale `.lock`
file left by a dead process is not a lock.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterable

from rr_actors.errors import ConfigError

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no lock (documented)
    fcntl = None  # type: ignore[assignment]

__all__ = ["LOCK_NAME", "StateDirLock"]

LOCK_NAME = ".lock"
"""The lock file's name in a state directory."""


class StateDirLock:
    """Exclusive locks on some state directories, held until `release`."""

    def __init__(self, fds: list[int]) -> None:
        self._fds = fds

    @classmethod
    def acquire(cls, directories: Iterable[str | os.PathLike[str]]) -> StateDirLock:
        """Create each directory if needed and lock it for this process.

        Raises:
            ConfigError: a directory is locked by another supervisor (the message names
                the directory and the holder's pid), or cannot be created or locked.
        """
        fds: list[int] = []
        try:
            unique = sorted({os.path.abspath(os.fspath(d)) for d in directories})
            fds.extend(_lock(directory) for directory in unique)
        except BaseException:
            cls(fds).release()
            raise
        return cls(fds)

    def release(self) -> None:
        """Release every lock (idempotent); the files stay."""
        fds, self._fds = self._fds, []
        for fd in fds:
            with contextlib.suppress(OSError):
                os.close(fd)  # closing the file releases its flock


def _lock(directory: str) -> int:
    path = os.path.join(directory, LOCK_NAME)
    try:
        os.makedirs(directory, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)  # not inherited (O_CLOEXEC)
    except OSError as exc:
        raise ConfigError(f"state_dir {directory!r} cannot be used: {exc}") from exc
    if fcntl is None:
        return fd
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = _holder(fd)
        os.close(fd)
        raise ConfigError(
            f"state_dir {directory!r} is in use by another supervisor (pid {holder}); "
            "give each supervisor tree its own state_dir"
        ) from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


def _holder(fd: int) -> str:
    """The pid the holder wrote in the lock file (`"unknown"` if it has not yet)."""
    with contextlib.suppress(OSError, ValueError):
        return str(int(os.pread(fd, 32, 0).decode().strip()))
    return "unknown"
