"""Linux (and glibc, and CPython-internal) tricks; `base.PortablePlatform` is the plain fallback.

Each trick says what it buys. CPython's private names (the forkserver singleton's fields,
`multiprocessing.spawn.get_preparation_data`) are used in this file and `forkserver` only,
each use degrading to the plain behaviour where the name is missing.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import hashlib
import logging
import multiprocessing
import multiprocessing.context
import os
import signal
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

from rr_actors._platform import forkserver as own_forkserver
from rr_actors._platform import linux_gate, linux_names
from rr_actors._platform.base import PARENT_GONE_EXIT, CpuSample, PortablePlatform

logger = logging.getLogger("rr_actors")

_PR_SET_PDEATHSIG = 1
_PR_SET_NAME = 15
_PIDFD_GETFD = 438  # (the syscall's number on every architecture but alpha)
_HELD: set[int] = set()  # every watch's inotify copies: a forked child closes its own
_LEAN_LOCK = threading.Lock()


@functools.cache
def _libc() -> Any:
    try:
        return ctypes.CDLL(None, use_errno=True)
    except OSError:
        return None


@functools.cache
def _malloc_trim() -> Callable[[int], object] | None:
    try:
        trim = _libc().malloc_trim
    except (AttributeError, TypeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    result: Callable[[int], object] = trim
    return result


def _install_lean_preparation(prefix: str) -> None:
    """Keep manager processes named `prefix*` from re-running the parent's `__main__` (idempotent).
    What it buys: a manager's (re)start skips re-importing the parent's main script as
    `__mp_main__`, which it never needs (its target is in rr_actors, its setup cloudpickled by
    value). Wraps CPython's `get_preparation_data` to drop the main-module entries."""
    from multiprocessing import spawn  # noqa: PLC0415

    with _LEAN_LOCK:
        original = spawn.get_preparation_data
        if getattr(original, "_rr_lean", False):
            return

        def get_preparation_data(name: str) -> dict[str, Any]:
            data: dict[str, Any] = original(name)
            if name.startswith(prefix):
                data.pop("init_main_from_path", None)
                data.pop("init_main_from_name", None)
            return data

        get_preparation_data._rr_lean = True  # type: ignore[attr-defined]
        spawn.get_preparation_data = get_preparation_data


def _let_go_of_the_forkserver() -> None:
    """Close this manager's copy of the pipe that keeps CPython's forkserver alive. What it buys:
    the forkserver exits when the supervisor's process dies, so the parent-death signal reaches a
    stuck manager (CPython hands every forked child a copy of the write end)."""
    from multiprocessing import forkserver  # noqa: PLC0415

    server = getattr(forkserver, "_forkserver", None)
    fd = getattr(server, "_forkserver_alive_fd", None)
    if server is None or not isinstance(fd, int):
        return  # spawn, or another CPython: nothing inherited here
    with contextlib.suppress(OSError):
        os.close(fd)
    server._forkserver_alive_fd = None


def _forget_the_forkserver() -> None:
    """In a forked child: CPython's forkserver singleton made new, where it has the fields."""
    from multiprocessing import forkserver  # noqa: PLC0415

    server = getattr(forkserver, "_forkserver", None)
    if server is not None and hasattr(server, "_forkserver_pid"):
        own_forkserver.forget_server(server)


