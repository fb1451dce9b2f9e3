"""One supervisor tree per state directory (`rr_actors._supervision.statedir`, issue 16): a
lock on `<state_dir>/.lock`; and the consumer registrars it remembers (issue 51).

Two trees given the same `state_dir` would share their managers' backups. The second one
gets `ConfigError` naming the holder's pid; the lock goes with the holder's stop or death
(a real SIGKILL of a real process). A program killed and started again on its
`state_dir` gets its consumer's last ids released (a real program, SIGKILLed).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import textwrap
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

import rr_actors as rr
from tests.support import selecting
from tests.support.supervising import wait_gone

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX flock")

HOLDER = textwrap.dedent(
    """
    import sys, threading
    import rr_actors as rr

    sup = rr.Supervisor([rr.ManagerSpec(sys.argv[2])], state_dir=sys.argv[1]).start()
    print("ready", flush=True)
    threading.Event().wait()
    """
)
"""Another program: a supervisor of one thread manager on the given state_dir."""


@contextlib.contextmanager
def holder(state_dir: Path, uid: str) -> Iterator[subprocess.Popen[str]]:
    """Run `HOLDER` on `state_dir` in its own process until it has started; kill it after."""
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(state_dir), f"h-{uid}"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        readable, _, _ = selecting.select([proc.stdout], [], [], 30.0)
        assert [proc.stdout] == readable
        assert "ready" == proc.stdout.readline().strip()
        yield proc
    finally:
        proc.kill()
        proc.wait(10.0)
        if proc.stdout is not None:
            proc.stdout.close()


PROGRAM = textwrap.dedent(
    """
    import json, sys, threading
    import rr_actors as rr

    state_dir, uid, consumer, run = sys.argv[1:]
    erm, action = f"erm-{uid}", f"action-{uid}"

    def setup(registrar):
        registrar.register_server("s", load=lambda request: request, unload=lambda *_: None)

    def load_five(registrar):
        if run == "first":
            for i in range(5):
                registrar.call(erm, "s", i)

    unloaded, unloads = threading.Event(), []

    def count(event):
        if isinstance(event, rr.events.ResourceUnloaded) and event.registrar == erm:
            unloads.append(event.resource_id)
            if len(unloads) == 5:
                unloaded.set()

    specs = [rr.ManagerSpec(erm, setup, isolation="process")]
    if consumer == "manager":  # a manager whose own config keeps no backup
        specs.append(rr.ManagerSpec(action, load_five, config=rr.RegistrarConfig(name=action)))
    sup = rr.Supervisor(specs, state_dir=state_dir)
    with sup.subscribe(count):
        sup.start()
        if consumer == "registrar":
            load_five(sup.registrar(action))
        if run == "first":
            print(json.dumps(sup.child(erm).pid), flush=True)
            threading.Event().wait()  # until SIGKILLed
        unloaded.wait(15.0)
        held = sup.run_in(erm, lambda registrar: registrar.server_queries("s"))
        sup.stop()
    print(json.dumps({"unloads": len(unloads), "held": len(held)}), flush=True)
    """
)
"""A program: a process manager `erm-<uid>` serving "s" on the given state_dir, and a
consumer `action-<uid>` that keeps no backup: a registrar taken with `registrar()`, or
a thread manager whose own config has no backup. Its first run loads 5 resources, prints
the manager's pid and waits to be killed; a later run waits (15 s at most) for the 5
`unload`s, then prints how many ran and how many ids "s" still holds."""


def run_program(state_dir: Path, uid: str, consumer: str, run: str) -> subprocess.Popen[str]:
    """Start `PROGRAM`'s run `run` on `state_dir`, with a `consumer` of that kind."""
    return subprocess.Popen(
        [sys.executable, "-c", PROGRAM, str(state_dir), uid, consumer, run],
        stdout=subprocess.PIPE,
        text=True,
    )


def read_line(proc: subprocess.Popen[str], timeout: float) -> str:
    """The next line `proc` prints, waited for `timeout` seconds at most."""
    assert proc.stdout is not None
    readable, _, _ = selecting.select([proc.stdout], [], [], timeout)
    assert [proc.stdout] == readable, f"no line within {timeout} s"
    return proc.stdout.readline().strip()


