"""Helpers of the supervisor tests: a clock and a timer driven by hand, process facts, the
kill scaffold (`sigkill`, `kill_and_wait_restarted`, `crash` for a thread manager), and a
manager process started without a supervisor (`bare_manager`)."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr
from rr_actors import testing
from rr_actors._platform import PLATFORM
from rr_actors._process.manager import ManagerExit, ManagerProcess
from tests.support import selecting

linux_trick = pytest.mark.skipif(
    PLATFORM.name != "linux",
    reason="tests a Linux trick; the portable platform (RR_ACTORS_PLATFORM=portable) has none",
)
"""Marks a test of what only a trick of `rr_actors._platform.linux` does."""


class FakeClock:
    """A monotonic clock that moves only when the test says so."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class _Handle:
    def __init__(self) -> None:
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True


class ManualTimer:
    """A `timer` that records delays and fires only when the test calls `fire()`."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.pending: list[tuple[float, Callable[[], None], _Handle]] = []
        self.delays: list[float] = []

    def __call__(self, delay: float, fn: Callable[[], None]) -> _Handle:
        handle = _Handle()
        with self.cond:
            self.pending.append((delay, fn, handle))
            self.delays.append(delay)
            self.cond.notify_all()
        return handle

    def wait_scheduled(self, count: int, timeout: float = 5.0) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: len(self.delays) >= count, timeout)

    def fire(self) -> None:
        with self.cond:
            pending, self.pending = self.pending, []
        for _, fn, handle in pending:
            if not handle.cancelled:
                fn()


def alive(pid: int) -> bool:
    """Whether process `pid` exists and is not a zombie."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        return not Path("/proc").exists()
    return state != "Z"


def wait_gone(pids: list[int], timeout: float = 15.0) -> list[int]:
    """Wait (bounded) until none of `pids` lives; return those still alive.

    Blocks on a pidfd per process (readable once it ended; pidfds work for processes that
    are not our children); polls only where there are no pidfds.
    """
    deadline = time.monotonic() + timeout
    for pid in pids:
        try:
            fd = os.pidfd_open(pid)
        except (AttributeError, OSError):  # gone already, or no pidfds: polled below
            continue
        try:
            selecting.select([fd], [], [], max(0.0, deadline - time.monotonic()))
        finally:
            os.close(fd)
    pause = threading.Event()
    while any(alive(p) for p in pids) and time.monotonic() < deadline:
        pause.wait(0.02)
    return [p for p in pids if alive(p)]


def pid_of(sup: rr.Supervisor, name: str) -> int:
    """The pid of running manager process `name` (never 0 or None: `os.kill(0, ...)`
    signals the whole process group)."""
    pid = sup.child(name).pid
    assert pid, f"{name} has no pid"
    return pid


def sigkill(sup: rr.Supervisor, name: str) -> int:
    """SIGKILL supervised manager process `name` (a real crash); return the pid it had."""
    pid = pid_of(sup, name)
    os.kill(pid, signal.SIGKILL)
    return pid


def kill_and_wait_restarted(
    sup: rr.Supervisor, name: str, *, timeout: float = 15.0
) -> rr.ChildInfo:
    """SIGKILL manager process `name`, then wait (bounded) until `sup` restarted it."""
    sigkill(sup, name)
    return sup.wait_restarted(name, timeout=timeout)


def crash(sup: rr.Supervisor, name: str) -> None:
    """Make thread manager `name`'s registrar actor die (the in-process SIGKILL)."""
    testing.crash(sup.run_in(name, lambda r: r))


def echo_setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("echo", load=lambda r: r, unload=lambda r, s: None)


def process(name: str, setup: Any = echo_setup, **kwargs: Any) -> rr.ManagerSpec:
    return rr.ManagerSpec(name, setup, isolation="process", **kwargs)


OWNER = textwrap.dedent(
    """
    import sys, threading
    import rr_actors as rr

    def setup(registrar):
        registrar.register_server("echo", load=lambda r: r, unload=lambda r, s: None)

    if __name__ == "__main__":
        uid, options = sys.argv[1], ({"heartbeat": None} if sys.argv[2] == "none" else {})
        sup = rr.Supervisor([rr.ManagerSpec(f"{n}-{uid}", setup, isolation="process",
                                            **options) for n in ("a", "b")])
        sup.start()
        print(" ".join(str(i.pid) for i in sup.which_children()), flush=True)
        threading.Event().wait()
    """
)
"""A user's main program: a supervisor of two manager processes; prints their pids."""


@contextlib.contextmanager
def killed_owner(uid: str, tmp_path: Path, *, heartbeat: bool = True) -> Iterator[list[int]]:
    """Run `OWNER` in its own process; yield its managers' pids, then SIGKILL it.

    `heartbeat=False` starts the managers without heartbeats. The owner's runtime
    directory, which a SIGKILLed owner cannot remove, is kept in a short temporary
    directory (AF_UNIX socket paths are limited to about 100 bytes) and removed here.
    """
    script = tmp_path / "owner.py"
    script.write_text(OWNER)
    runtime_parent = tempfile.mkdtemp(prefix="rr-test-")
    owner = subprocess.Popen(
        [sys.executable, str(script), uid, "default" if heartbeat else "none"],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "TMPDIR": runtime_parent},
    )
    try:
        assert owner.stdout is not None
        readable, _, _ = selecting.select([owner.stdout], [], [], 30.0)
        assert [owner.stdout] == readable  # it prints its managers' pids once they run
        pids = [int(p) for p in owner.stdout.readline().split()]
        assert 2 == len(pids)
        yield pids
    finally:
        owner.kill()
        owner.wait(10.0)
        if owner.stdout is not None:
            owner.stdout.close()
        shutil.rmtree(runtime_parent, ignore_errors=True)


@contextlib.contextmanager
def bare_manager(
    name: str,
    *,
    heartbeat: float | None = None,
    heartbeat_timeout: float | None = None,
    exited: threading.Event | None = None,
    **options: Any,
) -> Iterator[tuple[ManagerProcess, list[ManagerExit], threading.Event]]:
    """Manager process `name` (no setup) started by `ManagerProcess.start` itself, no
    supervisor; yields it, the exits its owner was told (in order) and `exited` (a new
    event by default), set at each; then stops it (5 s, then killed: none outlives the test).

    `options`: more of `ManagerProcess.start`'s (`spare`, `on_events`, ...); seconds."""
    exits: list[ManagerExit] = []
    told = threading.Event() if exited is None else exited
    handle = ManagerProcess.start(
        name,
        cloudpickle.dumps(None),
        rr.RegistrarConfig(name=name),
        None,
        start_timeout=30.0,
        heartbeat=heartbeat,
        heartbeat_timeout=heartbeat_timeout,
        on_exit=lambda how: (exits.append(how), told.set()),
        **options,
    )
    try:
        yield handle, exits, told
    finally:
        handle.stop(5.0)


def logging_consumer(provider: str, events: list[str]) -> Callable[[rr.ResourceRegistrar], None]:
    """A thread manager's setup: note `start <name>`, then load `<name>` from `provider`.

    The manager's clean stop unloads what it holds, so the provider notes `unload <name>`
    when (and in the order that) the supervisor stops it.
    """

    def setup(reg: rr.ResourceRegistrar) -> None:
        events.append(f"start {reg.name}")
        reg.call(provider, "log", reg.name)

    return setup