class PidfdExitWatch:
    """A `pidfd` and `/proc/<pid>` of a manager process: its exit, before its parent's word. What it
    buys: a crash seen as soon as the process exited, even while the forkserver (its parent, which
    reaps it) is stopped or busy. Until it is reaped, `/proc/<pid>/stat` (field 52) holds its exit
    status, read through a descriptor opened while it ran (a recycled pid cannot be read instead).
    Linux 5.3 and later. It holds copies of a pool's inotify descriptor (`pidfd_getfd`, 5.6): its
    killed process's exit (pidfd readable, zombie) waits for the kernel to destroy the watches of
    the last copy (an SRCU grace period); `close` pays that, once seen (a process manager: none)."""

    __slots__ = ("held", "pidfd", "proc")

    def __init__(self, pidfd: int, proc: int) -> None:
        self.pidfd = pidfd
        self.proc = proc
        self.held: list[int] = []
        with contextlib.suppress(OSError, AttributeError):  # (no /proc, no libc, no syscall)
            fds = os.open("fd", os.O_RDONLY | os.O_DIRECTORY, dir_fd=proc)
            try:
                for fd in os.listdir(fds):
                    if os.readlink(fd, dir_fd=fds) == "anon_inode:inotify":
                        self.held.append(_libc().syscall(_PIDFD_GETFD, pidfd, int(fd), 0))
                        _HELD.add(self.held[-1])
            finally:
                os.close(fds)

    @classmethod
    def open(cls, pid: int) -> PidfdExitWatch | None:
        """Watch process `pid` (call it while the process runs); `None` if unsupported."""
        try:
            pidfd = os.pidfd_open(pid)
        except (AttributeError, OSError):
            return None
        try:
            proc = os.open(f"/proc/{pid}", os.O_RDONLY | os.O_DIRECTORY)
        except OSError:
            os.close(pidfd)
            return None
        return cls(pidfd, proc)

    def fileno(self) -> int:
        return self.pidfd

    def exitcode(self) -> int | None:
        """As `Process.exitcode`; `None` while it runs, and once reaped (the sentinel has it
        then)."""
        try:
            stat_fd = os.open("stat", os.O_RDONLY, dir_fd=self.proc)
            try:
                stat = os.read(stat_fd, 4096).decode("ascii", "replace")
            finally:
                os.close(stat_fd)
        except OSError:
            return None  # reaped: the task and its /proc entry are gone
        fields = stat[stat.rindex(")") + 2 :].split()  # from field 3, the state
        if fields[0] != "Z" or len(fields) < 50:
            return None
        return os.waitstatus_to_exitcode(int(fields[49]))

    def close(self) -> None:
        _HELD.difference_update(self.held)
        for fd in (self.pidfd, self.proc, *self.held):  # (-1: not held)
            with contextlib.suppress(OSError):
                os.close(fd)


def _close_held() -> None:
    for fd in _HELD:  # (the parent's watches' copies: kept, they would outlive its managers)
        with contextlib.suppress(OSError):
            os.close(fd)
    _HELD.clear()


own_forkserver.after_fork_in_child("the exit watches' inotify copies", _close_held)


class _Thread(NamedTuple):
    """One thread's figures at a sample of `ProcCpuWatch` (nanoseconds)."""

    ran: int  # time on a CPU
    delay: int  # run-queue delay of the waits that ended (it got a CPU after them)
    arrivals: int  # how many times it got a CPU
    state: str  # R (running or waiting for a CPU), D (waiting for the disk), S, ...
    pending: float  # seconds of the wait under way, as far as seen (not in `delay` yet)
    blocked: float  # seconds seen in D (a disk's flush, a page fault): what the kernel omits


