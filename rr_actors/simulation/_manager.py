"""Manager processes in a simulation: what `ManagerProcess.start` starts while one runs.

```
 supervisor's task (its process)                       the manager's simulated process
   ManagerProcess.start ─► runtime.manager_process ─► start(): Scheduler.new_process,
                                                      its main task (`_child`):
                                                        attach (its own membership)
                                                        start_registrar: restore the backup
                                                        setup(registrar); settle in doubt
                                                        serve it on the network
        ◄── Ready(pid) | Failed(traceback, corrupt) | its end ── from_child (a simulated queue)
   watcher task (`_watch`)                              control loop (`_child`)
        ── Ping(n) every `heartbeat` s ────────────────► registrar mailbox ─► Pong(n)
        a silence past the bound: Hang ─► kill
        ── Stop(timeout, restarting) ────────► registrar.stop(); exit STOPPED_EXIT (1)
        ◄── Events([event]) while Forward(on) ────────── its registrar's events
        the end (`Scheduler.end`: a kill, an exit) ◄──── at_end: what it served is cut off,
                                                          then at_reaped: `_Ended`
        ──► on_exit(ManagerExit) ─► the supervisor's mailbox (the real `_supervision`)
```

The handle is a real `ManagerProcess` on a simulated queue instead of a pipe
(docs/explanation/simulation.md). Unlike a real manager process, the events of its start
go before `Ready` (no rule depends on that order, and each seed keeps its history).
"""

from __future__ import annotations

import functools
import itertools
import logging
import signal
import traceback
from collections.abc import Callable
from typing import Any, cast

import cloudpickle

from rr_actors import events
from rr_actors._core import runtime
from rr_actors._core.bus import Publisher
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._process.control import (
    ACTOR_DIED_EXIT,
    STOPPED_EXIT,
    Events,
    EventsSynced,
    Failed,
    Forward,
    FromParent,
    PeersStopped,
    PeerStarted,
    Ping,
    Pong,
    Ready,
    Stop,
    SyncEvents,
    stopped_cleanly,
)
from rr_actors._process.hearers import HEARERS
from rr_actors._process.heartbeat import Hang, Heartbeat
from rr_actors._process.manager import ManagerExit, ManagerProcess, describe
from rr_actors._process.tally import Received
from rr_actors._registrar import Served, start_registrar
from rr_actors._transport.messenger import Address, Transport
from rr_actors.config import RegistrarConfig
from rr_actors.errors import (
    CallTimeoutError,
    CatalogCorruptError,
    RegistrarUnavailableError,
    RrError,
)
from rr_actors.simulation import _primitives as sim
from rr_actors.simulation._processes import Process
from rr_actors.simulation._scheduler import Scheduler

__all__ = ["SimulatedManager", "start"]

logger = logging.getLogger("rr_actors")

KILLED = -signal.SIGKILL
"""The exit code of a process ended by SIGKILL (as `Process.exitcode` says it)."""


class _Ended:
    """The process ended (the last thing the parent reads from it)."""

    __slots__ = ("exitcode",)

    def __init__(self, exitcode: int | None) -> None:
        self.exitcode = exitcode


