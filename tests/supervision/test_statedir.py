"""One supervisor tree per state directory (`rr_actors._supervision.statedir`, issue 16): a
lock on `<state_dir>/.lock`.

Two trees given the same `state_dir` would share their managers' backups. The second one
gets `ConfigError` naming the holder's pid; the lock goes with the holder's stop or death
(a real SIGKILL of a real process).
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import subprocess
import sys
import textwrap
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

import rr_actors as rr

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
        readable, _, _ = select.select([proc.stdout], [], [], 30.0)
        assert [proc.stdout] == readable
        assert "ready" == proc.stdout.readline().strip()
        yield proc
    finally:
        proc.kill()
        proc.wait(10.0)
        if proc.stdout is not None:
            proc.stdout.close()


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
