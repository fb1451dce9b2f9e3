"""The child's side of a manager process: `main`, `standby` and the control loop.

Runs only in manager processes. `main` lets SIGINT pass (a Ctrl-C is the supervisor's
to handle: it stops the tree in order, as OTP leaves shutdown to the supervisor), dies
with the process that forked it, attaches to the system (its supervisor's process speaks
for it if it dies: rule 19), starts the registrar (which restores its catalog), runs
`setup(registrar)`, settles the in-doubt entries it was offered, serves, reports `Ready`
and answers control requests. It exits at EOF on the control pipe (the supervisor's
process is gone: `PARENT_GONE_EXIT`), with `STOPPED_EXIT` when its registrar was stopped
cleanly (by `Stop`, reported first with `Stopped`; or by code in the manager: a
`transient` manager is then not restarted), with `ACTOR_DIED_EXIT` when the registrar
actor died.

The requests and answers, drawn: `control.py`; the control loop dispatches on their type
(`_HANDLERS`). `Supervisor.run_in` goes over the system's transport, not this pipe.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import pickle
import signal
import socket
import struct
import sys
import threading
import time
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

import cloudpickle

from rr_actors import events
from rr_actors._core.actor import Inbox
from rr_actors._core.bus import Forwarder, Publisher
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._platform import PLATFORM
from rr_actors._process.control import (
    ACTOR_DIED_EXIT,
    PARENT_GONE_EXIT,
    STOPPED_EXIT,
    TITLE_PREFIX,
    Events,
    EventsSynced,
    Failed,
    Forward,
    FromChild,
    HearsAll,
    Monitoring,
    PeersStopped,
    PeerStarted,
    Ping,
    Pong,
    Probe,
    Progress,
    Ready,
    Start,
    Stop,
    Stopped,
    SyncEvents,
    Warm,
    WarmUp,
    stopped_cleanly,
)
from rr_actors._process.tally import Journal
from rr_actors._store.schema import empty_image, expected_objects
from rr_actors._transport.messenger import Address, Transport
from rr_actors.config import RegistrarConfig
from rr_actors.errors import CatalogCorruptError, RrError
from rr_actors.events.kinds import number_events

if TYPE_CHECKING:
    from rr_actors._registrar import ResourceRegistrar

logger = logging.getLogger("rr_actors")

empty_image()  # in the forkserver's preload: a fresh backup is written, not built, in each child

START_HOLD = 1.0
"""Seconds at most the events of a start are held back so that `Ready` goes first."""


def provider_names(registrar: ResourceRegistrar) -> set[str]:
    """The registrars `registrar` holds a query at (a parallel stop's dependencies, asked
    by `Supervisor.run`: defined here, where a manager process has it imported)."""
    return {query.serving_rr for query in registrar.client_queries(timeout=5.0)}


class Hooks:
    """What a pool's `setup` (`_supervision/policy.py`, `PoolSetup`) hooks into: this
    process's event hub, a step run before its registrar stops (the `Stop`'s timeout
    in seconds; whether it will be restarted), and the control pipe to its parent
    (`to_parent`: any thread; nothing if the parent is gone)."""

    hub: Publisher[events.Event] | None = None
    before_stop: Callable[[float, bool], None] | None = None
    to_parent: Callable[[FromChild], None] | None = None


HOOKS = Hooks()


def set_title(name: str) -> None:
    """Name this process after its manager for `ps` and `top` (the kernel's 15-byte name
    is the name itself; with `setproctitle`, the command line `rr-actors: <name>`)."""
    with contextlib.suppress(ImportError):  # (optional; preloaded by the forkserver)
        import setproctitle  # noqa: PLC0415

        setproctitle.setproctitle(f"{TITLE_PREFIX}{name}")
    PLATFORM.set_process_name(name)  # after setproctitle, which may set it to the title


class _Control:
    """The child's end of the control pipe; `send` may be called from any thread."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self.lock = threading.Lock()

    def send(self, message: FromChild) -> None:
        # OSError: the parent is gone; the control loop sees EOF and exits
        with self.lock, contextlib.suppress(OSError):
            self.conn.send(message)


class _Report:
    """This process's monitors, reported on the control pipe (`Membership.report`): held
    until `Ready` has gone (its supervisor reads what follows `Ready` on its handle), then
    sent as they come. Any thread."""

    def __init__(self, control: _Control) -> None:
        self.control = control
        self.lock = threading.Lock()
        self.held: list[FromChild] | None = []

    def monitoring(self, names: tuple[str, ...], at: float) -> None:
        self._send(Monitoring(names, at))

    def hears_all(self, on: bool, at: float) -> None:
        self._send(HearsAll(on, at))

    def _send(self, message: FromChild) -> None:
        with self.lock:
            if self.held is not None:
                self.held.append(message)
                return
        self.control.send(message)

    def ready(self) -> None:
        """`Ready` has gone: send what was held, in order, and from now on at once."""
        with self.lock:
            held, self.held = self.held or [], None
            for message in held:  # (under the lock: nothing overtakes them)
                self.control.send(message)


