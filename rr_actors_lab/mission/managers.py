"""The mission's three managers, as `setup(registrar)` functions (thesis chapter 6.1).

- [`erm_setup`][rr_actors_lab.mission.managers.erm_setup]: the *external resource manager*.
  Its server `program` starts one of the robot's programs as an OS process per distinct
  request, watches it through a pidfd and sends `FATAL` to every consumer when it dies.
  After a restart it re-adopts the processes its restored catalog names (pid *and*
  creation time checked: a reused pid cannot fool it).
- [`cm_setup`][rr_actors_lab.mission.managers.cm_setup]: the *component manager*: its server
  `lidar` builds a LiDAR component from an ERM process (a dependency).
- [`rm_setup`][rr_actors_lab.mission.managers.rm_setup]: the *robot manager*: its server
  `robot` loads a motor driver and a navigation process from the ERM; when the driver
  dies, it restarts it itself and sends `UPDATE` to the robot's consumers.

Each runs unchanged in a thread or in a manager process of its own; they keep no state
the catalog does not hold, so a restarted manager picks up where the killed one was.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import logging
import os
import selectors
import signal
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import rr_actors as rr
from rr_actors._core import traces
from rr_actors_lab.mission import programs

__all__ = ["ProcessTable", "cm_setup", "erm_setup", "rm_setup"]

logger = logging.getLogger("rr_actors.mission")

PROGRAM_SERVER = "program"
"""Name of the ERM's resource server that runs programs."""

READY_TIMEOUT = 10.0
"""Seconds a program gets to report that it is up before its load fails."""

STOP_GRACE = 2.0
"""Seconds a program gets to exit after SIGTERM before it is killed."""


def program_request(
    program: str,
    name: str,
    bus: str,
    *,
    watch_pid: int | None,
    **options: float | int,
) -> dict[str, Any]:
    """The request for the ERM's `program` server: run `program` as instance `name`.

    Args:
        program: `"lidar"`, `"driver"` or `"navigation"` (see `rr_actors_lab.mission.programs`).
        name: instance name (two LiDARs are two instances of one program).
        bus: the topic directory the program reads and writes.
        watch_pid: the program exits when this process dies (the mission's main process).
        **options: further command-line options, e.g. `rate=20.0` for `--rate 20.0`.

    Returns:
        A plain dict; equal dicts mean the same process (dedup).
    """
    return {
        "program": program,
        "name": name,
        "bus": bus,
        "watch_pid": watch_pid,
        "options": dict(sorted(options.items())),
    }


def _argv(request: dict[str, Any]) -> list[str]:
    argv = [
        sys.executable,
        str(Path(programs.__file__)),
        request["program"],
        "--bus",
        request["bus"],
        "--name",
        request["name"],
    ]
    if request.get("watch_pid") is not None:
        argv += ["--watch-pid", str(request["watch_pid"])]
    for key, value in request["options"].items():
        argv += [f"--{key.replace('_', '-')}", str(value)]
    return argv


@dataclasses.dataclass
class _Watched:
    """One running program the ERM watches."""

    response: dict[str, Any]
    pidfd: int | None
    popen: subprocess.Popen[bytes] | None  # None for a process re-adopted after a restart
    expected: bool = False  # set by `unload`: its exit is not a failure
    exited: threading.Event = dataclasses.field(default_factory=threading.Event)


