"""The parent's handle on one manager process, and how a child ended.

```
 supervisor's thread           the watcher (watcher.py: one thread)       manager process
   ManagerProcess.start ──────────────────────────────────────────────►  child.main / standby
        ◄── Ready(pid) ──────────────────────────────────────────────────
                               waits on: process sentinel, control pipe,
                               the platform's exit watch (a pidfd on Linux)
                               ── Ping(n) every `heartbeat` s ─────────►  registrar mailbox
                               ◄── Pong(n, trouble) ────────────────────
                               a late answer: Heartbeat judges the silence
                               ── Probe(n) at each look ───────────────►  control loop
                               ◄── Progress(n, ...) (its mailbox's) ────
                               (hung: SIGKILL ─────────────────────────►)
                               (late, excused: on_overloaded(pid, Late))
   stop ── Stop(timeout) ──────────────────────────────────────────────►  registrar.stop()
        ◄── (wait_exit=False; then `reap`) ◄── Stopped(code) ────────────  then its exit
                               exit seen ──► finish: on_exit(ManagerExit) ──► the supervisor
```

A manager is killed and reported like a crash when it is *hung* (`heartbeat.py`) or
*unhealthy*: its answers say its listener has been unable to accept connections for as
long. What the pipe holds is read before a silence is judged. The exit watch
(`Platform.watch_exit`, a pidfd on Linux) tells an exit before the forkserver reaps it.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import multiprocessing.connection
import os
import signal
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import TYPE_CHECKING, Any

from rr_actors._core import runtime
from rr_actors._platform import PLATFORM
from rr_actors._process.child import main
from rr_actors._process.control import (
    ACTOR_DIED_EXIT,
    POOL_GAVE_UP_EXIT,
    POOL_HUNG_EXIT,
    PROCESS_PREFIX,
    STOPPED_EXIT,
    Announce,
    Events,
    EventsSynced,
    Failed,
    Forward,
    FromParent,
    HearsAll,
    Monitoring,
    PeersStopped,
    PeerStarted,
    Ping,
    Pong,
    Probe,
    Progress,
    Ready,
    Stop,
    Stopped,
    SyncEvents,
    fork,
    mp_context,
    start_forkserver,
    stopped_cleanly,
)
from rr_actors._process.hearers import HEARERS
from rr_actors._process.heartbeat import PACE, Hang, Heartbeat, Late, Look
from rr_actors._process.tally import Received, Tally
from rr_actors._process.watcher import WATCHER
from rr_actors._transport.messenger import Address
from rr_actors.config import RegistrarConfig
from rr_actors.errors import CallTimeoutError, RegistrarUnavailableError, RrError

if TYPE_CHECKING:
    from rr_actors._process.spare import Spare

__all__ = [
    "ManagerExit",
    "ManagerProcess",
    "describe",
    "mp_context",
    "start_forkserver",
    "stopped_cleanly",
]

logger = logging.getLogger("rr_actors")

_SHUTDOWN_SIGNALS = frozenset({signal.SIGTERM})  # OTP's `shutdown`, not a crash

_READ_AT_ONCE = 1000  # a manager that floods its pipe cannot put off its judgement


class ManagerExit:
    """Why a child (a manager process or thread, a nested supervisor) ended.

    After OTP's exit reasons: `normal` and `shutdown` (`normal=True`) do not restart a
    `transient` child. `clean`: it let go of what it held itself (else the death watch
    releases it); default `normal` (a SIGTERM is normal but not clean).
    """

    __slots__ = ("clean", "normal", "reason")

    def __init__(self, reason: str, *, normal: bool, clean: bool | None = None) -> None:
        self.reason = reason
        self.normal = normal
        self.clean = normal if clean is None else clean

    def __repr__(self) -> str:
        return f"ManagerExit({self.reason!r}, normal={self.normal}, clean={self.clean})"


_EXITS: dict[int, tuple[str, bool]] = {
    STOPPED_EXIT: ("normal", True),  # its registrar stopped cleanly: the one normal exit
    0: ("exited with code 0 without stopping its registrar", False),  # nothing let go
    ACTOR_DIED_EXIT: ("registrar actor died", False),
    POOL_HUNG_EXIT: ("hung: one of its thread managers did not answer its heartbeat", False),
}


def describe(exitcode: int | None) -> ManagerExit:
    if exitcode is None:
        return ManagerExit("unknown exit", normal=False)
    if exitcode == POOL_GAVE_UP_EXIT:  # a pool's: OTP's `shutdown`, but nothing let go
        return ManagerExit("its supervisor gave up", normal=True, clean=False)
    known = _EXITS.get(exitcode)
    if known is not None:
        reason, normal = known
        return ManagerExit(reason, normal=normal)
    if exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        if -exitcode in _SHUTDOWN_SIGNALS:  # asked to stop: OTP's `shutdown`
            return ManagerExit(f"shutdown ({name})", normal=True, clean=False)
        return ManagerExit(f"killed by {name}", normal=False)
    return ManagerExit(f"exit code {exitcode}", normal=False)


class ManagerProcess:
    """The parent's handle on one running manager process (one incarnation); `on_exit`
    runs once, on a thread of its own, when the process ends, whatever the cause."""

    def __init__(
        self,
        name: str,
        process: BaseProcess,
        conn: Connection,
        *,
        heartbeat: float | None,
        heartbeat_timeout: float | None,
        on_exit: Callable[[ManagerExit], None],
        on_events: Callable[[list[Any]], None] | None = None,
        received: Received | None = None,
        on_overloaded: Callable[[int, Late], None] | None = None,
        on_announce: Callable[[str, bool], None] | None = None,
    ) -> None:
        self.name = name
        self._on_announce = on_announce
        self.process = process
        assert process.pid is not None  # (started)
        self.pid: int = process.pid
        self._received = received if received is not None else Received(on_events, None)
        self.conn = conn
        self._send_lock = runtime.Lock()
        self._beat = (
            None
            if heartbeat is None
            else Heartbeat(
                name,
                heartbeat,
                heartbeat_timeout or 3.0 * heartbeat,
                PLATFORM.watch_cpu(self.pid),
                runtime.monotonic(),
                probes=True,
                on_late=self._late,
                pace=PACE,
            )
        )
        self._on_overloaded = on_overloaded
        self._on_exit = on_exit
        self._syncs: dict[int, runtime.Event] = {}  # events-sync tokens waiting for answers
        self._sync_tokens = itertools.count(1)
        self._hung: Hang | None = None
        self._unhealthy: str | None = None  # why it was killed although it answered
        self._stopping = False
        self.exited = runtime.Event()
        self.exit: ManagerExit | None = None
        self.reported = runtime.Event()  # its `Stopped` came (`_reported` says it), or its exit
        self._reported: ManagerExit | None = None
        self._exit_by = 0.0  # (monotonic) `reap` kills it then
        self._exit_watch = PLATFORM.watch_exit(self.pid)
        self.forwarding = False  # as last told (`forward_events`); `start` sets it
        self._beating = self._beat is not None  # pinged and judged (not once killed)
        self._held = False  # its pings wait for `beat_from` (a tree's ordered start)
        self._beat_from: float | None = None  # (set by `beat_from`, read by the watcher)
        self.waitables: list[Any] = [process.sentinel, conn]  # what the watcher waits on
        if self._exit_watch is not None:
            self.waitables.append(self._exit_watch)

    @classmethod
    def start(
        cls,
        name: str,
        setup: bytes,
        config: RegistrarConfig,
        address: Address | None,
        *,
        start_timeout: float,
        heartbeat: float | None,
        heartbeat_timeout: float | None,
        on_exit: Callable[[ManagerExit], None],
        spare: Spare | None = None,
        forward_events: bool = False,
        on_events: Callable[[list[Any]], None] | None = None,
        on_overloaded: Callable[[int, Late], None] | None = None,
        announced: bool = False,
        on_announce: Callable[[str, bool], None] | None = None,
        hold: Callable[[ManagerProcess], None] | None = None,
    ) -> ManagerProcess:
        """Start a manager process and wait until it serves (its catalog restored);
        `announced`: its supervisor announces its starts (`start_registrar`); `hold`: its
        pings wait for `beat_from` (`hold(handle)` is told: a tree's ordered start, OTP's
        supervisor hears its children only after it).

        Seconds: `start_timeout`, `heartbeat` (`None`: none), `heartbeat_timeout` (`None`:
        three periods). `on_events` (each forwarded batch), `on_overloaded` (a late answer
        excused) and `on_announce` (a pool's registrar's name, `Announce`) run on the
        watcher thread that all manager processes share; `on_exit` on one of its own.

        Raises:
            CatalogCorruptError: its backup cannot be read (with its `path`; a note holds
                the manager's traceback).
            RegistrarUnavailableError: it failed otherwise or died before it was ready.
            CallTimeoutError: it was not ready within `start_timeout` seconds (killed).
        """
        simulated = runtime.manager_process
        if simulated is not None:  # a simulated process (`rr_actors.simulation`)
            started: ManagerProcess = simulated(
                name,
                setup,
                config,
                address,
                start_timeout=start_timeout,
                heartbeat=heartbeat,
                heartbeat_timeout=heartbeat_timeout,
                on_exit=on_exit,
                forward_events=forward_events,
                on_events=on_events,
                announced=announced,
            )
            return started
        tally = Tally.create() if on_events is not None else None
        backup = config.backup_path  # (its outbox: what a kill kept from the journal)
        received = Received(on_events, tally, None if backup is None else os.path.abspath(backup))
        deadline = runtime.monotonic() + start_timeout
        try:
            process, parent_conn = _launch(
                name, setup, config, address, spare, forward_events, tally, start_timeout, announced
            )
        except BaseException as e:
            if tally is not None:
                tally.close()  # (its file and map; nothing was forked to use it)
            if isinstance(e, TimeoutError):  # the fork itself (a stopped forkserver)
                raise CallTimeoutError(
                    f"manager {name!r} was not ready within {start_timeout:g} s"
                ) from e
            raise
        try:
            _await_ready(
                name,
                process,
                parent_conn,
                start_timeout,
                received,
                deadline=deadline,
                on_announce=on_announce,
            )
        except BaseException:
            received.close()  # (a Ctrl-C while waiting; after a failure it is closed)
            raise
        handle = cls(
            name,
            process,
            parent_conn,
            heartbeat=heartbeat,
            heartbeat_timeout=heartbeat_timeout,
            on_exit=on_exit,
            on_events=on_events,
            received=received,
            on_overloaded=on_overloaded,
            on_announce=on_announce,
        )
        handle.forwarding = forward_events
        if hold is not None and handle._beat is not None:
            handle._held = True
            hold(handle)
        WATCHER.watch(handle)
        return handle

    # -- requests ---------------------------------------------------------------------

    def _send(self, message: FromParent) -> bool:
        with self._send_lock:
            try:
                self.conn.send(message)
            except (OSError, ValueError):
                return False
        return True

    def tell_started(self, name: str) -> None:
        """Tell the manager's registrars that registrar `name` (re)started (`PeerStarted`;
        `HEARERS` says whom to tell). Any thread; nothing once its pipe is closed."""
        self._send(PeerStarted(name))

    def tell_stopped(self, names: tuple[str, ...], lost: tuple[str, ...] = ()) -> None:
        """Registrars `names` stopped for good, `lost` died (`PeersStopped`, before `Stop`)."""
        self._send(PeersStopped(names, lost))

    def forward_events(self, on: bool) -> None:
        self.forwarding = on  # (what the exit reads: nobody listens, nothing to count)
        self._send(Forward(on))

    def sync_events(self, timeout: float) -> bool:
        """Block until what the manager forwarded before this call reached `on_events`;
        whether it did within `timeout` seconds (`True` once it exited)."""
        token = next(self._sync_tokens)  # atomic in CPython
        done = self._syncs[token] = runtime.Event()
        try:
            if self.exited.is_set() or not self._send(SyncEvents(token, timeout)):
                return self.exited.is_set()
            return done.wait(timeout)
        finally:
            self._syncs.pop(token, None)

    def beat_from(self, when: float) -> None:
        """Ping it from `when` on (monotonic seconds), held until now (any thread)."""
        self._beat_from = when
        WATCHER.nudge(self)  # (its turn, on the watcher's thread, starts the pings)

    def quiet(self) -> None:
        """Ping it no more (its tree's stop began): its stop's `shutdown` catches a hang,
        as OTP's shutdown does, and a big tree's pings leave the watcher to the stops."""
        self._stopping = True  # (as `stop`: no more pings, no more judgements)

    def stop(
        self, timeout: float, *, restarting: bool = False, wait_exit: bool = True
    ) -> ManagerExit:
        """Ask the manager to stop its registrar and exit; kill it after `timeout` seconds
        (`restarting`: its peers see it unavailable for now, not stopped for good;
        `wait_exit=False`: once it reports its registrar stopped cleanly, its exit to `reap`).
        Its registrar's stop ends a fifth of that, 1 s at most, earlier (`child.py`)."""
        self._stopping = True
        self._exit_by = runtime.monotonic() + timeout
        self._send(Stop(timeout, restarting))
        if (self.exited if wait_exit else self.reported).wait(timeout):
            ended = self.exit if self.exited.is_set() else self._reported
            # not clean: it is told lost (rule 19) once it exited, when it can answer no one
            killed = None if ended is None or ended.clean else self.reap()
            if ended is not None:
                if killed is not None or not ended.normal:
                    return ended if killed is None else ManagerExit(killed, normal=False)
                return ManagerExit("shutdown", normal=True, clean=ended.clean)
        self.kill()
        self.exited.wait(10.0)
        return ManagerExit(f"killed: no clean stop within {timeout:g} s", normal=False)

    def reap(self) -> str | None:
        """Wait for its exit after `stop(wait_exit=False)` until that stop's `timeout` ran out,
        then kill it (OTP's `brutal_kill`); why it was killed (`None`: it exited)."""
        if self.exited.is_set() or self.exited.wait(max(self._exit_by - runtime.monotonic(), 0)):
            return None
        logger.error("manager %s stopped its registrar but did not exit: killing it", self.name)
        self.kill()
        self.exited.wait(10.0)
        return "killed: its registrar stopped, but its process did not exit within its shutdown"

    def kill(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            self.process.kill()

    # -- the watch (`watcher.py` waits; these steps judge) ----------------------------

    def wake_at(self) -> float | None:
        """When its next `turn` is due unwoken (monotonic seconds; `None`: when woken)."""
        if not self._beating or self._stopping or self._held:
            return None  # stopping: no pings; only its exit (or the pipe) wakes it
        assert self._beat is not None  # (beating)
        return self._beat.wake_at

    def turn(self, woke: list[Any]) -> tuple[bool, int | None]:
        """`woke` (its ready `waitables`) or `wake_at` came: read the pipe, then judge its
        silence. Whether it ended, and its exit code if the exit watch read it."""
        waitables = self.waitables
        ended, exitcode = self._ended(woke, waitables)
        if ended:
            return True, exitcode
        now = runtime.monotonic()  # what came before now is read before a judgement
        health = self._read_available(waitables, now)
        beat = self._beat
        if self._held and self._beat_from is not None and beat is not None:
            beat.restart(self._beat_from)
            self._held = False
        if beat is None or not self._beating or self._stopping or self._held:
            return False, None
        if health is not None and health[0] > beat.bound:
            self._kill_unhealthy(*health)
            self._beating = False
            return False, None
        verdict = beat.tick(now)
        if isinstance(verdict, Hang):
            self._hang(verdict)
            self._beating = False
        elif isinstance(verdict, Look):
            self._send(Probe(verdict.number))
        elif verdict is not None:
            self._send(Ping(verdict))
            beat.sent(runtime.monotonic())
        return False, None

    def watch_failed(self, error: BaseException) -> None:
        """Its turn raised `error` (logged): kill it; from now on only its exit is watched."""
        self._unhealthy = f"its watch failed ({type(error).__name__}: {error}) (killed)"
        self._beating = False
        self.waitables[:] = [self.process.sentinel]  # (what raised is read no more)
        self.kill()

    def _ended(self, woke: list[Any], waitables: list[Any]) -> tuple[bool, int | None]:
        if self.process.sentinel in woke:
            return True, None
        watch = self._exit_watch
        if watch is not None and watch in woke:
            exitcode = watch.exitcode()
            if exitcode is not None:
                return True, exitcode
            waitables.remove(watch)  # reaped meanwhile: the sentinel says it
        return False, None

    def _read_available(self, waitables: list[Any], now: float) -> tuple[float, str] | None:
        """Read what the manager has sent; the health its answer to the ping in flight
        says, if that came."""
        health = None
        for _ in range(_READ_AT_ONCE):
            if self.conn not in waitables or not _readable(self.conn):
                break
            answer = self._read_control(waitables, now)
            if answer is not None:
                health = answer
        return health

    def _read_control(self, waitables: list[Any], now: float) -> tuple[float, str] | None:
        """Read one message; if it answers the ping in flight, for how long (seconds) and
        why the manager has been unable to accept connections (`0.0, ""`: it can)."""
        try:
            message = self.conn.recv()
        except (EOFError, OSError):
            waitables.remove(self.conn)  # the exit follows: the sentinel says it
            return None
        handler = _HANDLERS.get(type(message))
        if handler is None:
            logger.error("manager %s sent an unknown control message %r", self.name, message)
            return None
        return handler(self, message, now)

    def _events(self, message: Events, _now: float) -> None:
        self._received.deliver(self.name, message.batch)

    def _announce(self, message: Announce, _now: float) -> None:
        if self._on_announce is not None:
            try:
                self._on_announce(message.name, message.restarted)
            except Exception:
                logger.exception("announcing %s (from %s) failed", message.name, self.name)

    def _monitoring(self, message: Monitoring, _now: float) -> None:
        HEARERS.monitoring(self, message.names, message.at)

    def _hears_all(self, message: HearsAll, _now: float) -> None:
        HEARERS.hears_all(self, on=message.on, at=message.at)

    def _synced(self, message: EventsSynced, _now: float) -> None:
        waiting = self._syncs.get(message.token)
        if waiting is not None:
            waiting.set()

    def _stopped(self, message: Stopped, _now: float) -> None:
        self._reported = describe(message.code)
        self.reported.set()

    def _pong(self, message: Pong, now: float) -> tuple[float, str] | None:
        if self._beat is None or not self._beat.answered(message.number, now):
            return None
        trouble = message.trouble
        return (0.0, "") if trouble is None else (float(trouble[0]), str(trouble[1]))

    def _progress(self, message: Progress, now: float) -> None:
        if self._beat is not None:
            self._beat.progress(
                message.number, message.pinged, message.handled, message.queued, now
            )

    def _late(self, late: Late) -> None:
        if self._on_overloaded is None:
            return
        try:
            self._on_overloaded(self.pid, late)
        except Exception:
            logger.exception("overload handler of manager %s raised", self.name)

    def _hang(self, hang: Hang) -> None:
        self._hung = hang
        logger.error("manager %s hangs (%s): killing it", self.name, hang.reason())
        self.kill()

    def _kill_unhealthy(self, unable_for: float, why: str) -> None:
        self._unhealthy = (
            f"unhealthy: could not accept connections for {unable_for:.3f} s ({why}) (killed)"
        )
        logger.error("manager %s is %s", self.name, self._unhealthy)
        self.kill()

    def finish(self, exitcode: int | None) -> None:
        if exitcode is None:
            self.process.join(5.0)
            exitcode = self.process.exitcode
        self._received.drain(self.name, self.conn)  # what it sent before it died, then
        self._received.count_lost(self.name, self.pid, listened=self.forwarding)  # (unsent)
        with self._send_lock, contextlib.suppress(OSError):  # (never under a request
            self.conn.close()  # being written: that would write to no descriptor)
        if self._hung is not None:
            result = ManagerExit(f"hung: {self._hung.reason()} (killed)", normal=False)
        elif self._unhealthy is not None:
            result = ManagerExit(self._unhealthy, normal=False)
        else:
            result = describe(exitcode)
        self.exit = result
        self.exited.set()
        HEARERS.forget(self)  # (after `exited`: a report read later is not kept)
        self.reported.set()
        for waiting in list(self._syncs.values()):  # nothing more will come
            waiting.set()
        try:
            if self._beat is not None:  # (leaves the pace before a restart's next life joins)
                self._beat.close()
        except Exception:  # (its exit is told all the same, its process released)
            logger.exception("manager %s: closing its heartbeat raised", self.name)
        try:
            self._on_exit(result)
        except Exception:
            logger.exception("exit handler of manager %s raised", self.name)
        finally:
            self.process.join(5.0)  # reaped by now, or soon: the forkserver's word
            release(self.process)
            if self._exit_watch is not None:
                self._exit_watch.close()


_HANDLERS: dict[type[Any], Callable[[ManagerProcess, Any, float], tuple[float, str] | None]] = {
    Events: ManagerProcess._events,
    EventsSynced: ManagerProcess._synced,
    Announce: ManagerProcess._announce,
    Monitoring: ManagerProcess._monitoring,
    HearsAll: ManagerProcess._hears_all,
    Pong: ManagerProcess._pong,
    Progress: ManagerProcess._progress,
    Stopped: ManagerProcess._stopped,
}


def release(process: BaseProcess) -> None:
    """Close the descriptors a reaped process object holds (not left to the garbage
    collector: a traceback that keeps a reference would keep them open)."""
    with contextlib.suppress(ValueError, OSError):
        process.close()


def _launch(
    name: str,
    setup: bytes,
    config: RegistrarConfig,
    address: Address | None,
    spare: Spare | None,
    forward: bool,
    tally: Tally | None,
    start_timeout: float,
    announced: bool = False,
) -> tuple[Any, Connection]:
    """Hand the manager to `spare`, or start a new process for it (`TimeoutError`: the
    fork took longer than `start_timeout`)."""
    path = None if tally is None else tally.path
    if spare is not None and spare.take(
        name, setup, config, address, forward=forward, tally=path, announced=announced
    ):
        return spare.process, spare.conn
    return fork(
        main,
        lambda conn, forker: (setup, config, address, conn, forker, forward, path, announced),
        f"{PROCESS_PREFIX}{name}",
        start_timeout,
    )


def _await_ready(
    name: str,
    process: BaseProcess,
    conn: Connection,
    start_timeout: float,
    received: Received,
    *,
    deadline: float | None = None,
    on_announce: Callable[[str, bool], None] | None = None,
) -> None:
    """Wait for the manager's `Ready`; raise if it never comes (events before it go to
    `received`, a pool's `Announce` of a manager it started to `on_announce`;
    `deadline`: when `start_timeout` ends, default from now)."""
    if deadline is None:
        deadline = runtime.monotonic() + start_timeout
    pid = process.pid
    assert pid is not None  # (started)
    ready: Ready | Failed | None = None
    ended = False  # the pipe was read to its end
    while ready is None:
        left = deadline - runtime.monotonic()
        woke = multiprocessing.connection.wait([conn, process.sentinel], max(left, 0))
        if conn in woke:
            try:
                message = conn.recv()
            except (EOFError, OSError):
                ended = True
                woke = [process.sentinel]
            else:
                if isinstance(message, Ready | Failed):
                    ready = message
                else:
                    _before_ready(name, message, received, on_announce)
        ended_first = ready is None and left > 0 and not ended and process.sentinel in woke
        if ended_first and _readable(conn):  # what it sent before it ended comes first
            continue  # (its Failed, behind events it forwarded)
        if ready is None and (process.sentinel in woke or left <= 0):
            if left <= 0:
                process.kill()
            reason = _reap(name, process, conn, received)
            if left <= 0:
                raise CallTimeoutError(f"manager {name!r} was not ready within {start_timeout:g} s")
            raise RegistrarUnavailableError(f"manager {name!r} died while starting ({reason})")
    if isinstance(ready, Failed):
        _reap(name, process, conn, received)
        raise _start_failed(name, pid, ready)


def _before_ready(
    name: str, message: object, received: Received, on_announce: Callable[[str, bool], None] | None
) -> None:
    """A message that came before the manager's `Ready`: its restore's in-doubt events, say,
    or a pool's `Announce` of a manager it started on an earlier run's catalog (a `Warm`,
    from a spare that warmed up after it was taken, is dropped)."""
    if isinstance(message, Events):
        received.deliver(name, message.batch)
    elif isinstance(message, Announce) and on_announce is not None:
        on_announce(message.name, message.restarted)


def _reap(name: str, process: BaseProcess, conn: Connection, received: Received) -> str:
    """After a start that failed: count its events, close its pipe; how it ended."""
    assert process.pid is not None  # (started)
    process.join(5.0)
    received.drain(name, conn)
    received.count_lost(name, process.pid)
    conn.close()
    reason = describe(process.exitcode).reason
    release(process)
    return reason


def _start_failed(name: str, pid: int, failed: Failed) -> RrError:
    """What a start that sent `failed` raises: its `CatalogCorruptError` (as in-process),
    else `RegistrarUnavailableError` with its traceback."""
    if failed.corrupt is not None:
        failed.corrupt.add_note(f"raised in manager {name!r} (pid {pid}):\n{failed.traceback}")
        return failed.corrupt
    return RegistrarUnavailableError(f"manager {name!r} failed to start:\n{failed.traceback}")


def _readable(conn: Connection) -> bool:
    try:
        return conn.poll(0)
    except (OSError, EOFError):
        return False
