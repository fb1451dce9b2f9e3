"""The mission's hosts: the managers' trees by name, and the robot's host process.

Each host makes its network (`host_network`: Zenoh, mutual TLS with its certificate)
and its supervisor of managers (`managers_tree`) the same way; `open_two_hosts` is the
station's side of starting both hosts.

    the station (the mission's process)                   the robot's host process
    ───────────────────────────────────                   (python -m rr_actors_lab.mission.hosts,
    Trees: erm, rm ─► RobotHost ─┐                          inside the robot's namespace)
           cm      ─► Supervisor │ pickles over a socket-   main(): ZenohNetwork (mutual TLS)
                                 │ pair (not the network    + Supervisor(erm, rm) + watch
                                 └ under test: F6 does ───► child, wait_restarted, run_in,
                                   not cut it)              flush_events on its Supervisor
           say() ◄── "robot: ..." story lines, ChildExited / ChildRestarted events ──┘

`Trees` answers the mission's few questions of the managers' supervisors whichever host a
manager is on. The socket pair is the teacher's hand on the robot: only the registrars'
Zenoh traffic crosses the veth, and only it is cut. When the station's `mission`
registrar is gone from the robot's view (after the `lease`), the robot's host stops the
robot itself; the mission drives on once it loaded the robot again after the heal.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import itertools
import logging
import os
import pickle
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import Future
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Literal, Protocol

import rr_actors as rr
from rr_actors import _log
from rr_actors._supervision.retry import restart_after_failure
from rr_actors_lab.mission import managers, programs
from rr_actors_lab.mission.config import MissionConfig, MissionError
from rr_actors_lab.mission.netns import TwoHosts
from rr_actors_lab.mission.output import shown

__all__ = [
    "CERTS",
    "LOG_FORMAT",
    "MEMBERS",
    "PORT",
    "ROBOT_LOG",
    "ROBOT_MANAGERS",
    "SYSTEM",
    "RobotHost",
    "RobotObserver",
    "RobotSettings",
    "Tree",
    "Trees",
    "host_network",
    "log_file",
    "main",
    "managers_tree",
    "open_two_hosts",
]

ROBOT_MANAGERS = ("erm", "rm")
"""The managers on the robot's host (the rest, `cm`, runs on the station)."""

SYSTEM = "mission"
"""The system's name (`ZenohNetwork(system=)`, the CA's)."""

MEMBERS = ("robot", "station")
"""The member names: each host's certificate's common name."""

PORT = 7447
"""The Zenoh port each host listens on (its own address in its own namespace)."""

ROBOT_LOG = "rr-actors-robot.log"
"""The file in the output directory that the robot's host's WARNINGs and ERRORs go to."""

CERTS = "certs"
"""The folder in the output directory for the CA and the hosts' certificates."""

START_TIMEOUT = 60.0
"""Seconds the robot's host gets to start its managers (a loaded machine is slow)."""

STOP_TIMEOUT = 30.0
"""Seconds the robot's host gets to stop its managers before it is SIGKILLed."""

WATCH_TICK = 0.02
"""Seconds between two looks of the robot's host at whether it still sees the station."""

STATION_REGISTRAR = "mission"
"""The registrar whose presence tells the robot's host that the station is there."""


class Tree(Protocol):
    """What the mission asks of the supervisor of a manager (a `Supervisor`, a `RobotHost`)."""

    def child(self, name: str) -> rr.ChildInfo:
        """See `Supervisor.child`."""
        ...

    def wait_restarted(
        self, name: str, *, timeout: float, restarts: int | None = None
    ) -> rr.ChildInfo:
        """See `Supervisor.wait_restarted`."""
        ...

    def run_in(self, name: str, fn: Callable[[rr.ResourceRegistrar], Any]) -> Any:
        """See `Supervisor.run_in`."""
        ...

    def subscribe(self, callback: Callable[[rr.events.Event], object]) -> Any:
        """See `Supervisor.subscribe` (returns something with `close()`)."""
        ...

    def flush_events(self, *, timeout: float = 5.0) -> bool:
        """See `Supervisor.flush_events`."""
        ...


