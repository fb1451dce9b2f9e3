"""What a platform offers: each method is a job, done with a trick or plainly.

Every job here is either an optimisation (the portable platform may skip it) or a second
line of defence whose first line works everywhere (the portable platform relies on the
first line alone). Nothing rr_actors promises depends on a trick. `PortablePlatform` is
that plain fallback of every trick: correct everywhere, only slower.
"""

from __future__ import annotations

import atexit
import collections
import dataclasses
import multiprocessing
import multiprocessing.context
from collections.abc import Callable, Collection, Sequence
from typing import Protocol

from rr_actors._platform import fork

__all__ = [
    "GATE_SOURCES",
    "PARENT_GONE_EXIT",
    "CpuSample",
    "CpuWatch",
    "ExitWatch",
    "ListenerGate",
    "NameWatch",
    "Platform",
    "PortablePlatform",
]

GATE_SOURCES = 256
"""Source addresses a `ListenerGate` drops (or admits) at once at most (more is a
firewall's job; on Linux, one socket filter's instructions stay under `BPF_MAXINSNS`)."""


class ExitWatch(Protocol):
    """Something to wait on that becomes readable when one process has exited.

    Made by [`Platform.watch_exit`][rr_actors._platform.base.Platform.watch_exit] while
    the process runs; the parent's watcher thread waits on `fileno()` beside the process
    sentinel.
    """

    def fileno(self) -> int:
        """A descriptor that becomes readable once the process has exited."""
        ...

    def exitcode(self) -> int | None:
        """The exit code as `Process.exitcode` gives it (`-N`: killed by signal N).

        `None` while the process runs, or when it can no longer be read here (then the
        process sentinel tells it).
        """
        ...

    def close(self) -> None:
        """Release the descriptors."""
        ...


@dataclasses.dataclass(frozen=True, slots=True)
class CpuSample:
    """What the kernel says of one process's use of the CPUs, at one moment.

    Attributes:
        stopped: it is stopped (`SIGSTOP`, a terminal's job control, a debugger): it
            cannot run at all, however idle the CPUs.
        waited: seconds its threads have spent runnable but waiting for a CPU (the
            scheduler's run-queue delay), summed over its threads, since the watch began
            (a thread that ended keeps its share). It grows only while the machine is
            too busy to run the process when it could run.
    """

    stopped: bool
    waited: float


class CpuWatch(Protocol):
    """Reads how one process gets the CPUs it asks for (for the heartbeat's judgement).

    Made by [`Platform.watch_cpu`][rr_actors._platform.base.Platform.watch_cpu] while
    the process runs; used by its parent's watcher thread only.
    """

    def sample(self) -> CpuSample | None:
        """Read it now; `None` once the process has exited (or cannot be read)."""
        ...

    def close(self) -> None:
        """Release the descriptors."""
        ...


class ListenerGate(Protocol):
    """A gate on one TCP listening socket of this process (a library's, such as Zenoh's).

    Made by [`Platform.listener_gate`][rr_actors._platform.base.Platform.listener_gate];
    used by one thread (`_transport/zenoh/ops/gate.py`'s).
    """

    address: str
    """The address the socket is bound to."""

    port: int
    """Its port."""

    def shorten_backlog(self, backlog: int) -> None:
        """Let at most about `backlog` connections wait in the kernel for an accept."""

    def drop_from(self, sources: Collection[str]) -> None:
        """Drop every packet from `sources` (IP addresses) at the socket from now on,
        replacing the filter set before (empty: drop nothing)."""

    def admit_only(self, sources: Collection[str]) -> None:
        """Drop every packet from any address but `sources` (IP addresses) at the socket
        from now on, replacing the filter set before (empty: drop every packet)."""

    def peers(self) -> collections.Counter[str]:
        """How many connections to the socket's port past the TCP handshake each remote
        address holds (never the half-open ones: their source address may be forged)."""
        ...

    def close(self) -> None:
        """Let go of the socket (the library's socket stays open, its filter attached)."""


