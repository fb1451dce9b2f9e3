"""Manager processes: the child's `main` and the parent's handle on one manager process.

A process manager is started with the `forkserver` context (`spawn` where there is no
forkserver), never with a plain `fork` of the threaded parent. In the child, `main`:

1. asks the kernel to kill it when the process that forked it dies (see `_die_with_parent`:
   with the forkserver context that is the forkserver, not the supervisor's process),
2. attaches to the system and starts the registrar, which restores its catalog,
3. runs the (cloudpickled) `setup(registrar)`, then serves the registrar on the system,
4. reports `ready` over its control pipe and answers control requests: `stop` and `ping`
   (the heartbeat, answered through the registrar actor's mailbox),
5. exits at once when the control pipe reaches EOF: the supervisor's process is gone,
6. exits with code 0 when its registrar was stopped cleanly by code in the manager (a
   `transient` manager is then not restarted, as in a thread), with code 71 when the
   registrar actor died.

Running a function against the registrar (`Supervisor.run_in`) goes over the system's
transport (`AttachedSystem.run`), not over the control pipe.

In the parent, [`ManagerProcess`][rr_actors._process.manager.ManagerProcess] owns the process and
its control pipe; one watcher thread per process blocks on the process sentinel, a
`pidfd` of the process (it tells the exit before the forkserver has reaped the child:
`_ExitWatch`) and the pipe (no polling), and sends the heartbeat pings.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import cloudpickle
import pykka

from rr_actors._core.directory import DIRECTORY
from rr_actors.config import RegistrarConfig
from rr_actors.errors import (
    CallTimeoutError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
)

__all__ = [
    "ManagerExit",
    "ManagerProcess",
    "Spare",
    "main",
    "mp_context",
    "standby",
    "stopped_cleanly",
]

logger = logging.getLogger("rr_actors")

_PR_SET_PDEATHSIG = 1
_PARENT_GONE_EXIT = 70  # the exit code of a manager whose parent died
_ACTOR_DIED_EXIT = 71  # the registrar actor died inside a living process


_PROCESS_PREFIX = "rr-manager-"  # the name of every manager process starts with it
_LEAN_LOCK = threading.Lock()


def _install_lean_preparation() -> None:
    """Keep manager processes from re-running the parent's `__main__` module (idempotent).

    A forkserver or spawn child first "prepares": it re-imports the parent's main script
    as `__mp_main__` so that objects pickled by reference to `__main__` resolve. A manager
    never needs that (its target lives in `rr_actors._process.manager`, its setup is cloudpickled by
    value, its config is plain data), and it costs every start (and every restart) the
    import time of whatever the main script imports: 10-40 ms for a script that imports
    `argparse` and `statistics`. (The forkserver's own `__main__` preload, meant to make
    this cheap, never runs on Python <= 3.13: it looks for a `main_path` key that
    `get_preparation_data` does not produce.) This wraps
    `multiprocessing.spawn.get_preparation_data` to drop the main-module entries for
    processes named `rr-manager-*` only; other processes are unaffected.
    """
    from multiprocessing import spawn  # noqa: PLC0415

    with _LEAN_LOCK:
        original = spawn.get_preparation_data
        if getattr(original, "_rr_lean", False):
            return

        def get_preparation_data(name: str) -> dict[str, Any]:
            data: dict[str, Any] = original(name)
            if name.startswith(_PROCESS_PREFIX):
                data.pop("init_main_from_path", None)
                data.pop("init_main_from_name", None)
            return data

        get_preparation_data._rr_lean = True  # type: ignore[attr-defined]
        spawn.get_preparation_data = get_preparation_data


def mp_context() -> multiprocessing.context.BaseContext:
    """The multiprocessing context for manager processes: forkserver, else spawn."""
    _install_lean_preparation()
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(
            [
                "rr_actors._process.manager",
                "rr_actors._registrar",
                "rr_actors._transport",
                "rr_actors._store.sqlite",
                "hmac",  # the transport's authkey handshake imports it lazily
            ]
        )
        return ctx
    return multiprocessing.get_context("spawn")


def start_forkserver() -> None:
    """Start the forkserver now (if manager processes use one), not at the first manager.

    The forkserver (and multiprocessing's resource tracker) are long-lived helper children
    of this process; tests that count child processes start them before counting.
    """
    if mp_context().get_start_method() == "forkserver":
        from multiprocessing import forkserver  # noqa: PLC0415

        forkserver.ensure_running()


def _forker_pid(ctx: multiprocessing.context.BaseContext) -> int | None:
    """The pid of the process that forks manager processes: the forkserver, or this one.

    Handed to the child so that it can tell whether that process died before the child
    asked to be killed with it (see `_die_with_parent`). `None` if it cannot be known.
    """
    if ctx.get_start_method() != "forkserver":
        return os.getpid()
    from multiprocessing import forkserver  # noqa: PLC0415

    forkserver.ensure_running()  # cheap when it runs: one waitpid(WNOHANG)
    # CPython keeps the pid in a private attribute (3.8 to 3.13); without it, no check.
    pid = getattr(getattr(forkserver, "_forkserver", None), "_forkserver_pid", None)
    return pid if isinstance(pid, int) else None


def _die_with_parent(expected_parent: int | None) -> None:
    """Linux: have the kernel SIGKILL this process when the process that forked it dies.

    That process is the forkserver with the forkserver context (the supervisor's process
    with spawn). The forkserver exits when the supervisor's process dies, so the signal
    also ends a manager whose supervisor died, but only as a second line: a manager sees
    its supervisor's death first as EOF on its control pipe (`_serve_control` exits at
    once). The signal is for a manager that is not reading its pipe (stuck, or stopped).

    `prctl` only covers deaths after it ran: if the forking process died between the fork
    and this call (the child was then re-parented, so `getppid()` changed), the process
    exits here at once with code 70.

    Args:
        expected_parent: the pid of the process that forked this one (`None`: unknown,
            no check).
    """
    if not sys.platform.startswith("linux"):
        return
    _let_go_of_the_forkserver()
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):  # no prctl: the control pipe EOF still works
        logger.debug("prctl(PR_SET_PDEATHSIG) unavailable")
        return
    if expected_parent is not None and os.getppid() != expected_parent:
        os._exit(_PARENT_GONE_EXIT)  # it died before prctl: the signal will never come


def _let_go_of_the_forkserver() -> None:
    """Close this process's copy of the pipe that keeps the forkserver alive.

    The forkserver exits when the process that started it dies: it sees EOF on a pipe
    whose write end only that process holds. But CPython hands a copy of that write end
    to every child the forkserver forks (`forkserver._forkserver._forkserver_alive_fd`),
    so while one manager lived the forkserver outlived the supervisor's process, and the
    parent-death signal never came. A forkserver child never uses its copy: one that
    starts processes with the forkserver context starts a forkserver of its own.
    """
    from multiprocessing import forkserver  # noqa: PLC0415

    server = getattr(forkserver, "_forkserver", None)
    fd = getattr(server, "_forkserver_alive_fd", None)
    if server is None or not isinstance(fd, int):
        return  # spawn, or another CPython: nothing inherited here
    with contextlib.suppress(OSError):
        os.close(fd)
    server._forkserver_alive_fd = None


def stopped_cleanly(name: str) -> bool:
    """Whether registrar `name` of this process, no longer running, was stopped by code.

    `False` if its actor died (a crash). The same test for both placements, so a
    `transient` manager whose registrar was stopped cleanly is not restarted in a
    thread or in a process alike.
    """
    return isinstance(DIRECTORY.gone_error(name), RegistrarStoppedError)


# -- the child ---------------------------------------------------------------------------


class _Control:
    """The child's end of the control pipe; `send` may be called from any thread."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self.lock = threading.Lock()

    def send(self, message: tuple[Any, ...]) -> None:
        # OSError: the parent is gone; the control loop sees EOF and exits
        with self.lock, contextlib.suppress(OSError):
            self.conn.send(message)