class ProcCpuWatch:
    """A process's run-queue delay and stopped state, from `/proc/<pid>` (opened while it ran). What
    it buys: the heartbeat tells a manager starved of CPU (or of the disk) from a hung one. The
    kernel counts per thread its delay (`schedstat`) only when a wait ends: one under way is
    estimated (runnable at two samples without a CPU between); a wait for the disk (state D at
    two samples without a CPU between: an `fdatasync`, issue 69) counts as one. Read only while
    late."""

    __slots__ = ("at", "gone", "proc", "threads")

    def __init__(self, proc: int) -> None:
        self.proc = proc
        self.threads: dict[str, _Thread] = {}  # by tid, at the last sample
        self.gone = 0.0  # seconds waited by threads that have ended since
        self.at = 0.0  # monotonic time of the last sample

    @classmethod
    def open(cls, pid: int) -> ProcCpuWatch | None:
        """Watch process `pid` (call it while it runs); `None` without `/proc` or schedstat
        files."""
        try:
            proc = os.open(f"/proc/{pid}", os.O_RDONLY | os.O_DIRECTORY)
        except OSError:
            return None
        watch = cls(proc)
        try:
            _read_at(proc, "schedstat")
        except OSError:
            watch.close()
            return None
        return watch

    def sample(self) -> CpuSample | None:
        """The process's state and total run-queue delay now; `None` once it has exited."""
        try:
            stat = _read_at(self.proc, "stat")
            task = os.open("task", os.O_RDONLY | os.O_DIRECTORY, dir_fd=self.proc)
            try:
                tids = os.listdir(task)
            finally:
                os.close(task)
        except OSError:
            return None  # exited: the task and its /proc entry are gone
        now = time.monotonic()
        since = now - self.at if self.threads else 0.0
        threads: dict[str, _Thread] = {}
        for tid in tids:
            seen = self._thread(tid, self.threads.get(tid), since)
            if seen is not None:
                threads[tid] = seen
        for tid, before in self.threads.items():
            after = threads.get(tid)
            if after is None or after.arrivals < before.arrivals:  # ended (or tid reused)
                self.gone += before.delay / 1e9 + before.pending + before.blocked
        self.threads, self.at = threads, now
        waited = self.gone + sum(t.delay / 1e9 + t.pending + t.blocked for t in threads.values())
        return CpuSample(stopped=_state(stat) in ("T", "t"), waited=waited)

    def _thread(self, tid: str, before: _Thread | None, since: float) -> _Thread | None:
        try:
            ran, delay, arrivals = map(int, _read_at(self.proc, f"task/{tid}/schedstat").split())
            state = _state(_read_at(self.proc, f"task/{tid}/stat"))
        except (OSError, ValueError):
            return None
        pending, blocked = 0.0, 0.0 if before is None else before.blocked
        # no CPU since: the same wait (or run) goes on
        if before is not None and state == before.state and arrivals == before.arrivals:
            if state == "R":
                pending = before.pending + max(0.0, since - (ran - before.ran) / 1e9)
            elif state == "D":
                blocked += since
        return _Thread(ran, delay, arrivals, state, pending, blocked)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self.proc)


def _state(stat: str) -> str:
    return stat[stat.rindex(")") + 2 :][:1]


def _read_at(directory: int, path: str) -> str:
    fd = os.open(path, os.O_RDONLY, dir_fd=directory)
    try:
        return os.read(fd, 4096).decode("ascii", "replace")
    finally:
        os.close(fd)


