"""What an experiment adds inside each manager: a switch that makes loads raise, and a cut.

Runs where the manager runs. Every `ManagerSpec` gets `setup=functools.partial(
instrumented_setup, path, options)`: the real setup runs with a registrar whose
`register_server` wraps each `load` (a coroutine one in a coroutine, `_aguarded`):

    injector ──Supervisor.run_in(name, arm_load_error(...))──► _SWITCHES.armed[name] (this module)
    client ──call──► registrar ──load(request)──► _guarded: armed to raise? ──► InjectedLoadError
                                                              else ──► the setup's own load

On the simulation the switch is per simulated process (virtual clock), and `kill_in_setup`
arms `SETUP_FAULTS[name]`, run after the next setup returned, before the manager serves;
`kill_before_commit` arms `COMMIT_FAULTS[pid]`, run at the registrar's next turn commit
(`arm_commit_fault`, through `run_in`: the probe `turn_commit`).
`cut_connections` (a SIGUSR2 handler on the manager's main thread, fired at an exact time)
shuts down every AF_UNIX connection of the registrar: calls in flight fail with
`RegistrarUnavailableError` and the next message connects again.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import os
import signal
import socket
import stat
import threading
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from rr_actors._core import runtime
from rr_actors._core.loops import is_coroutine_function

if TYPE_CHECKING:
    from rr_actors import ResourceRegistrar

__all__ = [
    "COMMIT_FAULTS",
    "CUT_SIGNAL",
    "SETUP_FAULTS",
    "InjectedLoadError",
    "arm_commit_fault",
    "arm_load_error",
    "catches_cut_signal",
    "cut_connections",
    "instrumented_setup",
]

CUT_SIGNAL = signal.SIGUSR2
"""The signal that makes a manager process cut its connections (`cut_connections`)."""


class InjectedLoadError(RuntimeError):
    """Raised by a `load` while a `load_error` fault is armed (callers get `ResourceLoadError`)."""


@dataclasses.dataclass
class _Armed:
    server: str | None
    remaining: int | None  # loads left to fail; None: every load until `until`
    until: float | None  # monotonic deadline (CLOCK_MONOTONIC is system-wide on Linux)
    message: str


class _Switches:
    """The load errors armed in this process (a simulated process has its own)."""

    def __init__(self) -> None:
        self.armed: dict[str, _Armed] = {}


_SWITCHES = runtime.process_state(_Switches(), _Switches)
_LOCK = threading.Lock()  # (never held across a wait: the simulation's one thread is safe)

SETUP_FAULTS: dict[str, Callable[[], object]] = {}
"""Manager name -> what its next setup runs once the plan's setup returned (popped then):
armed by the simulation's `kill_in_setup` fault only."""

COMMIT_FAULTS: dict[int, Callable[[], object]] = {}
"""Simulated pid -> what its registrar runs at its next turn's commit, before the write
(popped then): armed by the simulation's `kill_before_commit` fault only."""


def arm_commit_fault(registrar: ResourceRegistrar) -> None:
    """Make the registrar's next turn commit run `COMMIT_FAULTS[its process]` before its
    write (the probe `turn_commit`, `rr_actors.testing.intercept`): the changes of that turn
    staged, the answers it held not released. Run it in the manager with
    `Supervisor.run_in(manager, arm_commit_fault)`; installed once a registrar (its hook
    does nothing for a pid `COMMIT_FAULTS` does not name)."""
    from rr_actors.testing import intercept  # noqa: PLC0415 - only for this fault

    intercept(registrar, "turn_commit", before=_at_commit)


def _at_commit(staged: object) -> None:
    """The probe `turn_commit` (the registrar's actor thread): what is armed for this
    process, once."""
    del staged
    fire = COMMIT_FAULTS.pop(runtime.getpid(), None)
    if fire is not None:
        fire()


def arm_load_error(
    manager: str,
    server: str | None,
    loads: int,
    for_s: float | None,
    message: str,
    registrar: object = None,
) -> None:
    """Make the next `loads` loads of `manager` raise (or every load for `for_s` seconds).

    Run it in the manager with `Supervisor.run_in(manager, functools.partial(...))`.

    Args:
        manager: the manager's name.
        server: only loads of this server raise (`None`: any server).
        loads: how many loads raise (ignored with `for_s`).
        for_s: raise on every load for this many seconds instead.
        message: the exception's message.
        registrar: the manager's registrar (given by `run_in`; not used).
    """
    del registrar
    until = None if for_s is None else runtime.monotonic() + for_s
    with _LOCK:
        _SWITCHES.armed[manager] = _Armed(
            server, None if for_s is not None else loads, until, message
        )


