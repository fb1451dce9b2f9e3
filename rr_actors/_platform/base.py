"""What a platform offers: each method is a job, done with a trick or plainly.

Every job is an optimisation or a second line of defence whose first line works
everywhere: nothing rr_actors promises depends on a trick. `PortablePlatform` does each
plainly: correct everywhere, only slower.
"""

from __future__ import annotations

import atexit
import collections
import contextlib
import dataclasses
import multiprocessing
import multiprocessing.context
import os
import resource
from collections.abc import Callable, Collection, Sequence
from typing import Protocol

from rr_actors._platform import forkserver
from rr_actors.errors import RegistrarUnavailableError

GATE_SOURCES = 256
"""Source addresses a `ListenerGate` drops (or admits) at most (more is a firewall's job)."""


class ExitWatch(Protocol):
    """A descriptor that becomes readable when one process has exited (the parent waits on it
    beside the sentinel)."""

    def fileno(self) -> int: ...

    def exitcode(self) -> int | None:
        """As `Process.exitcode` (`-N`: killed by signal N); `None` while it runs or if
        unreadable."""
        ...

    def close(self) -> None: ...


@dataclasses.dataclass(frozen=True, slots=True)
class CpuSample:
    """One process's use of the CPUs: `stopped` (it cannot run at all), and `waited`, seconds its
    threads spent waiting for a CPU (or, on Linux, for the disk: state D) since the watch began.
    """

    stopped: bool
    waited: float


class CpuWatch(Protocol):
    """Reads how one process gets the CPUs it asks for (its parent's heartbeat watcher only)."""

    def sample(self) -> CpuSample | None:
        """Read it now; `None` once the process has exited (or cannot be read)."""
        ...

    def close(self) -> None: ...


class ListenerGate(Protocol):
    """A gate on one TCP listening socket of this process (Zenoh's), used by one thread."""

    address: str
    port: int

    def shorten_backlog(self, backlog: int) -> None: ...

    def drop_from(self, sources: Collection[str]) -> None:
        """Drop every packet from `sources` (IP addresses) from now on, replacing the filter
        before."""

    def admit_only(self, sources: Collection[str]) -> None:
        """Drop every packet from any address but `sources` from now on (empty: drop all)."""

    def peers(self) -> collections.Counter[str]:
        """Connections past the TCP handshake to the socket's port, per remote address."""
        ...

    def close(self) -> None:
        """Let go of the socket (the library's socket stays open, its filter attached)."""


class NameWatch(Protocol):
    """Tells whether some files' names may have changed: moved, deleted, replaced (one thread at
    a time)."""

    armable: bool
    """`False` while it cannot watch (`arm`, `quiet`: `False`): stat without asking it."""

    def arm(self, paths: Sequence[str]) -> bool:
        """Watch the absolute paths `paths` instead; whether every one is watched (if not, it is
        never quiet until an `arm` that succeeds).
        """
        ...

    def quiet(self) -> bool:
        """Whether nothing happened to the names since `arm` (`False` also for a harmless
        change)."""
        ...

    def close(self) -> None: ...


class Platform(Protocol):
    """The platform-specific jobs rr_actors has; `PortablePlatform` does each without tricks."""

    name: str

    def release_free_memory(self) -> None:
        """Hand the C heap's free pages back to the system now."""

    def manager_context(
        self, *, preload: Sequence[str] = (), lean_prefix: str | None = None
    ) -> multiprocessing.context.BaseContext:
        """The context manager processes start with: never a plain `fork` of the threaded parent.
        `preload`: what a forkserver imports once; `lean_prefix`: processes that skip `__main__`.
        """
        ...

    def runtime_parent(self) -> str | None:
        """The directory a system's runtime directory is made in (`None`: `tempfile`'s choice)."""
        ...

    def forker_pid(self, ctx: multiprocessing.context.BaseContext) -> int | None:
        """The pid of the process that forks manager processes (for `die_with_parent`), if known."""
        ...

    def die_with_parent(self, expected_parent: int | None) -> None:
        """In a manager process: end when the process that forked it dies (a second line: its
        control pipe's EOF is the first).
        """

    def watch_exit(self, pid: int) -> ExitWatch | None:
        """What tells process `pid`'s exit before its sentinel does (in the parent), or `None`."""
        ...

    def watch_cpu(self, pid: int) -> CpuWatch | None:
        """What tells whether process `pid` waits for a CPU (in the parent), or `None`: without it a
        manager silent past its bound is hung whatever the reason.
        """
        ...

    def set_process_name(self, title: str) -> None:
        """Name this process for `ps` and `top` (a convenience)."""

    def forget_in_child(self) -> None:
        """In a forked child: let go of the parent's forkserver, so the child can start managers."""

    def at_main_thread_end(self, fn: Callable[[], None]) -> None:
        """Have `fn()` called on the main thread when it ends, while daemon threads still run and
        before `multiprocessing` terminates daemonic children. `RuntimeError` at shutdown.
        """

    def watch_names(self) -> NameWatch | None:
        """A watch of files' names (not armed yet), or `None`: then the caller `stat`s them each
        time."""
        ...

    def listener_gate(self, host: str, port: int) -> ListenerGate | None:
        """A gate on this process's TCP listening socket at `host`:`port`, or `None` (then only a
        firewall keeps a handshake flood off).
        """
        ...

    def monotonic_clock(self) -> str | None:
        """A name of the clock `time.monotonic()` reads here: two processes that give the same name
        share it, so a `Load`'s deadline may cross as it is (`None`: as the time left).
        """
        ...