class _Pong:
    """A reply that answers a heartbeat ping once the registrar actor got to it, with how
    long (and why) its listener cannot accept connections (judged as a hang)."""

    def __init__(
        self, control: _Control, number: int, trouble: Callable[[], tuple[float, str] | None]
    ) -> None:
        self.control = control
        self.number = number
        self.trouble = trouble

    def set_result(self, _: Any) -> None:
        self.control.send(Pong(self.number, self.trouble()))

    def set_error(self, _: BaseException) -> None:
        pass  # no pong: the parent counts it as missed


def _supervisor_pid(conn: Connection) -> int:
    """The pid of the process that made the control pipe (Linux `SO_PEERCRED`; elsewhere
    the parent process)."""
    option = getattr(socket, "SO_PEERCRED", None)
    if option is not None:
        fd = os.dup(conn.fileno())
        try:
            pipe = socket.socket(fileno=fd)
        except OSError:  # not a socket pair
            os.close(fd)
        else:
            with pipe, contextlib.suppress(OSError):
                credentials = pipe.getsockopt(socket.SOL_SOCKET, option, 12)
                pid, _uid, _gid = struct.unpack("3i", credentials)
                if pid > 0:
                    return int(pid)
    return os.getppid()


def _exit(code: int, attached: Transport | None) -> None:
    if attached is not None:
        with contextlib.suppress(Exception):
            attached.close()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def main(
    setup: bytes,
    config: RegistrarConfig,
    address: Address | None,
    conn: Connection,
    parent: int | None = None,
    forward: bool = False,
    tally: str | None = None,
    announced: bool = False,
) -> None:
    """Run one manager: restore, set up, serve, then answer control requests until stopped.

    `setup`: cloudpickled (or of `None`); `address`: `None` runs unattached; `parent`: the
    forking process's pid; `tally`: the journal's file (`tally.py`), or `None`;
    `announced`: its supervisor announces its starts (`start_registrar`).
    """
    _let_ctrl_c_pass()  # first: a Ctrl-C from here on is the supervisor's
    PLATFORM.die_with_parent(parent)
    number_events()
    set_title(config.name)
    _run_manager(setup, config, address, conn, forward, tally, announced)


def _let_ctrl_c_pass() -> None:
    """Let a Ctrl-C in the terminal pass: its supervisor stops this manager, in order (a
    handler that does nothing, not `SIG_IGN`, which the processes it `exec`s would inherit)."""
    signal.signal(signal.SIGINT, _ctrl_c_passes)


def _ctrl_c_passes(signum: int, frame: object) -> None:
    del signum, frame


def _warm_up() -> None:
    """Pay a fresh process's first-use costs while it idles as a spare, not after a crash:
    a full collection copies the heap's copy-on-write pages once; the schema objects a
    backup is checked against are made once."""
    import gc  # noqa: PLC0415

    gc.collect()
    expected_objects()


def standby(conn: Connection, parent: int | None = None, warm: bool = True) -> None:
    """A spare (`spare.py`): wait, started but idle, for a `Start` with `main`'s arguments,
    and run it; exit at EOF unused. It warms up at once, or (`warm=False`: forked ahead of
    a start in order) when told (`WarmUp`), so that it does not compete with the starts."""
    _let_ctrl_c_pass()  # first: a Ctrl-C from here on is the supervisor's
    PLATFORM.die_with_parent(parent)
    number_events()  # (a manager process's, before it idles: not on the restart path)
    set_title("spare")
    try:
        start = None if warm else conn.recv()
        if start is None or isinstance(start, WarmUp):
            if not conn.poll(0):  # taken already: the warm-up would only delay the manager
                _warm_up()
                conn.send(Warm())
            start = conn.recv()
    except (EOFError, OSError):
        os._exit(0)  # released unused, or the parent is gone
    if not isinstance(start, Start):
        os._exit(0)
    set_title(start.config.name)
    _run_manager(
        start.setup, start.config, start.address, conn, start.forward, start.tally, start.announced
    )


class _Pickled:
    """An event as the journal pickled it, forwarded in its place (pickled once, not twice);
    it unpickles as the event."""

    __slots__ = ("data",)

    def __init__(self, data: bytes) -> None:
        self.data = data

    def __reduce__(self) -> tuple[Callable[[bytes], Any], tuple[bytes]]:
        return pickle.loads, (self.data,)


