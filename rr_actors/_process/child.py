"""The child's side of a manager process: `main`, `standby` and the control loop.

Runs only in manager processes (never in the supervisor's process). In the child, `main`:

1. asks the platform to end it when the process that forked it dies
   (`Platform.die_with_parent`: with the forkserver context that is the forkserver, not
   the supervisor's process) and names the process for `ps` (`rr-actors: <name>`),
2. attaches to the system and starts the registrar, which restores its catalog,
3. runs the (cloudpickled) `setup(registrar)`, then serves the registrar on the system,
4. reports `ready` over its control pipe and answers control requests: `stop`, `ping`
   (the heartbeat, answered through the registrar actor's mailbox, with how long its
   listener has been unable to accept connections, if it has) and `events` (whether to
   forward the registrar's events: only while the supervisor's process has listeners),
5. exits at once when the control pipe reaches EOF: the supervisor's process is gone,
6. exits with code 0 when its registrar was stopped cleanly by code in the manager (a
   `transient` manager is then not restarted, as in a thread), with code 71 when the
   registrar actor died.

```
 parent (ManagerProcess)            control pipe                child (this module)
   start ─────────── ("start", setup, config, address) ───────►  standby (a spare only)
         ◄──────────────── ("warm",)  (a spare, once warmed up)
         ◄──────────────── ("ready", pid) | ("failed", traceback)
   ping  ─────────────────── ("ping", n) ──────────────────────►  registrar mailbox
         ◄──────────────── ("pong", n, trouble)  (None, or (seconds, why) it cannot accept)
   events ───────────────── ("events", on) ────────────────────►  forward events or not
         ◄──────────────── ("events", [event, ...])  (batches, while on)
   sync  ─────────────────── ("events-sync", n, timeout) ──────►  send what is buffered
         ◄──────────────── ("events-synced", n)  (after those batches)
   stop  ─────────────────── ("stop", timeout, restarting) ────►  registrar.stop(); exit 0
   (EOF: the parent is gone) ──────────────────────────────────►  exit 70
```

Running a function against the registrar (`Supervisor.run_in`) goes over the system's
transport (`AttachedSystem.run`), not over the control pipe.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import threading
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import cloudpickle

from rr_actors import events
from rr_actors._core.bus import Forwarder, Publisher
from rr_actors._core.directory import DIRECTORY
from rr_actors._platform import PLATFORM
from rr_actors._process.context import (
    ACTOR_DIED_EXIT,
    PARENT_GONE_EXIT,
    TITLE_PREFIX,
    stopped_cleanly,
)
from rr_actors.config import RegistrarConfig
from rr_actors.errors import RrError

__all__ = ["main", "set_title", "standby"]

logger = logging.getLogger("rr_actors")


def set_title(name: str) -> None:
    """Name this process after its manager for `ps`, `top` and `pstree`.

    The kernel's 15-byte process name (`ps -o comm`, `top`; Linux's `prctl(PR_SET_NAME)`)
    becomes the name itself, which a prefix would crowd out. With the `setproctitle`
    package installed (extra `title`) the command line becomes `rr-actors: <name>` too
    (`ps aux`).
    """
    try:
        import setproctitle  # noqa: PLC0415 - optional; preloaded by the forkserver
    except ImportError:
        pass
    else:
        setproctitle.setproctitle(f"{TITLE_PREFIX}{name}")
    PLATFORM.set_process_name(name)  # after setproctitle, which may set it to the title


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
    """A reply that answers a heartbeat ping once the registrar actor got to it.

    The answer carries how long (and why) the registrar's listener has been unable to
    accept connections, if it has: a manager that can no longer accept is as useless to
    new peers as a hung one, and its supervisor judges both by the same bound.
    """

    def __init__(self, control: _Control, number: int, trouble: Callable[[], Any]) -> None:
        self.control = control
        self.number = number
        self.trouble = trouble

    def set_result(self, _: Any) -> None:
        self.control.send(("pong", self.number, self.trouble()))

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
    forward: bool = False,
) -> None:
    """Run one manager: restore, set up, serve, then answer control requests until stopped.

    Runs as the target of a manager process (never in the supervisor's process).

    Args:
        setup: `cloudpickle.dumps(setup_function_or_None)`.
        config: the registrar's configuration (its backup is restored before `setup`).
        address: the system's `SystemAddress`, or `None` to run unattached.
        conn: the child's end of the control pipe.
        parent: the pid of the process that forked this one (`Platform.die_with_parent`).
        forward: forward the registrar's events from the start (until told otherwise).
    """
    PLATFORM.die_with_parent(parent)
    set_title(config.name)
    _run_manager(setup, config, address, conn, forward)


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

    Runs as the target of a spare manager process (see `rr_actors._process.spare`): the
    interpreter start, the forkserver's fork and the child's bootstrap are paid before a
    manager crashes, not after. It warms up (unless it was handed a manager already),
    says `("warm",)`, and exits when the control pipe reaches EOF unused.

    Args:
        conn: the child's end of the control pipe; the first message is
            `("start", setup, config, address, forward)` with `main`'s arguments.
        parent: the pid of the process that forked this one (`Platform.die_with_parent`).
    """
    PLATFORM.die_with_parent(parent)
    set_title("spare")
    try:
        if not conn.poll(0):  # taken already: the warm-up would only delay the manager
            _warm_up()
            conn.send(("warm",))
        message = conn.recv()
    except (EOFError, OSError):
        os._exit(0)  # released unused, or the parent is gone
    if message[0] != "start":
        os._exit(0)
    _, setup, config, address, forward = message
    set_title(config.name)
    _run_manager(setup, config, address, conn, forward)


class _EventLine:
    """Forwards this process's registrar events to the supervisor's process while asked to.

    The registrar relays its events to `hub`; while forwarding is on, `hub`'s one sink is a
    `Forwarder` that sends batches over the control pipe (its own thread), so the
    registrar is `active` (builds events) only then.
    """

    def __init__(self, control: _Control, name: str, *, on: bool) -> None:
        self.hub: Publisher[events.Event] = events.publisher()
        self.forwarder: Forwarder[events.Event] = Forwarder(
            lambda batch: control.send(("events", batch)),
            notice=events.EventsDropped,
            name=f"{name}-events",
        )
        self.on = False
        self.switch(on=on)

    def switch(self, *, on: bool) -> None:
        """Forward from now on, or stop forwarding (control loop thread)."""
        if on and not self.on:
            self.hub.add_sink(self.forwarder)
        elif self.on and not on:
            self.hub.remove_sink(self.forwarder)
        self.on = on

    def flush(self, timeout: float) -> None:
        """Send what is buffered (before a clean exit)."""
        self.forwarder.close(timeout=timeout)

    def sync(self, control: _Control, token: int, timeout: float) -> None:
        """Send what is buffered, then `("events-synced", token)` after it (own thread)."""
        self.forwarder.wait_sent(timeout=timeout)
        control.send(("events-synced", token))


def _run_manager(
    setup: bytes, config: RegistrarConfig, address: Any, conn: Connection, forward: bool
) -> None:
    from rr_actors._registrar import Served, start_registrar  # noqa: PLC0415 - preloaded

    control = _Control(conn)
    line = _EventLine(control, config.name, on=forward)
    attached: Any = None
    try:
        if address is not None:
            attached = address.attach()
        registrar = start_registrar(config, upstream=line.hub)
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
        registrar._wait_stopped()
        if stopping.is_set():
            return  # the supervisor's `stop`: the control loop exits
        if stopped_cleanly(registrar.name):  # code in the manager called registrar.stop()
            _exit(0, attached)
        _exit(ACTOR_DIED_EXIT, attached)

    threading.Thread(target=watch_actor, name="rr-manager-actor-watch", daemon=True).start()
    control.send(("ready", os.getpid()))
    _serve_control(conn, control, registrar, attached, stopping, line)


def _serve_control(
    conn: Connection,
    control: _Control,
    registrar: Any,
    attached: Any,
    stopping: threading.Event,
    line: _EventLine,
) -> None:
    """The child's control loop: answer pings, forward events or not, stop; exit on EOF."""

    def trouble() -> tuple[float, str] | None:
        if attached is None:
            return None
        found: tuple[float, str] | None = attached.serving_trouble(registrar.name)
        return found

    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            os._exit(PARENT_GONE_EXIT)  # the supervisor's process is gone: no orphans
        kind = message[0]
        if kind == "ping":
            registrar._ping(_Pong(control, message[1], trouble))
        elif kind == "events":
            line.switch(on=bool(message[1]))
        elif kind == "events-sync":  # (a thread: the loop keeps answering pings)
            threading.Thread(
                target=line.sync, args=(control, *message[1:3]), name="rr-events-sync", daemon=True
            ).start()
        elif kind == "stop":
            stopping.set()
            if len(message) > 2 and message[2]:  # stopped to be restarted with its group:
                DIRECTORY.restarting.add(registrar.name)  # no tombstone, peers see "unavailable"
            code = 0
            try:
                registrar.stop(timeout=message[1])
            except RrError:
                logger.exception("manager %s did not stop cleanly", registrar.name)
                code = 1
            line.flush(timeout=1.0)  # its last events (the unloads of its stop) go too
            _exit(code, attached)