PARENT_GONE_EXIT = 70
"""The exit code of a manager process that found its parent gone."""


class PortablePlatform:
    """Every job done with the standard library's public API only.

    A manager whose supervisor died sees EOF on its control pipe and exits; the process
    sentinel tells crashes once the forkserver reaped the process.
    """

    name = "portable"

    def release_free_memory(self) -> None:
        """Nothing: freed memory stays with the C allocator (it is reused)."""

    def manager_context(
        self, *, preload: Sequence[str] = (), lean_prefix: str | None = None
    ) -> multiprocessing.context.BaseContext:
        """The forkserver context with no preload (spawn where there is none, or in a forked child,
        whose CPython forkserver is its parent's).
        """
        del preload, lean_prefix
        if (
            forkserver.forked_from() is None
            and "forkserver" in multiprocessing.get_all_start_methods()
        ):
            ctx = multiprocessing.get_context("forkserver")
            ctx.set_forkserver_preload([])
            return ctx
        return multiprocessing.get_context("spawn")

    def runtime_parent(self) -> str | None:
        return None

    def forker_pid(self, ctx: multiprocessing.context.BaseContext) -> int | None:
        del ctx
        return None

    def die_with_parent(self, expected_parent: int | None) -> None:
        del expected_parent

    def watch_exit(self, pid: int) -> ExitWatch | None:
        del pid
        return None

    def watch_cpu(self, pid: int) -> CpuWatch | None:
        del pid
        return None

    def set_process_name(self, title: str) -> None:
        """Nothing (install `setproctitle` to name manager processes everywhere)."""
        del title

    def forget_in_child(self) -> None:
        """Nothing: in a forked child, `manager_context` gives spawn."""

    def at_main_thread_end(self, fn: Callable[[], None]) -> None:
        """`atexit`: after the interpreter joined non-daemon threads, before `multiprocessing`'s
        handler, registered earlier.
        """
        atexit.register(fn)

    def watch_names(self) -> NameWatch | None:
        return None

    def listener_gate(self, host: str, port: int) -> ListenerGate | None:
        del host, port
        return None

    def monotonic_clock(self) -> str | None:
        return None


# -- the machine's bounds, named (issue 69) ------------------------------------------------------


def _read(path: str) -> str:
    try:
        with open(path, encoding="ascii") as file:
            return file.read().strip()
    except OSError:
        return "?"


def bound_reached(error: BaseException | None) -> str | None:
    """The machine's bound a failed start or connect ran into, named with its value (`None`:
    none). A manager that died while starting says nothing: then this process's open files and
    the system's threads are compared with their bounds (at 90%)."""
    nofile, nproc = (
        resource.getrlimit(r)[0] for r in (resource.RLIMIT_NOFILE, resource.RLIMIT_NPROC)
    )
    kernel = "/proc/sys/kernel/"
    files = f"open files per process (RLIMIT_NOFILE {nofile}: `ulimit -n`)"
    threads = (
        f"threads and processes (RLIMIT_NPROC {nproc}: `ulimit -u`; kernel.threads-max "
        f"{_read(kernel + 'threads-max')}; kernel.pid_max {_read(kernel + 'pid_max')})"
    )
    for _ in range(8):  # (the error, what it was raised from; a relayed traceback's text)
        text = f"{type(error).__name__}: {error}"
        if "Too many open files" in text:
            return files
        if "can't start new thread" in text or "Resource temporarily unavailable" in text:
            return threads
        if "MemoryError" in text or "Cannot allocate memory" in text:
            return "memory"
        error = None if error is None else error.__cause__ or error.__context__
    with contextlib.suppress(OSError, ValueError, IndexError):  # (no /proc: not known)
        if nofile != resource.RLIM_INFINITY and len(os.listdir("/proc/self/fd")) > 0.9 * nofile:
            return files
        most = min(int(_read(kernel + "threads-max")), int(_read(kernel + "pid_max")))
        if int(_read("/proc/loadavg").split()[3].split("/")[1]) > 0.9 * most:
            return threads
    return None


def no_thread(target: str, exc: RuntimeError, what: str) -> RegistrarUnavailableError:
    """The error of a call to registrar `target` that got no thread for `what` (its
    connection, its client actor): the machine's bound, named with its value."""
    error = RegistrarUnavailableError(
        f"registrar {target!r} cannot be reached: this machine's limit of "
        f"{bound_reached(exc) or f'threads ({exc})'} was reached (no thread for {what})"
    )
    error.__cause__ = exc
    return error