class _EventLine:
    """Forwards this process's registrar events to the supervisor's process while asked to.

    While on, `hub`'s one sink is a `Forwarder` (made at the first switch on) sending
    batches over the control pipe, so the registrar builds events only then. The events of
    the start are journaled at once but sent after `Ready` (or `START_HOLD`), in order, so
    that a restart is not held up by them.
    """

    def __init__(
        self,
        control: _Control,
        name: str,
        *,
        on: bool,
        tally: str | None,
        hold: float = START_HOLD,
    ) -> None:
        self.control = control
        self.name = name
        self.journal = None if tally is None else Journal.open(tally)
        self.hub: Publisher[events.Event] = events.publisher()
        self.forwarder: Forwarder[events.Event] | None = None
        self.sink: Callable[[events.Event], None] | None = None
        self.on = False
        self._held = threading.Event()  # set: the start is over, batches go at once
        self._hold_until = time.monotonic() + hold
        self.switch(on=on)

    def started(self) -> None:
        self._held.set()

    @staticmethod
    def _keep_and_forward(
        journal: Journal, forwarder: Forwarder[events.Event], event: events.Event
    ) -> None:
        data = journal(event)
        forwarder(event if data is None else _Pickled(data))  # type: ignore[arg-type]

    def _send(self, control: _Control, batch: list[events.Event]) -> None:
        if not self._held.is_set():  # (the forwarder's thread: held back, in order)
            self._held.wait(max(0.0, self._hold_until - time.monotonic()))
        control.send(Events(batch))
        if self.journal is not None:
            self.journal.sent()

    def switch(self, *, on: bool) -> None:
        if on and not self.on:
            if self.forwarder is None or self.sink is None:
                self.forwarder = Forwarder(
                    functools.partial(self._send, self.control),
                    notice=events.EventsDropped,
                    name=f"{self.name}-events",
                )
                self.sink = self.forwarder
                if self.journal is not None:
                    self.sink = functools.partial(
                        self._keep_and_forward, self.journal, self.forwarder
                    )
            self.hub.add_sink(self.sink)
        elif self.on and not on and self.sink is not None:
            self.hub.remove_sink(self.sink)
        self.on = on

    def flush(self, timeout: float) -> None:
        if self.forwarder is not None:
            self.forwarder.close(timeout=timeout)

    def sync(self, control: _Control, token: int, timeout: float) -> None:
        if self.forwarder is not None:
            self.forwarder.wait_sent(timeout=timeout)
        control.send(EventsSynced(token))


def _run_manager(
    setup: bytes,
    config: RegistrarConfig,
    address: Address | None,
    conn: Connection,
    forward: bool,
    tally: str | None = None,
    announced: bool = False,
) -> None:
    from rr_actors._registrar import Served, start_registrar  # noqa: PLC0415 - preloaded

    control = _Control(conn)
    line = _EventLine(control, config.name, on=forward, tally=tally)
    report = MEMBERSHIP.report = _Report(control)  # (before its restore monitors anything)
    attached: Transport | None = None
    try:
        if address is not None:
            attached = address.attach()
            attached.supervised_by(_supervisor_pid(conn))  # it restarts this one (rule 19)
        registrar = start_registrar(  # (it ends by `_exit`: no hook at the main thread's end)
            config, upstream=line.hub, hold_in_doubt=True, announced=announced, at_exit=False
        )
        HOOKS.hub = line.hub
        HOOKS.to_parent = control.send
        setup_fn = cloudpickle.loads(setup)
        if setup_fn is not None:
            setup_fn(registrar)
        registrar.settle_in_doubt()  # setup returned: what it was offered is handled
        if attached is not None:
            attached.serve(Served(registrar))
    except BaseException as exc:  # noqa: BLE001 - reported to the supervisor, then exit
        corrupt = exc if isinstance(exc, CatalogCorruptError) else None  # (its path matters)
        line.started()  # what it published before it failed goes first (as it can)
        line.flush(timeout=1.0)
        control.send(Failed("".join(traceback.format_exception(exc)), corrupt))
        os._exit(1)
    stopping = threading.Event()

    def watch_actor() -> None:
        registrar.wait_ended()
        if stopping.is_set():
            return  # the supervisor's `stop`: the control loop exits
        if stopped_cleanly(registrar.name):  # code in the manager called registrar.stop()
            _exit(STOPPED_EXIT, attached)
        _exit(ACTOR_DIED_EXIT, attached)

    control.send(Ready(os.getpid()))
    report.ready()
    line.started()  # the events of its start follow `Ready`, in their order
    # after `Ready`: a death before it started is seen at once (`wait_ended` returns)
    threading.Thread(target=watch_actor, name="rr-manager-actor-watch", daemon=True).start()
    _ControlLoop(conn, control, registrar, attached, stopping, line).run()