class _Pong:
    """A reply that answers a heartbeat ping once the registrar actor got to it."""

    def __init__(self, control: _Control, number: int) -> None:
        self.control = control
        self.number = number

    def set_result(self, _: Any) -> None:
        self.control.send(("pong", self.number))

    def set_error(self, _: BaseException) -> None:
        pass  # no pong: the parent counts it as missed


def _exit(code: int, attached: Any) -> None:
    """Leave the system (peers then see "stopped" or "died" at once), flush, exit."""
    if attached is not None:
        with contextlib.suppress(Exception):
            attached.close()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def main(
    setup: bytes,
    config: RegistrarConfig,
    address: Any,
    conn: Connection,
    parent: int | None = None,
) -> None:
    """Run one manager: restore, set up, serve, then answer control requests until stopped.

    Runs as the target of a manager process (never in the supervisor's process).

    Args:
        setup: `cloudpickle.dumps(setup_function_or_None)`.
        config: the registrar's configuration (its backup is restored before `setup`).
        address: the system's `SystemAddress`, or `None` to run unattached.
        conn: the child's end of the control pipe.
        parent: the pid of the process that forked this one (see `_die_with_parent`).
    """
    _die_with_parent(parent)
    _run_manager(setup, config, address, conn)


def _run_manager(setup: bytes, config: RegistrarConfig, address: Any, conn: Connection) -> None:
    from rr_actors._registrar import ResourceRegistrar, Served  # noqa: PLC0415 - preloaded

    control = _Control(conn)
    attached: Any = None
    try:
        if address is not None:
            attached = address.attach()
        registrar = ResourceRegistrar.start(config)
        setup_fn = cloudpickle.loads(setup)
        if setup_fn is not None:
            setup_fn(registrar)
        if attached is not None:
            attached.serve(Served(registrar))
    except BaseException as exc:  # noqa: BLE001 - reported to the supervisor, then exit
        control.send(("failed", "".join(traceback.format_exception(exc))))
        os._exit(1)
    stopping = threading.Event()

    def watch_actor() -> None:
        registrar._ref.actor_stopped.wait()
        if stopping.is_set():
            return  # the supervisor's `stop`: the control loop exits
        if stopped_cleanly(registrar.name):  # code in the manager called registrar.stop()
            _exit(0, attached)
        _exit(_ACTOR_DIED_EXIT, attached)

    threading.Thread(target=watch_actor, name="rr-manager-actor-watch", daemon=True).start()
    control.send(("ready", os.getpid()))
    _serve_control(conn, control, registrar, attached, stopping)