def start(
    sched: Scheduler,
    name: str,
    setup: bytes,
    config: RegistrarConfig,
    address: Address | None,
    *,
    start_timeout: float,
    heartbeat: float | None,
    heartbeat_timeout: float | None,
    on_exit: Callable[[ManagerExit], None],
    forward_events: bool = False,
    on_events: Callable[[list[Any]], None] | None = None,
    announced: bool = False,
) -> SimulatedManager:
    """`ManagerProcess.start` in a simulation: a new simulated process runs the manager;
    returns once it serves (see `ManagerProcess.start` for the arguments and errors)."""
    parent = sched.current().process
    received = Received(on_events, None)
    process = sched.new_process(name, parent)
    # (dies with its parent, as `PR_SET_PDEATHSIG` makes a real one: a program killed)
    parent.at_end.append(functools.partial(sched.end, process, KILLED))
    to_child: Any = runtime.SimpleQueue()
    from_child: Any = runtime.SimpleQueue()
    # (heard once what it served is cut off: a restart finds its names free)
    process.at_reaped.append(lambda: from_child.put(_Ended(process.exitcode)))
    sim.Thread(
        sched,
        target=_child,
        args=(
            sched,
            process,
            setup,
            config,
            address,
            parent.pid,
            forward_events,
            to_child,
            from_child,
            announced,
        ),
        name=f"{name}-main",
        daemon=True,
        process=process,
    ).start()
    deadline = runtime.monotonic() + start_timeout
    while True:
        try:
            message = from_child.get(timeout=max(0.0, deadline - runtime.monotonic()))
        except runtime.Empty:
            sched.end(process, KILLED)
            raise CallTimeoutError(
                f"manager {name!r} was not ready within {start_timeout:g} s"
            ) from None
        if isinstance(message, Events):  # (its restore's in-doubt events, say)
            received.deliver(name, message.batch)
        elif isinstance(message, Ready):
            break
        if isinstance(message, Failed):
            if message.corrupt is not None:  # (as `_process/manager.py` raises it)
                raise message.corrupt
            raise RegistrarUnavailableError(
                f"manager {name!r} failed to start:\n{message.traceback}"
            )
        if isinstance(message, _Ended):
            reason = describe(message.exitcode).reason
            raise RegistrarUnavailableError(f"manager {name!r} died while starting ({reason})")
    handle = SimulatedManager(
        name,
        sched,
        process,
        (to_child, from_child),
        heartbeat,
        heartbeat_timeout,
        on_exit,
        received,
    )
    runtime.Thread(target=handle.watch, name=f"rr-watch-{name}", daemon=True).start()
    return handle


class SimulatedManager(ManagerProcess):
    """The parent's handle on one manager in a simulated process (one incarnation)."""

    def __init__(  # (not ManagerProcess's: no real process, pipe or exit watch)
        self,
        name: str,
        sched: Scheduler,
        process: Process,
        queues: tuple[Any, Any],
        heartbeat: float | None,
        heartbeat_timeout: float | None,
        on_exit: Callable[[ManagerExit], None],
        received: Received,
    ) -> None:
        self.name = name
        self.pid = process.pid
        self._sched = sched
        self._process = process
        self._to_child, self._from_child = queues  # (its control pipe's two ways)
        self._received = received
        self._beat = (
            None
            if heartbeat is None
            else Heartbeat(
                name, heartbeat, heartbeat_timeout or 3.0 * heartbeat, None, runtime.monotonic()
            )
        )
        self._on_exit = on_exit
        self._syncs = {}
        self._sync_tokens = itertools.count(1)
        self._hung: Hang | None = None
        self._stopping = False
        self.exited = runtime.Event()
        self.exit: ManagerExit | None = None
        self.reported = runtime.Event()  # (its exit: a simulated child sends no `Stopped`)
        self._reported = None
        self._exit_by = 0.0
        # It reports no monitors: told every start from now on (registered before its child
        # runs: none is missed), not again those announced before it was made.
        HEARERS.hears_all(self, on=True, at=float("inf"))

    def _send(self, message: FromParent) -> bool:
        if not self._process.alive:
            return False
        self._to_child.put(message)
        return True

    def kill(self) -> None:
        """SIGKILL: its tasks never run again; its backup keeps what committed."""
        self._sched.end(self._process, KILLED)

    def stop_process(self) -> None:
        """SIGSTOP: its tasks do not run until `continue_process`."""
        self._sched.stop(self._process)

    def continue_process(self) -> None:
        """SIGCONT."""
        self._sched.cont(self._process)

    def watch(self) -> None:
        """The watcher task: the heartbeat, the child's answers, then its end."""
        beat = self._beat
        while True:
            if beat is None or self._stopping:
                timeout = None
            else:
                timeout = max(0.0, beat.wake_at - runtime.monotonic())
            ended = self._read(timeout)
            if ended is not None:
                break
            if beat is None or self._stopping:
                continue
            verdict = beat.tick(runtime.monotonic())
            if isinstance(verdict, Hang):
                self._hung = verdict
                logger.error("manager %s hangs (%s): killing it", self.name, verdict.reason())
                self.kill()
                beat = None
            elif isinstance(verdict, int):  # (no `Look`: it is made without probes)
                self._send(Ping(verdict))
                beat.sent(runtime.monotonic())
        self._finished(ended.exitcode)

    def _read(self, timeout: float | None) -> _Ended | None:
        """Read what the child sent (waiting `timeout` seconds for the first); its end,
        if that came."""
        try:
            message = self._from_child.get(timeout=timeout)
        except runtime.Empty:
            return None
        while True:
            if isinstance(message, _Ended):
                return message
            now = runtime.monotonic()
            if isinstance(message, Events):
                self._received.deliver(self.name, message.batch)
            elif isinstance(message, Pong) and self._beat is not None:
                self._beat.answered(message.number, now)
            elif isinstance(message, EventsSynced):
                self._synced(message, now)
            try:
                message = self._from_child.get(block=False)
            except runtime.Empty:
                return None

    def _finished(self, exitcode: int | None) -> None:
        if self._hung is not None:
            result = ManagerExit(f"hung: {self._hung.reason()} (killed)", normal=False)
        else:
            result = describe(exitcode)
        self.exit = result
        self.exited.set()
        HEARERS.forget(self)
        self.reported.set()
        for waiting in list(self._syncs.values()):
            waiting.set()
        try:
            self._on_exit(result)
        except Exception:
            logger.exception("exit handler of manager %s raised", self.name)