class ProcessTable:
    """The ERM's running programs: start, watch (a thread in `select` on each pidfd, re-adopted
    ones too), stop and re-adopt them; signals go through the pidfd, never a reused pid."""

    def __init__(self, registrar: rr.ResourceRegistrar, server: str = PROGRAM_SERVER) -> None:
        self.registrar = registrar
        self.server = server
        self._lock = threading.Lock()
        self._watched: dict[tuple[int, int], _Watched] = {}

    # -- the resource server's callbacks ----------------------------------------------

    def load(self, request: dict[str, Any]) -> dict[str, Any]:
        """Start the program; return `{"program", "name", "pid", "start_time"}` once it is up.

        Runs on a worker thread of the ERM. Raises `RuntimeError` (the caller gets a
        `ResourceLoadError`) if the program exits or stays silent before it is ready.
        """
        logs = Path(request["bus"]) / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        ready_r, ready_w = os.pipe()
        try:
            with (logs / f"{request['name']}.log").open("ab") as log:
                popen = subprocess.Popen(  # noqa: S603 - our own program, argv from a request
                    [*_argv(request), "--ready-fd", str(ready_w)],
                    pass_fds=(ready_w,),
                    stdin=subprocess.DEVNULL,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    start_new_session=True,  # a Ctrl-C in the terminal is the mission's to handle
                )
            os.close(ready_w)
            ready_w = -1
            with selectors.DefaultSelector() as selector:  # (not select(): fds of 1024 and up)
                selector.register(ready_r, selectors.EVENT_READ)
                readable = selector.select(READY_TIMEOUT)
            ready = bool(readable) and os.read(ready_r, 1) == b"R"
        finally:
            os.close(ready_r)
            if ready_w >= 0:
                os.close(ready_w)
        pidfd = os.pidfd_open(popen.pid)  # still our unreaped child: the pid is not reused
        created = programs.start_time(popen.pid)
        if not ready or created is None:
            signal.pidfd_send_signal(pidfd, signal.SIGKILL)
            code = popen.wait()
            os.close(pidfd)
            raise RuntimeError(f"{request['name']} did not start (exit code {code})")
        response = {
            "program": request["program"],
            "name": request["name"],
            "pid": popen.pid,
            "start_time": created,
        }
        self._watch(_Watched(response, pidfd, popen))
        logger.info("started %s (pid %d)", request["name"], popen.pid)
        return response

    def unload(self, request: dict[str, Any], response: dict[str, Any]) -> None:
        """Stop the program: SIGTERM, then SIGKILL after `STOP_GRACE` seconds.

        Runs on a worker thread of the ERM; returns once the process has exited. A process
        that had already died (and was reported `FATAL`) needs nothing more.
        """
        with self._lock:
            watched = self._watched.get((response["pid"], response["start_time"]))
            if watched is None:
                return
            watched.expected = True
            self._signal(watched, signal.SIGTERM)
        if not watched.exited.wait(STOP_GRACE):
            with self._lock:
                self._signal(watched, signal.SIGKILL)
            watched.exited.wait(STOP_GRACE)
        logger.info("stopped %s (pid %d)", request["name"], response["pid"])

    # -- after a restart --------------------------------------------------------------

    def adopt(self, queries: list[rr.Query]) -> list[rr.Query]:
        """Watch again the processes that restored `queries` name; return those that died.

        A process counts as the same only if both its pid and its creation time match
        what was recorded when it was started.
        """
        dead: dict[tuple[int, int], rr.Query] = {}
        seen: set[tuple[int, int]] = set()
        for query in queries:
            response = query.response
            key = (response["pid"], response["start_time"])
            if key in seen or key in dead:
                continue
            try:
                pidfd = os.pidfd_open(response["pid"])
            except ProcessLookupError:
                dead[key] = query
                continue
            if programs.start_time(response["pid"]) != response["start_time"]:
                os.close(pidfd)  # a zombie, or another process that got the pid
                dead[key] = query
                continue
            seen.add(key)
            self._watch(_Watched(dict(response), pidfd, None))
            logger.info("re-adopted %s (pid %d)", response["name"], response["pid"])
        return list(dead.values())

    def stop_strays(self, in_doubt: tuple[rr.Query, ...]) -> None:
        """Stop programs whose load a crash cut short (found from their pid files)."""
        for query in in_doubt:
            request = query.request
            pids = Path(request["bus"]) / "pids"
            for path in pids.glob("*.json"):
                with contextlib.suppress(OSError, ValueError, KeyError):
                    record = json.loads(path.read_text())
                    known = (record["pid"], record["start_time"]) in self._watched
                    if record["name"] == request["name"] and not known:
                        _kill_if_same(record["pid"], record["start_time"])

    # -- plumbing ---------------------------------------------------------------------

    def _watch(self, watched: _Watched) -> None:
        key = (watched.response["pid"], watched.response["start_time"])
        with self._lock:
            self._watched[key] = watched
        threading.Thread(
            target=self._watcher,
            args=(key, watched),
            name=f"erm-watch-{key[0]}",
            daemon=True,
        ).start()

    def _watcher(self, key: tuple[int, int], watched: _Watched) -> None:
        assert watched.pidfd is not None
        with selectors.DefaultSelector() as selector:  # (not select(): fds of 1024 and up)
            selector.register(watched.pidfd, selectors.EVENT_READ)
            selector.select()  # readable when the process has exited
        code = watched.popen.wait() if watched.popen is not None else None
        with self._lock:
            os.close(watched.pidfd)
            watched.pidfd = None
            self._watched.pop(key, None)
            expected = watched.expected
        watched.exited.set()
        if not expected:
            how = "was killed" if code is not None and code < 0 else f"exited ({code})"
            if code is None:
                how = "exited"
            self.report_death(watched.response, f"{watched.response['name']} {how}")

    def report_death(self, response: dict[str, Any], message: str) -> None:
        """Send `FATAL` about the process in `response` to every consumer of it."""
        try:
            for query in self.registrar.server_queries(self.server):
                if query.response == response:
                    self.registrar.send_status(query.id, rr.Status.FATAL, message)
                    return
        except rr.RrError as exc:  # the registrar stopped or died meanwhile
            logger.warning("could not report that %s: %s", message, exc)

    @staticmethod
    def _signal(watched: _Watched, signum: int) -> None:
        """Signal through the pidfd (under the table's lock, so the fd is still open)."""
        if watched.pidfd is not None:
            with contextlib.suppress(ProcessLookupError):
                signal.pidfd_send_signal(watched.pidfd, signum)