def _warm_up() -> None:
    """Pay a fresh process's first-use costs while it idles as a spare, not after a crash.

    A forked child shares its parent's memory copy-on-write: the first write to a page
    (Python writes reference counts and GC headers everywhere) copies it, which made the
    first registrar start in a new process about twice as slow as in a warm one. A full
    collection touches every tracked object (and so most of the heap) once; opening an
    in-memory SQLite database initialises the library.
    """
    import gc  # noqa: PLC0415
    import sqlite3  # noqa: PLC0415

    gc.collect()
    with contextlib.closing(sqlite3.connect(":memory:")) as db:
        db.execute("CREATE TABLE t (x)").fetchall()


def standby(conn: Connection, parent: int | None = None) -> None:
    """Wait, started but idle, until the parent hands over a manager's arguments; run it.

    Runs as the target of a spare manager process (see [`Spare`][rr_actors._process.manager.Spare]):
    the interpreter start, the forkserver's fork and the child's bootstrap are paid before
    a manager crashes, not after. Exits when the control pipe reaches EOF.

    Args:
        conn: the child's end of the control pipe; the first message is
            `("start", setup, config, address)` with `main`'s arguments.
        parent: the pid of the process that forked this one (see `_die_with_parent`).
    """
    _die_with_parent(parent)
    _warm_up()
    try:
        message = conn.recv()
    except (EOFError, OSError):
        os._exit(0)  # released unused, or the parent is gone
    if message[0] != "start":
        os._exit(0)
    _, setup, config, address = message
    _run_manager(setup, config, address, conn)


