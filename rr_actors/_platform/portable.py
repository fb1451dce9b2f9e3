"""The plain fallback of every platform trick: correct everywhere, only slower.

Orphans: a manager process whose supervisor's process died sees EOF on its control pipe
and exits (the first line everywhere); there is no parent-death signal for one too stuck
to read it. Crashes: the process sentinel tells them, once the process's parent (the
forkserver) has reaped it.
"""

from __future__ import annotations

import atexit
import multiprocessing
import multiprocessing.context
from collections.abc import Callable, Sequence

from rr_actors._platform import fork
from rr_actors._platform.base import CpuWatch, ExitWatch, ListenerGate, NameWatch

__all__ = ["PARENT_GONE_EXIT", "PortablePlatform"]

PARENT_GONE_EXIT = 70
"""The exit code of a manager process that found its parent gone."""


class PortablePlatform:
    """Every job done with the standard library's public API only."""

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
