"""Simulated processes: their own per-process state, a SIGKILL that runs nothing more, a
SIGSTOP that runs nothing until SIGCONT."""

from __future__ import annotations

import signal
import socket
import threading
from typing import Any

import pytest

from rr_actors import simulation
from rr_actors._core import runtime
from rr_actors._core.directory import DIRECTORY
from rr_actors.simulation._processes import Process, States

pytest.importorskip("greenlet")  # (the simulation extra)


def test_each_process_has_a_pid_and_its_own_per_process_state() -> None:
    seen: dict[str, object] = {}

    def child() -> None:
        seen["child pid"] = simulation.pid()
        seen["child expects"] = DIRECTORY.restart_expected("x")
        DIRECTORY.expect_restart("y")
        runtime.Thread(target=lambda: seen.update(thread=simulation.pid()), name="t").start()

    def main() -> None:
        DIRECTORY.expect_restart("x")
        pid = simulation.start_process(child, name="child")
        simulation.sleep(1.0)
        seen["main pid"], seen["child"] = simulation.pid(), pid
        seen["main expects"] = (DIRECTORY.restart_expected("x"), DIRECTORY.restart_expected("y"))

    simulation.run(main, seed=1)

    assert 1 == seen["main pid"]
    assert seen["child"] == seen["child pid"] == seen["thread"] == 2
    assert seen["child expects"] is False  # (fresh: the main process's is not its)
    assert (True, False) == seen["main expects"]  # (its own stays its own)
    assert not DIRECTORY.restart_expected("x")  # (the real process's state is back)


def test_a_killed_process_runs_nothing_more_not_even_its_finally_blocks() -> None:
    journal: list[str] = []

    def child() -> None:
        def tick() -> None:
            try:
                while True:
                    simulation.sleep(1.0)
                    journal.append(f"tick {simulation.now():g}")
            finally:
                journal.append("finally")

        runtime.Thread(target=tick, name="ticker", daemon=True).start()
        runtime.Event().wait()

    def main() -> list[str]:
        pid = simulation.start_process(child, name="child")
        simulation.sleep(2.5)
        simulation.kill(pid)
        simulation.sleep(5.0)
        return list(journal)

    run = simulation.run(main, seed=3)

    assert ["tick 1", "tick 2"] == run.value
    assert () == run.errors


def test_held_files_are_closed_as_their_process_is_killed_and_the_rest_as_the_run_ends() -> None:
    """`runtime.hold`: a killed process's files are closed at the kill, as the kernel
    closes a dead process's (not when the collector finds its memory); those of a process
    alive at the run's end, when it ends. A real thread's `hold` registers nothing."""
    killed, alive = socket.socketpair(), socket.socketpair()
    seen: dict[str, int] = {}

    def child(sockets: tuple[socket.socket, socket.socket]) -> None:
        assert runtime.hold(sockets[0]) is sockets[0]
        runtime.Event().wait()

    def main() -> None:
        pid = simulation.start_process(lambda: child(killed), name="killed")
        simulation.start_process(lambda: child(alive), name="alive")
        simulation.sleep(1.0)
        simulation.kill(pid)
        seen["killed"], seen["alive"] = killed[0].fileno(), alive[0].fileno()
        outside = threading.Thread(target=runtime.hold, args=(alive[1],))
        outside.start()
        outside.join()

    try:
        run = simulation.run(main, seed=1)

        assert () == run.errors
        assert seen["killed"] == -1  # (closed as it died, the run going on)
        assert seen["alive"] >= 0
        assert (-1, -1) == (killed[0].fileno(), alive[0].fileno())  # (the run ended)
        assert (killed[1].fileno(), alive[1].fileno()) >= (0, 0)  # (held by nobody)
    finally:
        for sock in (*killed, *alive):
            sock.close()


def test_a_kill_lets_go_of_a_lock_of_another_process_its_thread_held() -> None:
    """Only a carrier's objects are shared between simulated processes: a dead process
    holds none of their locks."""

    def main() -> bool:
        shared = runtime.Lock()

        def child() -> None:
            shared.acquire()
            runtime.Event().wait()

        pid = simulation.start_process(child, name="child")
        simulation.sleep(1.0)
        taken_before = shared.acquire(timeout=1.0)
        simulation.kill(pid)
        return not taken_before and shared.acquire(timeout=1.0)

    assert simulation.run(main, seed=1).value


def test_a_stopped_process_runs_nothing_until_it_is_continued() -> None:
    journal: list[float] = []

    def child() -> None:
        while True:
            simulation.sleep(1.0)
            journal.append(simulation.now())

    def main() -> list[float]:
        pid = simulation.start_process(child, name="child")
        simulation.sleep(1.5)
        simulation.kill(pid, signal.SIGSTOP)
        simulation.sleep(5.0)
        simulation.kill(pid, signal.SIGCONT)
        simulation.sleep(1.2)
        simulation.kill(pid)
        return list(journal)

    assert [1.0, 6.5, 7.5] == simulation.run(main, seed=1).value  # (its 2.0 tick at 6.5)


def test_killing_an_unknown_pid_raises_as_os_kill_does() -> None:
    def main() -> None:
        simulation.kill(99)

    with pytest.raises(ProcessLookupError):
        simulation.run(main, seed=1)


class Plain:
    def __init__(self) -> None:
        self.items: list[int] = []
        self.name = "fresh"


class Slotted:
    __slots__ = ("count", "late")

    def __init__(self) -> None:
        self.count = 0
        self.late = "fresh"


@pytest.mark.parametrize("steps", [1, 3])
def test_each_process_keeps_its_own_state_of_a_plain_and_a_slotted_singleton(
    steps: int,
) -> None:
    plain, slotted = Plain(), Slotted()
    plain.items.append(99)
    real_dict = plain.__dict__
    del slotted.late  # (a field the real one lacks comes back missing)
    states = States(((plain, Plain), (slotted, Slotted)))
    first, second = Process(1, "a", states.fresh()), Process(2, "b", states.fresh())

    for _ in range(steps):
        states.install(first)
        plain.items.append(1)
        slotted.count += 1
        states.install(second)
        assert ([], 0, "fresh") == (plain.items, slotted.count, slotted.late)
        plain.name = "second's"
    states.install(first)
    seen: Any = (list(plain.items), slotted.count, plain.name)
    states.close()

    assert ([1] * steps, steps, "fresh") == seen
    assert plain.__dict__ is real_dict
    assert [99] == plain.items
    assert 0 == slotted.count
    assert not hasattr(slotted, "late")


def test_every_registered_instance_is_swapped_whole_at_a_switch() -> None:
    """A switch between simulated processes (most steps of a run) swaps each registered
    singleton's `__dict__`, one assignment each; only a class (pykka's registry) has its
    fields copied out and back in, one by one (a slotted instance would: the clock was)."""
    from rr_actors._core import hlc  # noqa: PLC0415

    states = States(runtime.process_states())
    copied = [obj for _, obj, _, _ in states._copied]

    assert [] == [obj for obj in copied if not isinstance(obj, type)]
    assert hlc.CLOCK in [obj for _, obj in states._swapped]