class _ControlLoop:
    """The child's control loop: answer pings, forward events or not, stop; exit on EOF."""

    def __init__(
        self,
        conn: Connection,
        control: _Control,
        registrar: ResourceRegistrar,
        attached: Transport | None,
        stopping: threading.Event,
        line: _EventLine,
    ) -> None:
        self.conn = conn
        self.control = control
        self.registrar = registrar
        self.attached = attached
        self.stopping = stopping
        self.line = line
        inbox = registrar._actor.ref.actor_inbox
        assert isinstance(inbox, Inbox)  # (a registrar actor's)
        self.inbox = inbox
        self.pinged = (0, 0)  # the last ping's number, and the handled count when it came

    def run(self) -> None:
        while True:
            try:
                message = self.conn.recv()
            except (EOFError, OSError):
                os._exit(PARENT_GONE_EXIT)  # the supervisor's process is gone: no orphans
            handler = _HANDLERS.get(type(message))
            if handler is None:
                logger.error("manager %s: unknown control message %r", self.registrar.name, message)
                continue
            handler(self, message)

    def trouble(self) -> tuple[float, str] | None:
        if self.attached is None:
            return None
        return self.attached.serving_trouble(self.registrar.name)

    def ping(self, message: Ping) -> None:
        """Answer through the registrar actor's mailbox: a hung actor sends no pong."""
        self.pinged = (message.number, self.inbox.handled)
        self.registrar._actor.ping(_Pong(self.control, message.number, self.trouble))

    def probe(self, message: Probe) -> None:
        """Answer at once: how far the registrar actor got through its mailbox (a busy
        one is not hung: `heartbeat.py`)."""
        inbox = self.inbox
        number, pinged = self.pinged
        handled = inbox.handled
        self.control.send(
            Progress(
                message.number,
                pinged if number == message.number else handled,
                handled,
                inbox.qsize(),
            )
        )

    def forward(self, message: Forward) -> None:
        self.line.switch(on=message.on)

    def peer_started(self, message: PeerStarted) -> None:
        """Every registrar of this process that monitors it hears it (a pool's managers too;
        its supervisor tells only what this process reported it monitors, `_Report`)."""
        MEMBERSHIP.started(message.name)

    def peers_stopped(self, message: PeersStopped) -> None:
        """Into this process's membership (every registrar here hears it before `Stop`)."""
        MEMBERSHIP.stopped_all(message.names, by="its supervisor (the tree's stop)")
        for name in message.lost:
            MEMBERSHIP.lost(name, by="its supervisor (the tree's stop)")

    def sync_events(self, message: SyncEvents) -> None:
        threading.Thread(
            target=self.line.sync,
            args=(self.control, message.token, message.timeout),
            name="rr-events-sync",
            daemon=True,
        ).start()

    def stop(self, message: Stop) -> None:
        """Exit within `message.timeout` seconds of reading it (its parent kills it that long
        after sending it): a pool's managers and its registrar stop by one deadline, a fifth
        earlier (1 s at most); its last events take half the rest, the pipe's delay the other."""
        registrar = self.registrar
        exit_by = time.monotonic() + message.timeout
        margin = min(message.timeout / 5, 1.0)
        self.stopping.set()
        if message.restarting:  # stopped to be restarted with its group:
            DIRECTORY.mark_restarting([registrar.name])  # no tombstone: "unavailable"
        code = STOPPED_EXIT
        before_stop = HOOKS.before_stop
        if before_stop is not None:  # a pool: its supervisor stops its managers first
            try:
                before_stop(_left(exit_by - margin), message.restarting)
            except Exception:
                logger.exception("manager %s: stopping its pool failed", registrar.name)
                code = 1
        try:
            registrar.stop(timeout=_left(exit_by - margin))
        except RrError:
            logger.exception("manager %s did not stop cleanly", registrar.name)
            code = 1
        self.line.flush(timeout=min(1.0, _left(exit_by - margin / 2)))  # its stop's unloads
        self.control.send(Stopped(code))  # (its supervisor may go on: only the exit is left)
        _exit(code, self.attached)


def _left(deadline: float) -> float:
    """Seconds left until `deadline` (monotonic), at least 1 ms (a stop's is never 0)."""
    return max(deadline - time.monotonic(), 1e-3)


_HANDLERS: dict[type[Any], Callable[[_ControlLoop, Any], None]] = {
    Ping: _ControlLoop.ping,
    Probe: _ControlLoop.probe,
    Forward: _ControlLoop.forward,
    SyncEvents: _ControlLoop.sync_events,
    Stop: _ControlLoop.stop,
    PeerStarted: _ControlLoop.peer_started,
    PeersStopped: _ControlLoop.peers_stopped,
}