class NameWatch(Protocol):
    """Tells whether some files' names may have changed: moved, deleted, replaced
    (`Platform.watch_names`). Used by one thread at a time."""

    def arm(self, paths: Sequence[str]) -> bool:
        """Watch the absolute paths `paths` (existing files) instead of what was watched
        before; quiet until one may change. Returns whether every one is watched (if
        not, it is never quiet until an `arm` that succeeds)."""
        ...

    def quiet(self) -> bool:
        """Whether nothing happened to the names armed since `arm` (exact for a change
        made before the call; `False` also for a harmless change, a `chmod` say)."""
        ...

    def close(self) -> None:
        """Stop watching (idempotent)."""


class Platform(Protocol):
    """The platform-specific jobs rr_actors has; `PortablePlatform` does each without tricks."""

    name: str
    """`"linux"` or `"portable"`."""

    def release_free_memory(self) -> None:
        """Hand the C heap's free pages back to the system now (an optimisation)."""

    def manager_context(
        self, *, preload: Sequence[str] = (), lean_prefix: str | None = None
    ) -> multiprocessing.context.BaseContext:
        """The multiprocessing context manager processes are started with (in the parent).

        Never a plain `fork` of the threaded parent: `forkserver` where there is one,
        else `spawn`.

        Args:
            preload: modules a forkserver may import once for all its children.
            lean_prefix: processes whose name starts with it need not re-import the
                parent's main module (`None`: every process does).
        """
        ...

    def runtime_parent(self) -> str | None:
        """The directory a system's private runtime directory is made in (`None`: the
        temporary directory, `tempfile`'s choice). An optimisation: a memory-backed one
        makes the files each served registrar creates cheap."""
        ...

    def forker_pid(self, ctx: multiprocessing.context.BaseContext) -> int | None:
        """The pid of the process that forks manager processes (in the parent).

        Handed to the child for `die_with_parent`; `None` if it cannot be known.
        """
        ...

    def die_with_parent(self, expected_parent: int | None) -> None:
        """Make this manager process end when the process that forked it dies (in the child).

        A second line of defence: a manager first sees its supervisor's death as EOF on
        its control pipe and exits. This is for a manager too stuck to read its pipe.
        """

    def watch_exit(self, pid: int) -> ExitWatch | None:
        """Something that tells process `pid`'s exit early (in the parent), or `None`.

        An optimisation: the process sentinel always tells the exit too, once the
        process's parent has reaped it.
        """
        ...

    def watch_cpu(self, pid: int) -> CpuWatch | None:
        """Something that tells whether process `pid` waits for a CPU (in the parent), or
        `None` where the platform does not say.

        A refinement of the heartbeat's judgement (`rr_actors._process.heartbeat`):
        without it, a manager silent past its bound is hung whatever the reason.
        """
        ...

    def set_process_name(self, title: str) -> None:
        """Name this process for `ps` and `top` (in the child; only a convenience)."""

    def forget_in_child(self) -> None:
        """In a child forked from this process (`rr_actors._platform.fork`): let go of what
        only the parent can use, so that manager processes can be started from the child.

        The forkserver the parent started is not the child's child: the child must start
        its own (or spawn).
        """

    def at_main_thread_end(self, fn: Callable[[], None]) -> None:
        """Have `fn()` called on the main thread when it ends (in any process).

        It runs while every daemon thread still runs and before `multiprocessing`'s own
        exit handler terminates daemonic child processes. Raises `RuntimeError` when the
        interpreter is shutting down already.
        """

    def watch_names(self) -> NameWatch | None:
        """A watch that tells when some files' names may have changed (not armed yet), or
        `None` where the platform cannot tell (then the caller `stat`s them each time).

        An optimisation: a catalog backup's store checks before each commit that its
        path still names its file; the watch spares it the `stat` calls.
        """
        ...

    def listener_gate(self, host: str, port: int) -> ListenerGate | None:
        """A gate on this process's TCP listening socket bound to `host`:`port` (an IP
        address), or `None` where there is none (the socket is not found, or no platform
        support: then only a firewall keeps a flood of failed handshakes off)."""
        ...

    def monotonic_clock(self) -> str | None:
        """A name of the clock `time.monotonic()` reads in this process: two processes
        that give the same name read one clock, so a time of one is a time of the other
        (`None`: the platform does not say; no other process's time is trusted then).

        A refinement of the deadline a `Load` carries to another process: the time left
        (which does not count its time in a pipe), or, on one clock, the deadline itself.
        """
        ...