class LinuxPlatform:
    """The tricks, for Linux with glibc and CPython 3.11-3.13."""

    name = "linux"

    def release_free_memory(self) -> None:
        """glibc's `malloc_trim(0)`: every free page back to the system, not only the heap's top."""
        trim = _malloc_trim()
        if trim is not None:
            trim(0)

    def manager_context(
        self, *, preload: Sequence[str] = (), lean_prefix: str | None = None
    ) -> multiprocessing.context.BaseContext:
        """A forkserver context with `preload` imported once in the server (rr_actors' own,
        `forkserver`; else CPython's; spawn where there is none). What it buys: a manager's
        (re)start does not pay those imports; processes named `lean_prefix*` also skip the parent's
        main module (`_install_lean_preparation`)."""
        if lean_prefix is not None:
            _install_lean_preparation(lean_prefix)
        if "forkserver" not in multiprocessing.get_all_start_methods():
            return multiprocessing.get_context("spawn")
        own: multiprocessing.context.BaseContext | None = own_forkserver.context(preload)
        if own is not None:
            return own
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(list(preload))
        return ctx

    def runtime_parent(self) -> str | None:
        """`$XDG_RUNTIME_DIR`, else `/dev/shm`, unless `TMPDIR` is set (`None`). What it buys: the
        files each served registrar creates are made on a tmpfs, not a disk."""
        if os.environ.get("TMPDIR"):
            return None
        shm = "/dev/shm"  # noqa: S108 - the parent of a fresh 0700 directory (mkdtemp)
        for parent in (os.environ.get("XDG_RUNTIME_DIR", ""), shm):
            if parent and os.path.isdir(parent) and os.access(parent, os.W_OK | os.X_OK):
                return parent
        return None

    def forker_pid(self, ctx: multiprocessing.context.BaseContext) -> int | None:
        """The forkserver's pid (started if it does not run; this process's with spawn; `None` where
        the private field is missing). What it buys: the child tells that the forkserver died before
        its `prctl`."""
        if ctx.get_start_method() != "forkserver":
            return os.getpid()
        own = own_forkserver.server_pid(ctx)
        if own is not None:
            return own
        from multiprocessing import forkserver  # noqa: PLC0415

        forkserver.ensure_running()  # cheap when it runs: one waitpid(WNOHANG)
        pid = getattr(getattr(forkserver, "_forkserver", None), "_forkserver_pid", None)
        return pid if isinstance(pid, int) else None

    def die_with_parent(self, expected_parent: int | None) -> None:
        """Have the kernel SIGKILL this process when its forker dies (`prctl(PR_SET_PDEATHSIG)`).
        What it buys: no orphan even of a manager too stuck to read its control pipe. If the forker
        (`expected_parent`) died before the `prctl`, it exits at once (`PARENT_GONE_EXIT`)."""
        _let_go_of_the_forkserver()
        libc = _libc()
        try:
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except AttributeError:  # no prctl: the control pipe EOF still works
            logger.debug("prctl(PR_SET_PDEATHSIG) unavailable")
            return
        if expected_parent is not None and os.getppid() != expected_parent:
            os._exit(PARENT_GONE_EXIT)  # it died before prctl: the signal will never come

    def watch_exit(self, pid: int) -> PidfdExitWatch | None:
        return PidfdExitWatch.open(pid)

    def watch_cpu(self, pid: int) -> ProcCpuWatch | None:
        return ProcCpuWatch.open(pid)

    def set_process_name(self, title: str) -> None:
        """`prctl(PR_SET_NAME)`, 15 bytes kept, ending at a whole UTF-8 character. What it buys:
        manager processes told apart in `ps -o comm` and `top` without `setproctitle`."""
        libc = _libc()
        with contextlib.suppress(AttributeError):
            kept = title.encode()[:15].decode(errors="ignore").encode()
            libc.prctl(_PR_SET_NAME, ctypes.c_char_p(kept), 0, 0, 0)

    def forget_in_child(self) -> None:
        """In a forked child: a forkserver of its own at the next manager; the lean lock made
        new."""
        global _LEAN_LOCK  # a thread of the parent may have held it at the fork
        _LEAN_LOCK = threading.Lock()
        _forget_the_forkserver()
        own_forkserver.forget_in_child()

    def at_main_thread_end(self, fn: Callable[[], None]) -> None:
        """CPython's private `threading._register_atexit` (as `concurrent.futures` uses it), else
        `atexit`. What it buys: `fn` runs before the interpreter waits for non-daemon threads.
        """
        hook = getattr(threading, "_register_atexit", None)
        if hook is None:
            PortablePlatform().at_main_thread_end(fn)
        else:
            hook(fn)

    def watch_names(self) -> linux_names.InotifyNameWatch | None:
        """inotify (`linux_names`): one `poll` a commit instead of two `stat` calls."""
        return linux_names.watch_names()

    def listener_gate(self, host: str, port: int) -> linux_gate.LinuxListenerGate | None:
        sock = linux_gate.find_listener(host, port)
        return None if sock is None else linux_gate.LinuxListenerGate(sock)

    def monotonic_clock(self) -> str | None:
        return _monotonic_clock()


@functools.cache
def _monotonic_clock() -> str | None:
    """The name of `CLOCK_MONOTONIC` here: the boot id and the time namespace; `None` if unreadable.
    What it buys: processes of one boot and namespace share the clock, so a deadline crosses between
    them exact."""
    try:
        with open("/proc/sys/kernel/random/boot_id", encoding="ascii") as boot:
            boot_id = boot.read().strip()
    except OSError:
        return None
    try:
        namespace = os.stat("/proc/self/ns/time").st_ino
    except OSError:  # (a kernel before 5.6: one clock for the whole boot)
        namespace = 0
    if not boot_id:
        return None
    return hashlib.blake2b(f"{boot_id}/{namespace}".encode(), digest_size=8).hexdigest()