class _Pong:
    """Answers a ping once the registrar actor got to it (a hung actor sends none)."""

    def __init__(self, from_child: Any, number: int) -> None:
        self.from_child = from_child
        self.number = number

    def set_result(self, _: Any) -> None:
        self.from_child.put(Pong(self.number, None))

    def set_error(self, _: BaseException) -> None:
        pass


def _links_closed(attached: Transport) -> None:
    """The process ended: what it served is cut off the network (the kernel's part):
    its own servers, not another process's of the same name (beyond a cut)."""
    messenger = cast(Any, attached)
    if messenger.closed:  # (it left first: an exit)
        return
    hub = messenger.link()
    for name in messenger.served():
        served = messenger.serving(name)
        if served is not None:
            hub.end(served, "unavailable")


def _child(
    sched: Scheduler,
    process: Process,
    setup: bytes,
    config: RegistrarConfig,
    address: Address | None,
    parent: int,
    forward: bool,
    to_child: Any,
    from_child: Any,
    announced: bool = False,
) -> None:
    """The manager process's main task: restore, set up, serve; then the control loop."""
    child = _Child(sched, process, from_child, forward=forward)
    try:
        registrar = child.start(setup, config, address, parent, announced=announced)
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, then exit 1
        corrupt = exc if isinstance(exc, CatalogCorruptError) else None
        from_child.put(Failed("".join(traceback.format_exception(exc)), corrupt))
        sched.end(process, 1)
    from_child.put(Ready(process.pid))
    runtime.Thread(target=child.watch_actor, name="rr-manager-actor-watch", daemon=True).start()
    while True:
        message = to_child.get()
        handler = _HANDLERS.get(type(message))
        if handler is None:
            logger.error("manager %s: unknown control message %r", registrar.name, message)
        else:
            handler(child, message)