def _kill_if_same(pid: int, created: int) -> None:
    """SIGKILL process `pid` if it is still the one created at `created`."""
    try:
        pidfd = os.pidfd_open(pid)
    except ProcessLookupError:
        return
    try:
        if programs.start_time(pid) == created:
            signal.pidfd_send_signal(pidfd, signal.SIGKILL)
    finally:
        os.close(pidfd)


def _named(key: str) -> Callable[[dict[str, Any]], str]:
    """A server's `label=`: the observer names each resource by its request's `key`."""

    def label(request: dict[str, Any]) -> str:
        return str(request[key])

    return label


def erm_setup(registrar: rr.ResourceRegistrar) -> None:
    """Set up the external resource manager: server `program`, then re-adopt.

    Runs in the ERM (its thread or process) after its catalog was restored. Processes
    that died while the ERM was down are reported `FATAL` to their consumers from a
    background thread, once setup has returned and the ERM serves again.
    """
    table = ProcessTable(registrar)
    registrar.register_server(
        PROGRAM_SERVER, load=table.load, unload=table.unload, label=_named("name")
    )
    table.stop_strays(registrar.in_doubt)
    dead = table.adopt(registrar.server_queries(PROGRAM_SERVER))
    if dead:

        def report() -> None:
            for query in dead:
                table.report_death(query.response, f"{query.response['name']} died meanwhile")

        threading.Thread(target=report, name="erm-report-dead", daemon=True).start()


def cm_setup(registrar: rr.ResourceRegistrar, *, erm: str = "erm") -> None:
    """Set up the component manager: server `lidar`, a LiDAR component from an ERM process.

    Request: `{"name": "lidar1", "bus": DIR, "watch_pid": PID, "rate": HZ, "seed": N}`.
    Response: `{"lidar", "pid", "start_time"}` of its process. The process is a dependency
    of the component, so unloading the component stops it, and its `FATAL` reaches the
    component's consumers.
    """

    def load(request: dict[str, Any]) -> dict[str, Any]:
        process = registrar.call(
            erm,
            PROGRAM_SERVER,
            program_request(
                "lidar",
                request["name"],
                request["bus"],
                watch_pid=request.get("watch_pid"),
                rate=request["rate"],
                seed=request["seed"],
            ),
        )
        return {
            "lidar": request["name"],
            "pid": process.response["pid"],
            "start_time": process.response["start_time"],
        }

    def unload(request: dict[str, Any], response: dict[str, Any]) -> None:
        """Nothing to do: the LiDAR process (a dependency) was released just before."""

    registrar.register_server("lidar", load=load, unload=unload, label=_named("name"))