@pytest.mark.parametrize("consumer", ["registrar", "manager"])
def test_a_program_killed_and_started_again_has_its_consumers_last_ids_released(
    uid: str, tmp_path: Path, consumer: str
) -> None:
    first = run_program(tmp_path, uid, consumer, "first")
    try:
        manager = json.loads(read_line(first, 20.0))
        os.kill(first.pid, signal.SIGKILL)
    finally:
        first.kill()
        first.wait(10.0)
        assert first.stdout is not None
        first.stdout.close()
    assert [] == wait_gone([manager], 10.0)  # it ends with its program (no orphans)

    again = run_program(tmp_path, uid, consumer, "again")
    try:
        outcome = json.loads(read_line(again, 30.0))
    finally:
        again.kill()
        again.wait(10.0)
        assert again.stdout is not None
        again.stdout.close()

    assert {"unloads": 5, "held": 0} == outcome


def test_a_second_supervisor_on_the_same_state_dir_is_refused_naming_the_holders_pid(
    supervisors: Callable[..., rr.Supervisor], uid: str, tmp_path: Path
) -> None:
    supervisors([rr.ManagerSpec(f"a-{uid}")], state_dir=tmp_path).start()

    with pytest.raises(
        rr.ConfigError, match=rf"in use by another supervisor \(pid {os.getpid()}\)"
    ):
        supervisors([rr.ManagerSpec(f"b-{uid}")], state_dir=tmp_path).start()


def test_a_state_dir_held_by_a_supervisor_of_this_process_says_to_stop_that_one_first(
    supervisors: Callable[..., rr.Supervisor], uid: str, tmp_path: Path
) -> None:
    supervisors([rr.ManagerSpec(f"a-{uid}")], state_dir=tmp_path).start()

    with pytest.raises(rr.ConfigError) as raised:
        supervisors([rr.ManagerSpec(f"b-{uid}")], state_dir=tmp_path).start()

    assert (
        f"state_dir {str(tmp_path)!r} is in use by another supervisor (pid {os.getpid()}), one "
        "of this process that is still running: stop it first, or give each supervisor tree "
        "its own state_dir"
    ) == str(raised.value)


def test_a_state_dir_is_free_again_once_its_supervisor_stopped(
    supervisors: Callable[..., rr.Supervisor], uid: str, tmp_path: Path
) -> None:
    supervisors([rr.ManagerSpec(f"a-{uid}")], state_dir=tmp_path).start().stop()

    second = supervisors([rr.ManagerSpec(f"b-{uid}")], state_dir=tmp_path).start()
    assert "running" == second.child(f"b-{uid}").state


def test_a_nested_supervisor_with_its_own_state_dir_locks_it_too(
    supervisors: Callable[..., rr.Supervisor], uid: str, tmp_path: Path
) -> None:
    inner = rr.SupervisorSpec(f"inner-{uid}", (rr.ManagerSpec(f"x-{uid}"),), state_dir=tmp_path)
    supervisors([inner], state_dir=tmp_path / "top").start()

    with pytest.raises(rr.ConfigError, match="in use by another supervisor"):
        supervisors([rr.ManagerSpec(f"b-{uid}")], state_dir=tmp_path).start()


def test_a_state_dir_held_by_another_process_names_that_process(
    supervisors: Callable[..., rr.Supervisor], uid: str, tmp_path: Path
) -> None:
    with holder(tmp_path, uid) as other:
        sup = supervisors([rr.ManagerSpec(f"b-{uid}")], state_dir=tmp_path)

        with pytest.raises(rr.ConfigError, match=rf"\(pid {other.pid}\)"):
            sup.start()


def test_a_state_dir_is_free_again_once_its_holder_was_killed(
    supervisors: Callable[..., rr.Supervisor], uid: str, tmp_path: Path
) -> None:
    with holder(tmp_path, uid) as other:
        os.kill(other.pid, signal.SIGKILL)
        other.wait(10.0)

    sup = supervisors([rr.ManagerSpec(f"b-{uid}")], state_dir=tmp_path).start()
    assert "running" == sup.child(f"b-{uid}").state


def test_a_simulation_takes_no_lock_on_a_state_dir_but_makes_it(tmp_path: Path) -> None:
    # (its processes are one OS process: a simulated program killed would hold it for
    # good, and its start again on the same state_dir would be refused)
    pytest.importorskip("greenlet")
    from rr_actors import simulation  # noqa: PLC0415 - the simulation extra
    from rr_actors._supervision.statedir import LOCK_NAME, StateDirLock  # noqa: PLC0415

    state = tmp_path / "state"

    def twice() -> None:
        StateDirLock.acquire([state])
        StateDirLock.acquire([state])  # (never released: as by a killed program)

    simulation.run(twice, seed=1)

    assert state.is_dir()
    assert not (state / LOCK_NAME).exists()