def _serve_control(
    conn: Connection, control: _Control, registrar: Any, attached: Any, stopping: threading.Event
) -> None:
    """The child's control loop: answer pings, stop; exit on EOF."""
    from rr_actors._registrar.messages import Request  # noqa: PLC0415 - preloaded

    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            os._exit(_PARENT_GONE_EXIT)  # the supervisor's process is gone: no orphans
        kind = message[0]
        if kind == "ping":
            pong = _Pong(control, message[1])
            with contextlib.suppress(pykka.ActorDeadError):
                registrar._ref.tell(Request(lambda _actor, reply: reply.set_result(None), pong))
        elif kind == "stop":
            stopping.set()
            code = 0
            try:
                registrar.stop(timeout=message[1])
            except RrError:
                logger.exception("manager %s did not stop cleanly", registrar.name)
                code = 1
            _exit(code, attached)


# -- the parent --------------------------------------------------------------------------


class ManagerExit:
    """Why a child (a manager process or thread, a nested supervisor) ended.

    Attributes:
        reason: what happened, for people (`ChildInfo.last_exit`).
        normal: whether it counts as a normal exit (a `transient` child is then not
            restarted).
    """

    __slots__ = ("normal", "reason")

    def __init__(self, reason: str, *, normal: bool) -> None:
        self.reason = reason
        self.normal = normal

    def __repr__(self) -> str:
        return f"ManagerExit({self.reason!r}, normal={self.normal})"


def _describe(exitcode: int | None) -> ManagerExit:
    if exitcode == 0:
        return ManagerExit("normal", normal=True)
    if exitcode is None:
        return ManagerExit("unknown exit", normal=False)
    if exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        return ManagerExit(f"killed by {name}", normal=False)
    if exitcode == _ACTOR_DIED_EXIT:
        return ManagerExit("registrar actor died", normal=False)
    return ManagerExit(f"exit code {exitcode}", normal=False)


class Spare:
    """A manager process started ahead of need, idle until it is given a manager to run.

    The supervisor keeps one so that a restart does not wait for a process to start:
    it only sends the manager's arguments, and the spare restores, sets up and serves.
    A spare that is never used exits when [`close`][rr_actors._process.manager.Spare.close]d (or
    when its parent dies, like any manager process).
    """

    def __init__(self, process: Any, conn: Connection) -> None:
        self.process = process
        self.conn = conn

    @classmethod
    def start(cls) -> Spare:
        """Start a spare process (returns once it was forked; it idles on its pipe)."""
        ctx = mp_context()
        parent_conn, child_conn = ctx.Pipe(duplex=True)
        process = ctx.Process(  # type: ignore[attr-defined]
            target=standby,
            args=(child_conn, _forker_pid(ctx)),
            name=f"{_PROCESS_PREFIX}spare",
            daemon=True,
        )
        process.start()
        child_conn.close()
        return cls(process, parent_conn)

    def take(self, name: str, setup: bytes, config: RegistrarConfig, address: Any) -> bool:
        """Hand manager `name`'s arguments to the spare; `False` if it is not usable."""
        if not self.process.is_alive():
            self.close()
            return False
        try:
            self.conn.send(("start", setup, config, address))
        except (OSError, ValueError):
            self.close()
            return False
        self.process.name = f"{_PROCESS_PREFIX}{name}"
        return True

    def close(self, timeout: float = 5.0) -> None:
        """Release an unused spare: it sees EOF and exits; killed after `timeout` seconds."""
        with contextlib.suppress(OSError):
            self.conn.close()
        self.process.join(timeout)
        if self.process.exitcode is None:
            with contextlib.suppress(OSError, ValueError):
                self.process.kill()
            self.process.join(timeout)


class _ExitWatch:
    """A `pidfd` and `/proc/<pid>` of a manager process: its exit, before its parent's word.

    With the forkserver context the supervisor's process is not the manager's parent: the
    process sentinel becomes readable once the forkserver has reaped the child and written
    its status (0.2-0.4 ms after the exit on the project's VM). A `pidfd` is readable as
    soon as the process has exited, and until it is reaped the kernel still shows its exit
    status in `/proc/<pid>/stat` (field 52), read through a directory descriptor opened
    while the process ran, so that a recycled pid cannot be read instead. Linux 5.3 and
    later; elsewhere `open` returns `None` and the sentinel alone is used.
    """

    __slots__ = ("pidfd", "proc")

    def __init__(self, pidfd: int, proc: int) -> None:
        self.pidfd = pidfd
        self.proc = proc

    @classmethod
    def open(cls, pid: int) -> _ExitWatch | None:
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

    def exitcode(self) -> int | None:
        """The exit code as `Process.exitcode` gives it (`-N`: killed by signal N).

        `None` while the process runs, and once its parent has reaped it (then the
        sentinel has it).
        """
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
        for fd in (self.pidfd, self.proc):
            with contextlib.suppress(OSError):
                os.close(fd)