class Trees:
    """The managers' supervision trees by manager name, and the host each runs on.

    Args:
        of: the tree of each manager.
        host_of: the host of each manager (`"robot"`, `"station"`; one host: empty).
    """

    def __init__(self, of: dict[str, Tree], host_of: dict[str, str] | None = None) -> None:
        self.of = of
        self.host_of = host_of or {}

    def _distinct(self) -> list[Tree]:
        distinct: list[Tree] = []
        for tree in self.of.values():
            if all(tree is not seen for seen in distinct):
                distinct.append(tree)
        return distinct

    def child(self, name: str) -> rr.ChildInfo:
        """The snapshot of manager `name` (see `Supervisor.child`)."""
        return self.of[name].child(name)

    def wait_restarted(
        self, name: str, *, timeout: float, restarts: int | None = None
    ) -> rr.ChildInfo:
        """See `Supervisor.wait_restarted`."""
        return self.of[name].wait_restarted(name, timeout=timeout, restarts=restarts)

    def run_in(self, name: str, fn: Callable[[rr.ResourceRegistrar], Any]) -> Any:
        """Run `fn(registrar)` in manager `name` (see `Supervisor.run_in`)."""
        return self.of[name].run_in(name, fn)

    def subscribe(self, callback: Callable[[rr.events.Event], object]) -> contextlib.ExitStack:
        """Follow the events of every tree; close the returned stack to stop."""
        stack = contextlib.ExitStack()
        for tree in self._distinct():
            stack.callback(tree.subscribe(callback).close)
        return stack

    def flush_events(self) -> None:
        """Bring every tree's recent events here (see `Supervisor.flush_events`)."""
        for tree in self._distinct():
            tree.flush_events()

    def call_with_retry(
        self,
        app: rr.ResourceRegistrar,
        provider: str,
        server: str,
        request: Any,
        *,
        on_status: rr.StatusCallback,
        timeout: float,
    ) -> rr.Query:
        """`app.call(...)`, waiting out a restart of `provider` (as `Supervisor.call_with_retry`,
        one query id for every attempt).

        Raises:
            RegistrarUnavailableError, CallTimeoutError: as `Supervisor.call_with_retry`.
        """
        tree = self.of[provider]
        if isinstance(tree, rr.Supervisor):
            return tree.call_with_retry(
                app, provider, server, request, on_status=on_status, timeout=timeout
            )
        qid = str(uuid.uuid4())
        deadline = time.monotonic() + timeout
        tried_again_at = -1
        while True:
            before = tree.child(provider)
            try:
                return app.call(
                    provider,
                    server,
                    request,
                    on_status=on_status,
                    timeout=max(deadline - time.monotonic(), 1e-3),
                    query_id=qid,
                )
            except rr.RegistrarUnavailableError:
                if time.monotonic() >= deadline:
                    raise
            target = restart_after_failure(before, tree.child(provider), tried_again_at)
            if target == before.restarts:
                tried_again_at = target
            tree.wait_restarted(
                provider, timeout=max(deadline - time.monotonic(), 1e-3), restarts=target
            )


@dataclasses.dataclass(frozen=True)
class RobotObserver:
    """The robot's host shares its tree with the station's observer page (`--hosts 2 --observe`):
    its own page is on the robot's loopback, which no browser reaches.

    Attributes:
        allow_faults: the station's page may kill, hang and FATAL the robot's managers
            (`--allow-faults`).
    """

    allow_faults: bool = False


@dataclasses.dataclass(frozen=True)
class RobotSettings:
    """What the robot's host needs to start (sent to its process on the socket pair).

    Attributes:
        system: the system's name.
        certs: the directory of `ca.pem`, `robot.pem` and `robot.key`.
        listen: the robot's Zenoh endpoint.
        connect: the station's.
        lease: seconds after which a silent peer counts as gone.
        state: the robot's managers' state directory.
        bus: the programs' topics (the robot's host pauses the goal when it loses the station).
        isolation: the managers' isolation.
        log: the file the robot's host's WARNINGs and ERRORs go to.
        observer: share the robot's tree with the station's observer page (`None`: no).
        trace: make spans of the robot's tree there (`otel.Exporting`, inherited `OTEL_*`).
    """

    system: str
    certs: str
    listen: str
    connect: str
    lease: float
    state: str
    bus: str
    isolation: str
    log: str
    observer: RobotObserver | None = None
    trace: bool = False


