"""The one thread that watches every manager process of a process
(`rr_actors._process.watcher`): real processes, real SIGSTOP and SIGKILL, bounded waits.

A thread per manager held the interpreter lock with a thousand of them (issue 69); these
tests hold the watcher to what those threads did, among many managers at once.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._process.control import Ping, Pong, Ready, Stop, mp_context, start_forkserver
from rr_actors._process.manager import ManagerExit, ManagerProcess
from rr_actors._process.watcher import ROUND, Watcher
from tests.support.supervising import bare_manager, pid_of, process

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")


@pytest.fixture(scope="module", autouse=True)
def forkserver() -> None:
    """Start the forkserver before the leak check counts this process's children."""
    start_forkserver()


def watcher_threads() -> int:
    return sum(1 for t in threading.enumerate() if t.name.startswith("rr-watch"))


def names(uid: str, count: int) -> list[str]:
    return [f"m{i}-{uid}" for i in range(count)]


@pytest.mark.timeout(240)  # (forty manager processes start, on a loaded machine too)
def test_a_supervisor_of_thirty_process_managers_has_as_many_watcher_threads_as_one_of_ten(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    counted = []
    for count in (10, 30):
        specs = [process(name, heartbeat=0.25) for name in names(f"{count}-{uid}", count)]
        sup = supervisors(specs).start()
        try:
            counted.append(watcher_threads())
        finally:
            sup.stop()

    assert [1, 1] == counted


def test_a_hung_manager_among_many_healthy_ones_is_killed_as_hung_and_restarted_alone(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    many = names(uid, 20)
    sup = supervisors([process(n, heartbeat=0.2, heartbeat_timeout=1.5) for n in many]).start()
    before = {name: pid_of(sup, name) for name in many}
    hung = many[7]
    os.kill(before[hung], signal.SIGSTOP)
    info = sup.wait_restarted(hung, timeout=30.0)
    after = {name: pid_of(sup, name) for name in many}

    assert info.last_exit is not None
    assert (True, True) == (info.last_exit.startswith("hung"), after[hung] != before[hung])
    assert {n: p for n, p in before.items() if n != hung} == {
        n: p for n, p in after.items() if n != hung
    }


def test_a_manager_sigkilled_among_many_is_seen_dead_and_restarted_alone(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    many = names(uid, 20)
    sup = supervisors([process(n, heartbeat=0.25) for n in many]).start()
    before = {name: pid_of(sup, name) for name in many}
    killed = many[12]
    os.kill(before[killed], signal.SIGKILL)
    info = sup.wait_restarted(killed, timeout=30.0)
    after = {name: pid_of(sup, name) for name in many}

    assert ("killed by SIGKILL", True) == (info.last_exit, after[killed] != before[killed])
    assert {n: p for n, p in before.items() if n != killed} == {
        n: p for n, p in after.items() if n != killed
    }


# -- a handle whose turn raises ------------------------------------------------------------------


def double(conn: Connection, garbage: bool) -> None:
    """A manager process's double: ready, then (`garbage`) bytes that are no message, then
    it answers every ping until told to stop."""
    conn.send(Ready(os.getpid()))
    if garbage:
        conn.send_bytes(b"not a control message")
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            os._exit(0)
        if isinstance(message, Stop):
            os._exit(0)
        if isinstance(message, Ping):
            conn.send(Pong(message.number))


class _Double:
    """What `ManagerProcess.start` takes a spare for: a running `double` and its pipe."""

    def __init__(self, *, garbage: bool) -> None:
        ctx = mp_context()
        self.conn, child = ctx.Pipe(duplex=True)
        self.process = ctx.Process(target=double, args=(child, garbage), daemon=True)  # type: ignore[attr-defined]
        self.process.start()
        child.close()

    def take(self, *_args: Any, **_kwargs: Any) -> bool:
        return True


def start_double(
    name: str, *, garbage: bool
) -> contextlib.AbstractContextManager[tuple[ManagerProcess, list[ManagerExit], threading.Event]]:
    """`bare_manager` `name`, whose process is a `double` (pings every 0.1 s, hung after 2 s)."""
    return bare_manager(name, heartbeat=0.1, heartbeat_timeout=2.0, spare=_Double(garbage=garbage))


def test_a_manager_whose_watch_raises_is_killed_and_reported_while_the_others_are_still_watched(
    uid: str, caplog: pytest.LogCaptureFixture
) -> None:
    with (
        start_double(f"good-{uid}", garbage=False) as (good, good_exits, good_exited),
        start_double(f"bad-{uid}", garbage=True) as (bad, bad_exits, bad_exited),
    ):
        assert bad_exited.wait(20.0)
        os.kill(good.pid, signal.SIGKILL)  # what the watch sees now: the others' still goes on
        assert good_exited.wait(20.0)

    assert [(False, True)] == [(e.normal, "its watch failed" in e.reason) for e in bad_exits]
    assert ["killed by SIGKILL"] == [e.reason for e in good_exits]
    assert any(f"watching manager {bad.name} failed" in r.getMessage() for r in caplog.records)


class _Watched:
    """A watched handle without a process: `turns` gets its name at each turn. `due`: its
    first turn says it is due again at once (a ping due), its second ends it; else it ends
    at a turn woken by its `waitables`. `hold` (an event): its first turn waits for it;
    `at_turn`: called at each turn."""

    def __init__(self, name: str, turns: list[str], *, due: bool = False, **kw: Any) -> None:
        self.name, self.turns, self.due, self.taken = name, turns, due, 0
        self.waitables: list[Any] = kw.get("waitables", [])
        self.hold: threading.Event | None = kw.get("hold")
        self.at_turn: Callable[[], None] = kw.get("at_turn", lambda: None)
        self.ended = threading.Event()

    def wake_at(self) -> float | None:
        return 0.0 if self.due and self.taken == 1 else None

    def turn(self, woke: list[Any]) -> tuple[bool, int | None]:
        if self.hold is not None:
            assert self.hold.wait(20.0)
            self.hold = None
        self.taken += 1
        self.turns.append(self.name if woke or self.taken > 1 else f"({self.name} added)")
        self.at_turn()
        return (self.taken == 2 if self.due else bool(woke)), None

    def watch_failed(self, error: BaseException) -> None:
        raise AssertionError(error)

    def finish(self, exitcode: int | None) -> None:
        self.ended.set()


def test_an_exit_is_seen_within_a_round_of_due_turns_however_many_are_due() -> None:
    # A thousand managers on a busy machine: the watcher was behind its pings and took every
    # one due before its next look at what was ready, an exit seen a period late (issue 69).
    turns: list[str] = []
    read, write = os.pipe()
    go = threading.Event()
    watcher = Watcher()
    blocker = _Watched("blocker", turns, due=True, hold=go)
    exiting = _Watched("exit", turns, waitables=[read])
    fired: list[int] = []

    def exit_now() -> None:  # (at the first ping due: the exit happens then)
        if not fired:
            fired.append(len(turns))
            os.write(write, b"x")

    due = [_Watched(f"due{i}", turns, due=True) for i in range(3 * ROUND)]
    for handle in due:  # (its second turn: its ping due)
        handle.at_turn = lambda h=handle: exit_now() if h.taken == 2 else None
    try:
        watcher.watch(blocker)
        for handle in [exiting, *due]:
            watcher.watch(handle)  # (one round adds them all: the blocker holds the thread)
        go.set()
        assert all(h.ended.wait(20.0) for h in [blocker, exiting, *due])
    finally:
        os.close(read)
        os.close(write)

    assert turns.index("exit") - fired[0] <= ROUND, turns