PARENT_GONE_EXIT = 70
"""The exit code of a manager process that found its parent gone."""


class PortablePlatform:
    """Every job done with the standard library's public API only.

    Orphans: a manager process whose supervisor's process died sees EOF on its control
    pipe and exits (the first line everywhere); there is no parent-death signal for one
    too stuck to read it. Crashes: the process sentinel tells them, once the process's
    parent (the forkserver) has reaped it.
    """

    name = "portable"

    def release_free_memory(self) -> None:
        """Nothing: freed memory stays with the C allocator (it is reused)."""

    def manager_context(
        self, *, preload: Sequence[str] = (), lean_prefix: str | None = None
    ) -> multiprocessing.context.BaseContext:
        """The forkserver context (spawn where there is none), with no preload.

        Spawn in a child forked from a process that ran rr_actors: the forkserver
        CPython keeps is its parent's, which it cannot use (`forget_in_child`).

        Each manager process imports what it needs after its fork, and re-imports the
        parent's main module as `__mp_main__` (multiprocessing's own behaviour), so
        `preload` and `lean_prefix` are ignored.
        """
        del preload, lean_prefix
        if fork.forked_from() is None and "forkserver" in multiprocessing.get_all_start_methods():
            ctx = multiprocessing.get_context("forkserver")
            ctx.set_forkserver_preload([])
            return ctx
        return multiprocessing.get_context("spawn")

    def runtime_parent(self) -> str | None:
        """`None`: the temporary directory (`TMPDIR`, `tempfile`'s choice)."""
        return None

    def forker_pid(self, ctx: multiprocessing.context.BaseContext) -> int | None:
        """`None`: the forkserver's pid is not public, and nothing here needs it."""
        del ctx
        return None

    def die_with_parent(self, expected_parent: int | None) -> None:
        """Nothing: the control pipe's EOF ends a manager whose supervisor died."""
        del expected_parent

    def watch_exit(self, pid: int) -> ExitWatch | None:
        """`None`: the process sentinel alone tells the exit."""
        del pid
        return None

    def watch_cpu(self, pid: int) -> CpuWatch | None:
        """`None`: no portable way to read a process's run-queue delay (so a manager silent
        past its heartbeat bound counts as hung, starved or not)."""
        del pid
        return None

    def set_process_name(self, title: str) -> None:
        """Nothing (install `setproctitle` to name manager processes everywhere)."""
        del title

    def forget_in_child(self) -> None:
        """Nothing: in a forked child, `manager_context` gives spawn (CPython's forkserver
        singleton is the parent's, and only its private attributes could reset it)."""

    def at_main_thread_end(self, fn: Callable[[], None]) -> None:
        """`atexit`: after the interpreter joined its non-daemon threads (ours are daemons,
        so they still run), and before `multiprocessing`'s handler, registered earlier."""
        atexit.register(fn)

    def watch_names(self) -> NameWatch | None:
        """`None`: a backup's store `stat`s its names before every commit."""
        return None

    def listener_gate(self, host: str, port: int) -> ListenerGate | None:
        """`None`: no gate (a firewall is the defence against a handshake flood)."""
        del host, port
        return None

    def monotonic_clock(self) -> str | None:
        """`None`: a deadline crosses to another process as the time left."""
        return None