class ManagerProcess:
    """The parent's handle on one running manager process (one incarnation).

    Start with [`start`][rr_actors._process.manager.ManagerProcess.start]; `on_exit(ManagerExit)`
    runs once on the watcher thread when the process ends, whatever the cause.
    """

    def __init__(
        self,
        name: str,
        process: Any,
        conn: Connection,
        *,
        heartbeat: float | None,
        heartbeat_timeout: float | None,
        on_exit: Callable[[ManagerExit], None],
    ) -> None:
        self.name = name
        self.process = process
        self.pid: int = process.pid
        self.conn = conn
        self._send_lock = threading.Lock()
        self._heartbeat = heartbeat
        self._heartbeat_timeout = heartbeat_timeout
        self._on_exit = on_exit
        self._hung_for: float | None = None
        self._stopping = False
        self.exited = threading.Event()
        self.exit: ManagerExit | None = None
        self._exit_watch = _ExitWatch.open(self.pid)

    @classmethod
    def start(
        cls,
        name: str,
        setup: bytes,
        config: RegistrarConfig,
        address: Any,
        *,
        start_timeout: float,
        heartbeat: float | None,
        heartbeat_timeout: float | None,
        on_exit: Callable[[ManagerExit], None],
        spare: Spare | None = None,
    ) -> ManagerProcess:
        """Start a manager process and wait until it serves (its catalog restored).

        Args:
            name, setup, config, address: what the manager runs (see `main`).
            start_timeout: seconds it may take to restore, set up and serve.
            heartbeat, heartbeat_timeout: seconds between pings (`None`: no heartbeat),
                and of silence before it counts as hung (`None`: three periods).
            on_exit: called once, on the watcher thread, with how it ended.
            spare: an idle pre-started process to run it in (else a new one is started;
                also if the spare died meanwhile).

        Raises:
            RegistrarUnavailableError: it failed (setup raised, its backup could not be
                read, ...) or died before it was ready; the message holds its traceback.
            CallTimeoutError: it was not ready within `start_timeout` seconds (it is killed).
        """
        if spare is not None and spare.take(name, setup, config, address):
            process, parent_conn = spare.process, spare.conn
        else:
            ctx = mp_context()
            parent_conn, child_conn = ctx.Pipe(duplex=True)
            process = ctx.Process(  # type: ignore[attr-defined]
                target=main,
                args=(setup, config, address, child_conn, _forker_pid(ctx)),
                name=f"{_PROCESS_PREFIX}{name}",
                daemon=True,
            )
            process.start()
            child_conn.close()
        deadline = time.monotonic() + start_timeout
        ready: Any = None
        while ready is None:
            left = deadline - time.monotonic()
            woke = multiprocessing.connection.wait([parent_conn, process.sentinel], max(left, 0))
            if parent_conn in woke:
                try:
                    ready = parent_conn.recv()
                except (EOFError, OSError):
                    woke = [process.sentinel]
            if ready is None and (process.sentinel in woke or left <= 0):
                if left <= 0:
                    process.kill()
                process.join(5.0)
                parent_conn.close()
                if left <= 0:
                    raise CallTimeoutError(
                        f"manager {name!r} was not ready within {start_timeout:g} s"
                    )
                raise RegistrarUnavailableError(
                    f"manager {name!r} died while starting ({_describe(process.exitcode).reason})"
                )
        if ready[0] != "ready":
            process.join(5.0)
            parent_conn.close()
            raise RegistrarUnavailableError(f"manager {name!r} failed to start:\n{ready[1]}")
        handle = cls(
            name,
            process,
            parent_conn,
            heartbeat=heartbeat,
            heartbeat_timeout=heartbeat_timeout,
            on_exit=on_exit,
        )
        threading.Thread(target=handle._watch, name=f"rr-watch-{name}", daemon=True).start()
        return handle

    # -- requests ---------------------------------------------------------------------

    def _send(self, message: tuple[Any, ...]) -> bool:
        with self._send_lock:
            try:
                self.conn.send(message)
            except (OSError, ValueError):
                return False
        return True

    def stop(self, timeout: float) -> ManagerExit:
        """Ask the manager to stop its registrar and exit; kill it after `timeout` seconds.

        Returns:
            How it ended (`"shutdown"`, or `"killed: shutdown timeout"`, or what it died of).
        """
        self._stopping = True
        self._send(("stop", timeout))
        if self.exited.wait(timeout) and self.exit is not None:
            if self.exit.normal:
                return ManagerExit("shutdown", normal=True)
            return self.exit
        self.kill()
        self.exited.wait(10.0)
        return ManagerExit(f"killed: no clean stop within {timeout:g} s", normal=False)

    def kill(self) -> None:
        """SIGKILL the process (no cleanup; its backup keeps what was written)."""
        with contextlib.suppress(OSError, ValueError):
            self.process.kill()

    # -- the watcher thread -----------------------------------------------------------

    def _watch(self) -> None:
        """Block on the sentinel, the `pidfd` and the control pipe; ping on the heartbeat."""
        waitables: list[Any] = [self.process.sentinel, self.conn]
        if self._exit_watch is not None:
            waitables.append(self._exit_watch.pidfd)
        period = self._heartbeat
        sent = 0
        oldest_unanswered: float | None = None
        next_ping = time.monotonic() + (period or 0.0)
        while True:
            if period is None or self._stopping:
                timeout = None  # stopping: no pings; block until it exits (or the pipe says)
            else:
                timeout = max(0.0, next_ping - time.monotonic())
            woke = multiprocessing.connection.wait(waitables, timeout)
            ended, exitcode = self._ended(woke, waitables)
            if ended:
                break
            if self.conn in woke:
                try:
                    message = self.conn.recv()
                except (EOFError, OSError):
                    waitables.remove(self.conn)
                    continue
                if message[0] == "pong" and message[1] == sent:
                    oldest_unanswered = None
            if period is None or self._stopping:
                continue
            now = time.monotonic()
            hung_after = self._heartbeat_timeout or 3.0 * period
            if oldest_unanswered is not None and now - oldest_unanswered > hung_after:
                self._hang(now - oldest_unanswered)
                period = None
            elif now >= next_ping:
                if oldest_unanswered is None:  # one ping in flight at a time
                    sent += 1
                    oldest_unanswered = now
                    self._send(("ping", sent))
                next_ping = now + period
        self._finish(exitcode)

    def _ended(self, woke: list[Any], waitables: list[Any]) -> tuple[bool, int | None]:
        """Whether the process ended, with its exit code if it was read early (`_ExitWatch`)."""
        if self.process.sentinel in woke:
            return True, None
        watch = self._exit_watch
        if watch is not None and watch.pidfd in woke:
            exitcode = watch.exitcode()
            if exitcode is not None:
                return True, exitcode
            waitables.remove(watch.pidfd)  # reaped meanwhile: the sentinel says it
        return False, None

    def _hang(self, silent_for: float) -> None:
        self._hung_for = silent_for
        logger.error(
            "manager %s hangs (no heartbeat answer for %.3f s): killing it", self.name, silent_for
        )
        self.kill()

    def _finish(self, exitcode: int | None) -> None:
        """Report the exit; `exitcode` if it was read before the parent reaped the process."""
        if exitcode is None:
            self.process.join(5.0)
            exitcode = self.process.exitcode
        with contextlib.suppress(OSError):
            self.conn.close()
        if self._hung_for is not None:
            result = ManagerExit(
                f"hung: no heartbeat answer for {self._hung_for:.3f} s (killed)", normal=False
            )
        else:
            result = _describe(exitcode)
        self.exit = result
        self.exited.set()
        try:
            self._on_exit(result)
        except Exception:
            logger.exception("exit handler of manager %s raised", self.name)
        finally:
            self.process.join(5.0)  # reaped by now, or soon: the forkserver's word
            if self._exit_watch is not None:
                self._exit_watch.close()