class _Subscription:
    def __init__(self, host: RobotHost, callback: Callable[[rr.events.Event], object]) -> None:
        self._host = host
        self._callback = callback

    def close(self) -> None:
        with contextlib.suppress(ValueError):
            self._host.subscribers.remove(self._callback)


class RobotHost:
    """The station's handle on the robot's host process (see the module docstring).

    Make it with `RobotHost.start`; `close()` stops the robot's managers and the process. Its
    methods may be called from any thread. With the station's `network`, `wait_restarted`
    returns only once the station sees the manager served too (its token comes over the
    network, the news over the socket pair: a call in between would find nobody).

    Attributes:
        pid: the robot's host process.
        subscribers: callbacks of `subscribe` (called on this handle's reader thread).
    """

    def __init__(
        self,
        process: subprocess.Popen[bytes],
        conn: Connection,
        say: Callable[[str], None],
        network: rr.ZenohNetwork | None = None,
    ) -> None:
        self._process = process
        self._conn = conn
        self._say = say
        self._network = network
        self.pid = process.pid
        self.subscribers: list[Callable[[rr.events.Event], object]] = []
        self.on_watch: Callable[[str, float], object] = lambda _kind, _at: None
        """Called with `"lost"` or `"back"` and when (monotonic seconds) the robot's host
        saw the station go or come back (on this handle's reader thread)."""
        self._lock = threading.Lock()
        self._ids = itertools.count()
        self._waiting: dict[int, Future[Any]] = {}
        self._ready: Future[int] = Future()
        self._closed = False
        self._reader = threading.Thread(target=self._read, name="mission-robot-host", daemon=True)
        self._reader.start()

    @classmethod
    def start(
        cls,
        prefix: list[str],
        settings: RobotSettings,
        *,
        say: Callable[[str], None],
        network: rr.ZenohNetwork | None = None,
    ) -> RobotHost:
        """Start the robot's host (`prefix` puts it in the robot's namespace) and its managers.

        Args:
            prefix: the command that runs a program on the robot's host (`ip netns exec <ns>`).
            settings: what it starts.
            say: receives its story lines (on this handle's reader thread).
            network: the station's (`wait_restarted` waits until it sees the manager served).

        Raises:
            MissionError: it did not start (its error, or its output, is in the message).
        """
        ours, theirs = socket.socketpair()
        program = f"from rr_actors_lab.mission.hosts import main; main({theirs.fileno()})"
        command = [*prefix, sys.executable, "-c", program]
        try:
            process = subprocess.Popen(  # noqa: S603 - ip and this interpreter, no shell
                command, pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL
            )
        finally:
            theirs.close()
        conn = Connection(ours.detach())
        host = cls(process, conn, say, network)
        try:
            host._send(("start", settings))
            host._ready.result(timeout=START_TIMEOUT)
        except BaseException as exc:
            host.close()
            if isinstance(exc, MissionError | KeyboardInterrupt):
                raise
            raise MissionError(f"the robot's host did not start: {exc}") from exc
        return host

    def _send(self, message: Any) -> None:
        with self._lock:
            self._conn.send(message)

    def _read(self) -> None:
        """The reader thread: replies to their callers, events to subscribers, story lines."""
        try:
            while True:
                self._dispatch(self._conn.recv())
        except (EOFError, OSError):
            pass
        gone = MissionError("the robot's host process ended")
        if not self._ready.done():
            self._ready.set_exception(gone)
        for future in list(self._waiting.values()):
            if not future.done():
                future.set_exception(gone)
        self._waiting.clear()

    def _dispatch(self, message: tuple[Any, ...]) -> None:
        kind = message[0]
        if kind == "reply":
            _, call_id, ok, value = message
            future = self._waiting.pop(call_id, None)
            if future is None:
                return
            if ok:
                future.set_result(value)
            else:
                future.set_exception(value)
        elif kind == "event":
            for callback in list(self.subscribers):
                callback(message[1])
        elif kind == "say":
            self._say(message[1])
        elif kind == "watch":
            self.on_watch(message[1], message[2])
        elif kind == "ready":
            self._ready.set_result(message[1])
        elif kind == "failed":
            self._ready.set_exception(MissionError(f"the robot's host: {message[1]}"))

    def _call(self, method: str, *args: Any, timeout: float, **kwargs: Any) -> Any:
        call_id = next(self._ids)
        future: Future[Any] = Future()
        self._waiting[call_id] = future
        try:
            self._send(("call", call_id, method, args, kwargs))
        except OSError as exc:
            self._waiting.pop(call_id, None)
            raise MissionError("the robot's host process ended") from exc
        try:
            return future.result(timeout=timeout)
        except TimeoutError as exc:
            if isinstance(exc, rr.CallTimeoutError):  # its answer: a wait of the robot's
                raise  # supervisor's ran out (not a silence of its host)
            self._waiting.pop(call_id, None)
            raise rr.CallTimeoutError(f"the robot's host did not answer {method}") from None

    def child(self, name: str) -> rr.ChildInfo:
        """See `Supervisor.child` (of the robot's supervisor)."""
        info: rr.ChildInfo = self._call("child", name, timeout=10.0)
        return info

    def wait_restarted(
        self, name: str, *, timeout: float, restarts: int | None = None
    ) -> rr.ChildInfo:
        """See `Supervisor.wait_restarted` (of the robot's supervisor); with the station's
        network, it returns once the station sees `name` served too (see the class).

        Raises:
            CallTimeoutError: not restarted, or not seen served here, within `timeout`.
        """
        deadline = time.monotonic() + timeout
        info: rr.ChildInfo = self._call(
            "wait_restarted", name, timeout=timeout + 10.0, wait_s=timeout, restarts=restarts
        )
        if self._network is not None:
            try:
                self._network.wait_for(name, timeout=max(deadline - time.monotonic(), 0.0))
            except rr.RegistrarUnavailableError as exc:
                raise rr.CallTimeoutError(
                    f"{name} was restarted on the robot, but the station did not see it "
                    f"served within {timeout:g} s: {exc}"
                ) from exc
        return info

    def run_in(self, name: str, fn: Callable[[rr.ResourceRegistrar], Any]) -> Any:
        """See `Supervisor.run_in`; `fn` must pickle by reference (a module's function)."""
        return self._call("run_in", name, fn, timeout=20.0)

    def subscribe(self, callback: Callable[[rr.events.Event], object]) -> _Subscription:
        """Call `callback` with the robot's supervisor's `ChildExited` and `ChildRestarted`."""
        self.subscribers.append(callback)
        return _Subscription(self, callback)

    def flush_events(self, *, timeout: float = 5.0) -> bool:
        """See `Supervisor.flush_events` (events then reach this side in order)."""
        return bool(self._call("flush_events", timeout=timeout + 5.0, wait_s=timeout))

    def close(self) -> None:
        """Stop the robot's managers and its host process (SIGKILL after `STOP_TIMEOUT`)."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(OSError):
            self._send(("stop",))
        try:
            self._process.wait(STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        finally:
            self._conn.close()
            self._reader.join(5.0)


# -- the robot's host process ----------------------------------------------------------------


def host_network(
    certs: Path, member: str, *, system: str, listen: str, connect: str, lease: float
) -> rr.ZenohNetwork:
    """The Zenoh network of host `member` (`"robot"`, `"station"`): mutual TLS with its
    certificate in `certs` (`<member>.pem`, `<member>.key`, the CA's `ca.pem`)."""
    tls = rr.ZenohTLS(
        ca=certs / "ca.pem",
        cert=certs / f"{member}.pem",
        key=certs / f"{member}.key",
        members=list(MEMBERS),
    )
    return rr.ZenohNetwork(system=system, listen=[listen], connect=[connect], tls=tls, lease=lease)


LOG_FORMAT = "%(asctime)s %(name)s %(levelname)s %(message)s"
"""The format of the lines in the run's log files (each host's, and its managers')."""


def log_file(path: Path) -> logging.FileHandler:
    """A handler that appends rr_actors' WARNINGs and ERRORs to `path` (opened at the
    first line: no empty file). Appending, so that the host's process and its manager
    processes share the file without cutting each other's lines off."""
    handler = logging.FileHandler(path, mode="a", encoding="utf-8", delay=True)
    handler.setLevel(logging.WARNING)
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    return handler


def _logged_to(
    log: str, setup: Callable[[rr.ResourceRegistrar], None], registrar: rr.ResourceRegistrar
) -> None:
    """Run `setup`, with this process's rr_actors WARNINGs and ERRORs going to `log`
    (runs in the manager: in a manager process that configured no logging, the file
    stands in for rr_actors' own handler, which prints them on the terminal)."""
    if not _log.configured():
        logging.getLogger("rr_actors").addHandler(log_file(Path(log)))
    setup(registrar)


def _this_process_log() -> str | None:
    """The file this process's rr_actors WARNINGs go to (the run's log), if any."""
    for handler in logging.getLogger("rr_actors").handlers:
        if isinstance(handler, logging.FileHandler) and handler.level <= logging.WARNING:
            return handler.baseFilename
    return None


def managers_tree(
    names: tuple[str, ...],
    *,
    isolation: Literal["process", "thread"],
    state_dir: str | Path,
    network: rr.ZenohNetwork | None,
    name: str | None,
) -> rr.Supervisor:
    """A host's supervisor of the managers `names` (not started): one for one, permanent; its
    manager processes log where this process does (the story tells deliberate losses)."""
    setups = managers.setups()
    log = _this_process_log()
    specs = [
        rr.ManagerSpec(
            manager,
            setup=setups[manager]
            if log is None or isolation != "process"
            else functools.partial(_logged_to, log, setups[manager]),
            isolation=isolation,
            restart="permanent",
        )
        for manager in names
    ]
    return rr.Supervisor(
        specs,
        strategy="one_for_one",
        max_restarts=10,
        period=10.0,
        state_dir=state_dir,
        network=network,
        name=name,
    )


def open_two_hosts(
    link: TwoHosts,
    config: MissionConfig,
    out: Path,
    *,
    state: Path,
    bus: Path,
    robot_observer: RobotObserver | None,
    say: Callable[[str], None],
    stack: contextlib.ExitStack,
    trace: bool = False,
) -> tuple[rr.ZenohNetwork, RobotHost]:
    """The station's side: start the robot's host (erm, rm), open the station's network; both
    closed by `stack` (the robot's host first).

    Args:
        link: the two hosts' namespaces (this process runs in the station's).
        config: the mission (its `lease` and `isolation`).
        out: the output directory (the certificates, the robot's log).
        state: the managers' state directories (`robot/` for the robot's).
        bus: the programs' topics.
        robot_observer: share the robot's tree with the station's page, or `None`.
        say: tells one line of the story (also from the robot host's reader thread).
        stack: where the closing goes.
        trace: the robot's host makes spans of its tree (`RobotSettings.trace`).

    Raises:
        MissionError: the robot's host did not start.
    """
    certs = out / CERTS
    say(
        f"two hosts: the robot ({link.robot_address}: erm, rm and their programs) and the "
        f"station ({link.station_address}: the mission and cm), mutual TLS ({shown(certs)})"
    )
    network = host_network(
        certs,
        "station",
        system=SYSTEM,
        listen=f"tls/{link.station_address}:{PORT}",
        connect=f"tls/{link.robot_address}:{PORT}",
        lease=config.lease,
    )
    stack.callback(network.close)
    robot = RobotHost.start(
        link.exec_in(link.robot),
        RobotSettings(
            system=SYSTEM,
            certs=str(certs),
            listen=f"tls/{link.robot_address}:{PORT}",
            connect=f"tls/{link.station_address}:{PORT}",
            lease=config.lease,
            state=str(state / "robot"),
            bus=str(bus),
            isolation=config.isolation,
            log=str(out / ROBOT_LOG),
            observer=robot_observer,
            trace=trace,
        ),
        say=say,
        network=network,
    )
    stack.callback(robot.close)
    say(f"robot's host up (pid {robot.pid}): erm and rm started there")
    return network, robot


def _watch_station(
    net: rr.ZenohNetwork, bus: Path, stop: threading.Event, send: Callable[[Any], None]
) -> None:
    """Stop the robot when the station is gone from view; say when it is back."""
    seen = lost = False
    while not stop.wait(WATCH_TICK):
        present = STATION_REGISTRAR in net.names()
        if present and lost:
            lost = False
            send(("watch", "back", time.monotonic()))
            send(("say", "robot: the station is back (its registrars are served again)"))
        elif not present and seen and not lost and not stop.is_set():
            lost = True
            goal = programs.read_topic(bus, "goal") or {}
            programs.publish(bus, "goal", {**goal, "paused": True})
            send(("watch", "lost", time.monotonic()))
            send(("say", "robot: the station is gone (its lease ran out); the robot stops itself"))
        seen = seen or present


def _serve(sup: rr.Supervisor, conn: Connection, send: Callable[[Any], None]) -> None:
    """Answer the station's calls (each on a thread of its own: some wait) until `stop`."""

    def answer(call_id: int, method: str, args: tuple[Any, ...], kwargs: dict[str, Any]) -> None:
        try:
            if method == "wait_restarted":
                value: Any = sup.wait_restarted(
                    args[0], timeout=kwargs["wait_s"], restarts=kwargs["restarts"]
                )
            elif method == "flush_events":
                value = sup.flush_events(timeout=kwargs["wait_s"])
            else:
                value = getattr(sup, method)(*args)
            pickle.dumps(value)
            send(("reply", call_id, True, value))
        except Exception as exc:  # noqa: BLE001 - handed to the caller, whatever it is
            try:
                pickle.dumps(exc)
            except Exception:  # noqa: BLE001 - an exception that does not pickle: its text
                exc = MissionError(f"{exc.__class__.__name__}: {exc}")
            send(("reply", call_id, False, exc))

    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        if message[0] == "stop":
            return
        threading.Thread(target=answer, args=message[1:], daemon=True).start()


def main(fd: int) -> None:
    """The robot's host: start its managers, answer the station until it says stop."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the station stops it (a terminal's Ctrl-C)

    conn = Connection(fd)
    lock = threading.Lock()

    def send(message: Any) -> None:
        with lock, contextlib.suppress(OSError):
            conn.send(message)

    _, settings = conn.recv()
    assert isinstance(settings, RobotSettings)
    Path(settings.log).unlink(missing_ok=True)  # (this run's lines only)
    logging.getLogger("rr_actors").addHandler(log_file(Path(settings.log)))  # (the story
    # says what matters; its manager processes' lines go there too: `managers_tree`)
    try:
        net = host_network(
            Path(settings.certs),
            "robot",
            system=settings.system,
            listen=settings.listen,
            connect=settings.connect,
            lease=settings.lease,
        )
        sup = managers_tree(
            ROBOT_MANAGERS,
            isolation=settings.isolation,  # type: ignore[arg-type]
            state_dir=settings.state,
            network=net,
            name="robot",
        )
    except Exception as exc:  # noqa: BLE001 - told to the station, which fails the mission
        send(("failed", f"{exc.__class__.__name__}: {exc}"))
        return
    stop = threading.Event()

    def on_event(event: rr.events.Event) -> None:
        if isinstance(event, rr.events.ChildExited | rr.events.ChildRestarted):
            send(("event", event))

    watch = threading.Thread(
        target=_watch_station,
        args=(net, Path(settings.bus), stop, send),
        name="robot-watch",
        daemon=True,
    )
    with net, contextlib.ExitStack() as stack:  # (the stack first: the observer, then net)
        try:
            sup.subscribe(on_event)
            if settings.trace:  # its spans exported once its tree stopped
                from rr_actors_lab import otel  # noqa: PLC0415 - only --trace needs it

                exporting = otel.Exporting()
                exporting.trace(sup)
                stack.callback(exporting.close)
            if settings.observer is not None:  # (before the start: the page sees it start)
                from rr_actors_lab.observe import observe  # noqa: PLC0415 - its extra's

                observer = observe(
                    sup,
                    allow_faults=settings.observer.allow_faults,
                    across_hosts=True,
                    keep_serving=True,  # (its final state is shared as it stops)
                )
                stack.callback(observer.close)  # (after the stop, before the network goes)
            sup.start()
        except Exception as exc:  # noqa: BLE001 - as above
            send(("failed", f"{exc.__class__.__name__}: {exc}"))
            with contextlib.suppress(Exception):
                sup.stop()
            return
        try:
            watch.start()
            send(("ready", os.getpid()))
            _serve(sup, conn, send)
        finally:
            stop.set()
            watch.join(5.0)
            sup.stop()
    send(("stopped", None))