def _should_fail(manager: str, server: str) -> str | None:
    """The message to raise with if a load of `manager/server` must fail now, else `None`."""
    with _LOCK:
        armed = _SWITCHES.armed.get(manager)
        if armed is None or (armed.server is not None and armed.server != server):
            return None
        if armed.until is not None:
            if runtime.monotonic() < armed.until:
                return armed.message
            del _SWITCHES.armed[manager]
            return None
        assert armed.remaining is not None
        armed.remaining -= 1
        if armed.remaining <= 0:
            del _SWITCHES.armed[manager]
        return armed.message


def _guarded(manager: str, server: str, load: Callable[[Any], Any], request: Any) -> Any:
    message = _should_fail(manager, server)
    if message is not None:
        raise InjectedLoadError(message)
    return load(request)


async def _aguarded(manager: str, server: str, load: Callable[[Any], Any], request: Any) -> Any:
    """`_guarded` for a coroutine `load`: a coroutine function too, so that the registrar
    awaits it on its loop as it would the setup's own."""
    message = _should_fail(manager, server)
    if message is not None:
        raise InjectedLoadError(message)
    return await load(request)


class _FaultableRegistrar:
    """The registrar as a manager's setup sees it: the same, but loads can be made to fail."""

    def __init__(self, registrar: Any, manager: str) -> None:
        self._registrar = registrar
        self._manager = manager

    def register_server(self, name: str, *, load: Callable[[Any], Any], **kwargs: Any) -> None:
        self._registrar.register_server(name, load=self._guarded(name, load), **kwargs)

    async def aregister_server(
        self, name: str, *, load: Callable[[Any], Any], **kwargs: Any
    ) -> None:
        await self._registrar.aregister_server(name, load=self._guarded(name, load), **kwargs)

    def _guarded(self, server: str, load: Callable[[Any], Any]) -> Callable[[Any], Any]:
        """`load` behind the switch; a coroutine function exactly when `load` is one (the
        registrar tells them apart by that, and awaits a coroutine `load` on its loop)."""
        wrap = _aguarded if is_coroutine_function(load) else _guarded
        return functools.partial(wrap, self._manager, server, load)

    def __getattr__(self, attribute: str) -> Any:
        return getattr(self._registrar, attribute)


def instrumented_setup(
    path: str, options: Mapping[str, Any], base_dir: str | None, registrar: Any
) -> None:
    """Import the setup at `path` and run it on a registrar whose loads can be made to fail.

    On the main thread of a process manager it also installs the `CUT_SIGNAL` handler.

    Args:
        path: the setup's import path (`"module:function"`).
        options: keyword arguments for the setup.
        base_dir: a directory searched first for `path` (the plan's), or `None`.
        registrar: the manager's registrar (given by the supervisor).
    """
    from rr_actors_lab.experiments.reading import import_object  # noqa: PLC0415 - runs in managers

    if runtime.handles_signals():
        signal.signal(CUT_SIGNAL, _on_cut_signal)
    setup = import_object(path, base_dir=base_dir)
    setup(_FaultableRegistrar(registrar, registrar.name), **options)
    fault = SETUP_FAULTS.pop(registrar.name, None)
    if fault is not None:
        fault()


def _on_cut_signal(_signum: int, _frame: object) -> None:
    cut_connections()


def cut_connections() -> int:
    """Shut down this process's connections on the system's sockets; return how many.

    A connection counts if it is an AF_UNIX stream socket, not listening, whose own or
    peer address is a registrar socket (`<runtime_dir>/<name>.sock`). Control pipes
    (unnamed socket pairs) and listeners are left alone, so the manager keeps serving
    and its supervisor keeps seeing it.
    """
    cut = 0
    for entry in os.listdir("/proc/self/fd"):
        fd = int(entry)
        try:
            if not stat.S_ISSOCK(os.fstat(fd).st_mode):
                continue
            sock = socket.socket(fileno=os.dup(fd))
        except OSError:
            continue
        with sock:
            try:
                if sock.family != socket.AF_UNIX or sock.getsockopt(
                    socket.SOL_SOCKET, socket.SO_ACCEPTCONN
                ):
                    continue
                names = [sock.getsockname()]
                with contextlib.suppress(OSError):
                    names.append(sock.getpeername())
                if any(isinstance(n, str) and n.endswith(".sock") for n in names):
                    sock.shutdown(socket.SHUT_RDWR)
                    cut += 1
            except OSError:
                continue
    return cut


def catches_cut_signal(pid: int) -> bool:
    """Whether process `pid` handles `CUT_SIGNAL` (else the signal would kill it)."""
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("SigCgt:"):
                    mask = int(line.split()[1], 16)
                    return bool(mask >> (int(CUT_SIGNAL) - 1) & 1)
    except (OSError, ValueError):
        return False
    return False