@dataclasses.dataclass
class _RobotManager:
    registrar: rr.ResourceRegistrar
    erm: str

    def load(self, request: dict[str, Any]) -> dict[str, Any]:
        bus, watch = request["bus"], request.get("watch_pid")
        driver = self.registrar.call(
            self.erm,
            PROGRAM_SERVER,
            program_request(
                "driver",
                f"{request['robot']}-driver",
                bus,
                watch_pid=watch,
                rate=request["driver_rate"],
                cmd_timeout=request["cmd_timeout"],
            ),
            on_status=self.on_driver_status,
        )
        navigation = self.registrar.call(
            self.erm,
            PROGRAM_SERVER,
            program_request(
                "navigation",
                f"{request['robot']}-navigation",
                bus,
                watch_pid=watch,
                rate=request["nav_rate"],
                scan_timeout=request["scan_timeout"],
            ),
        )
        return {
            "robot": request["robot"],
            "driver_query": driver.id,
            "driver_pid": driver.response["pid"],
            "driver_start_time": driver.response["start_time"],
            "navigation_pid": navigation.response["pid"],
        }

    def unload(self, request: dict[str, Any], response: dict[str, Any]) -> None:
        # The first driver and the navigation were dependencies and are released already;
        # a driver this manager restarted is its own query, released here.
        with contextlib.suppress(rr.UnknownQueryError):
            self.registrar.unload(response["driver_query"])

    def on_driver_status(self, query: rr.Query, update: rr.StatusUpdate) -> None:
        """Client status callback of a driver query: restart a driver that died."""
        if update.status is rr.Status.FATAL:
            # (a thread starts with no trace context: it carries the callback's, so that
            # the restart's calls are in the trace of the callback's run, `--trace`)
            traced = traces.current()
            threading.Thread(
                target=self.restart_driver,
                args=(query, traced),
                name="rm-restart-driver",
                daemon=True,
            ).start()

    def restart_driver(self, dead: rr.Query, traced: str = "") -> None:
        """Release the dead driver, start a new one, tell the robot's consumers (`UPDATE`);
        under the span `traced` names (the status callback's run), if any."""
        traces.adopt(traced)
        try:
            with contextlib.suppress(rr.UnknownQueryError):
                self.registrar.unload(dead.id)
            new = self.registrar.call(
                self.erm, PROGRAM_SERVER, dead.request, on_status=self.on_driver_status
            )
            for robot in self.registrar.server_queries("robot"):
                if robot.response["driver_query"] == dead.id:
                    self.registrar.update_response(
                        robot.id,
                        {
                            **robot.response,
                            "driver_query": new.id,
                            "driver_pid": new.response["pid"],
                            "driver_start_time": new.response["start_time"],
                        },
                    )
                    self.registrar.send_status(
                        robot.id,
                        rr.Status.UPDATE,
                        f"motor driver restarted (pid {new.response['pid']})",
                    )
                    return
            self.registrar.unload(new.id)  # the robot was unloaded meanwhile
        except rr.RrError:
            logger.exception("restarting the motor driver failed")

    def reattach(self) -> None:
        """After a restart: status callbacks are code, not catalog data; attach them again."""
        for query in self.registrar.client_queries():
            if query.serving_rr == self.erm and query.request.get("program") == "driver":
                self.registrar.set_status_callback(query.id, self.on_driver_status)


def rm_setup(registrar: rr.ResourceRegistrar, *, erm: str = "erm") -> None:
    """Set up the robot manager: server `robot` (a motor driver and a navigation process).

    Request: `{"robot", "bus", "watch_pid", "driver_rate", "nav_rate", "cmd_timeout",
    "scan_timeout"}`. Response: `{"robot", "driver_query", "driver_pid",
    "driver_start_time", "navigation_pid"}`; `update_response` changes it when the driver
    is restarted.
    """
    manager = _RobotManager(registrar, erm)
    registrar.register_server(
        "robot", load=manager.load, unload=manager.unload, label=_named("robot")
    )
    manager.reattach()


def setups(*, erm: str = "erm") -> dict[str, Callable[[rr.ResourceRegistrar], None]]:
    """The three setup functions, with the consumers pointed at the ERM named `erm`."""
    return {
        "erm": erm_setup,
        "cm": functools.partial(cm_setup, erm=erm),
        "rm": functools.partial(rm_setup, erm=erm),
    }
