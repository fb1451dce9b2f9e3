"""One supervisor tree per state directory: an advisory lock on `<state_dir>/.lock`.

Two trees sharing a state directory would share their managers' backups: after a restart
each would hold the other's consumer ids. The first tree to start claims
`<state_dir>/.lock` (`_platform.lockfile`: an exclusive `flock`, its pid written there);
a second one (in this process or another) gets `ConfigError` naming that pid. The lock
goes at the tree's stop (the file removed), or when its process dies, however it dies (a
stale `.lock` file left by a dead process is not a lock). Each manager's backup is
claimed the same way on its own (`<backup_path>.lock`), whoever starts it. A simulation
takes no lock (`runtime.guards_files`: its files are its own): its processes are one OS
process, whose lock a killed simulated program would never let go.

The directory also remembers the registrars of the tree that keep no backup and may hold
ids at those that do: the consumers `registrar()` starts without one, and the managers
whose own config has none (`<state_dir>/.consumers/<name>`, an empty file each). Their
ids are in the other managers' backups, and such a registrar's next start (in a program
started again after a SIGKILL, say) holds none of them: the supervisor tells it that it
lost everything (`tree.lost_everything`), and reconciling releases them (rule 20). The
marks stay: a name started once is reconciled at each later start, as a registrar with
a backup reconciles at each of its starts.
"""

from __future__ import annotations

import os
from collections.abc import Iterable

from rr_actors._core import runtime
from rr_actors._platform import lockfile
from rr_actors.errors import ConfigError

__all__ = ["CONSUMERS", "LOCK_NAME", "StateDirLock", "ran_before"]

LOCK_NAME = ".lock"
"""The lock file's name in a state directory."""

CONSUMERS = ".consumers"
"""The folder of a state directory that marks the registrars without a backup started on it."""


class StateDirLock:
    """Exclusive locks on some state directories, held until `release`."""

    def __init__(self, fds: list[int]) -> None:
        self._fds = fds

    @classmethod
    def acquire(cls, directories: Iterable[str | os.PathLike[str]]) -> StateDirLock:
        """Create each directory if needed and lock it for this supervisor.

        Raises:
            ConfigError: a directory is locked by another supervisor (the message names
                the directory and the holder's pid), or cannot be created or locked.
        """
        fds: list[int] = []
        try:
            unique = sorted({os.path.abspath(os.fspath(d)) for d in directories})
            fds.extend(fd for fd in map(_lock, unique) if fd is not None)
        except BaseException:
            cls(fds).release()
            raise
        return cls(fds)

    def release(self) -> None:
        """Release every lock (idempotent)."""
        fds, self._fds = self._fds, []
        for fd in fds:
            lockfile.release(fd)


def _lock(directory: str) -> int | None:
    try:
        os.makedirs(directory, exist_ok=True)
        if not runtime.guards_files():  # (a simulation: see the module's docstring)
            return None
        return lockfile.claim(os.path.join(directory, LOCK_NAME))
    except lockfile.HeldError as held:
        ours = held.holder == str(os.getpid())  # (a tree this program did not stop)
        then = ", one of this process that is still running: stop it first, or" if ours else ";"
        raise ConfigError(
            f"state_dir {directory!r} is in use by another supervisor (pid {held.holder})"
            f"{then} give each supervisor tree its own state_dir"
        ) from None
    except OSError as exc:
        raise ConfigError(f"state_dir {directory!r} cannot be used: {exc}") from exc


def ran_before(directory: str | os.PathLike[str], name: str) -> bool:
    """Mark that registrar `name`, which keeps no backup, runs on state directory
    `directory`; return whether it was marked already (a registrar of that name ran
    there before: its ids may still be held in the managers' backups).

    Raises:
        ConfigError: the mark cannot be written (the message names the file).
    """
    folder = os.path.join(os.fspath(directory), CONSUMERS)
    mark = os.path.join(folder, name)
    try:
        os.makedirs(folder, exist_ok=True)
        with open(mark, "x"):
            pass
    except FileExistsError:
        return True
    except OSError as exc:
        raise ConfigError(
            f"state_dir {os.fspath(directory)!r}: cannot mark {mark!r}: {exc}"
        ) from exc
    return False