class _Child:
    """The manager process's side: its registrar, its events to the parent (one by one,
    while told to forward), its control requests (`_HANDLERS`)."""

    def __init__(self, sched: Scheduler, process: Process, from_child: Any, *, forward: bool):
        self.sched = sched
        self.process = process
        self.from_child = from_child
        self.hub: Publisher[events.Event] = events.publisher()  # what its registrar relays to
        self.forwarding = False
        self.switch(on=forward)
        self.attached: Transport | None = None
        self.registrar: Any = None
        self.stopping = runtime.Event()

    def start(
        self,
        setup: bytes,
        config: RegistrarConfig,
        address: Address | None,
        parent: int,
        *,
        announced: bool = False,
    ) -> Any:
        """Attach, restore the registrar from its backup, set it up, serve it."""
        if address is not None:
            self.attached = address.attach()
            self.attached.supervised_by(parent)
            self.process.at_end.append(functools.partial(_links_closed, self.attached))
        registrar = self.registrar = start_registrar(
            config, upstream=self.hub, hold_in_doubt=True, announced=announced
        )
        setup_fn = cloudpickle.loads(setup)
        if setup_fn is not None:
            setup_fn(registrar)
        registrar.settle_in_doubt()
        if self.attached is not None:
            self.attached.serve(Served(registrar))
        return registrar

    def sink(self, event: events.Event) -> None:
        self.from_child.put(Events([event]))

    def switch(self, *, on: bool) -> None:
        if on and not self.forwarding:
            self.hub.add_sink(self.sink)
        elif self.forwarding and not on:
            self.hub.remove_sink(self.sink)
        self.forwarding = on

    def watch_actor(self) -> None:
        """Exit when the registrar actor ends: `STOPPED_EXIT` if code in the manager stopped it."""
        registrar = self.registrar
        registrar.wait_ended()
        if not self.stopping.is_set():
            self.exit(STOPPED_EXIT if stopped_cleanly(registrar.name) else ACTOR_DIED_EXIT)

    def ping(self, message: Ping) -> None:
        """Answer through the registrar actor's mailbox: a hung actor sends no pong."""
        self.registrar._actor.ping(_Pong(self.from_child, message.number))

    def sync_events(self, message: SyncEvents) -> None:
        self.from_child.put(EventsSynced(message.token))  # (its events went before, in order)

    def forward(self, message: Forward) -> None:
        self.switch(on=message.on)

    def peer_started(self, message: PeerStarted) -> None:
        MEMBERSHIP.started(message.name)  # (if its registrar has business with it)

    def peers_stopped(self, message: PeersStopped) -> None:
        """Into this process's membership: its registrar hears them before its `Stop`."""
        MEMBERSHIP.stopped_all(message.names, by="its supervisor (the tree's stop)")
        for name in message.lost:
            MEMBERSHIP.lost(name, by="its supervisor (the tree's stop)")

    def stop(self, message: Stop) -> None:
        """Stop the registrar, exit (`STOPPED_EXIT`, or 1 if it did not stop)."""
        registrar = self.registrar
        self.stopping.set()
        if message.restarting:  # stopped to be restarted with its group: no tombstone
            DIRECTORY.mark_restarting([registrar.name])
        code = STOPPED_EXIT
        try:
            registrar.stop(timeout=message.timeout)
        except RrError:
            logger.exception("manager %s did not stop cleanly", registrar.name)
            code = 1
        self.exit(code)

    def exit(self, code: int) -> None:
        """Leave the network (peers see "stopped" or "died" at once), then end."""
        if self.attached is not None:
            try:
                self.attached.close()
            except Exception:
                logger.exception("leaving the network")
        self.sched.end(self.process, code)


_HANDLERS: dict[type[Any], Callable[[_Child, Any], None]] = {
    Ping: _Child.ping,
    SyncEvents: _Child.sync_events,
    Forward: _Child.forward,
    Stop: _Child.stop,
    PeerStarted: _Child.peer_started,
    PeersStopped: _Child.peers_stopped,
}
"""What the child does with each message of the parent's."""
