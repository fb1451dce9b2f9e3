"""The control pipe's vocabulary: every message pickles, and each end handles what it gets;
how manager processes start (rr_actors chooses; `set_start_method` does not change it)."""

from __future__ import annotations

import multiprocessing
import os
import pathlib
import pickle
import sys
import textwrap
import typing

import pytest

from rr_actors._process import child, control, manager
from rr_actors.config import RegistrarConfig
from tests.support.python import python
from tests.support.supervising import linux_trick

EXAMPLES = [
    control.WarmUp(),
    control.Start(b"setup", RegistrarConfig(name="erm"), None, forward=True),
    control.Ping(3),
    control.Forward(on=True),
    control.SyncEvents(7, 1.5),
    control.Stop(2.0, restarting=True),
    control.Warm(),
    control.Ready(1234),
    control.Failed("Traceback ..."),
    control.Pong(3, (1.25, "EMFILE")),
    control.Events([]),
    control.EventsSynced(7),
]


@pytest.mark.parametrize("message", EXAMPLES, ids=lambda m: type(m).__name__)
def test_a_control_message_crosses_the_pipe_unchanged(message: object) -> None:
    assert message == pickle.loads(pickle.dumps(message))


def test_the_child_handles_every_message_of_the_parent_but_the_ones_standby_reads() -> None:
    sent_by_parent = set(typing.get_args(control.FromParent))

    assert sent_by_parent - {control.WarmUp, control.Start} == set(child._HANDLERS)


def test_the_parent_handles_every_message_a_running_manager_sends() -> None:
    sent_by_child = set(typing.get_args(control.FromChild))
    before_it_runs = {control.Warm, control.Ready, control.Failed}  # (_await_ready's)

    assert sent_by_child - before_it_runs == set(manager._HANDLERS)


# -- how manager processes start: rr_actors chooses; `set_start_method` does not change it ------

SCRIPT = textwrap.dedent(
    """
    import multiprocessing, os
    import rr_actors as rr

    def main():
        multiprocessing.set_start_method({method!r})
        sup = rr.Supervisor([rr.ManagerSpec("m", lambda r: None, isolation="process")])
        with sup:
            parent = sup.run_in("m", lambda registrar: os.getppid())
        print("forked by this process" if parent == os.getpid() else "forked elsewhere")

    if __name__ == "__main__":
        main()
    """
)


@pytest.mark.skipif(
    "forkserver" not in multiprocessing.get_all_start_methods(), reason="needs a forkserver"
)
@pytest.mark.parametrize("method", ["spawn", "fork"])
def test_a_start_method_set_by_the_program_does_not_change_how_managers_start(
    method: str,
) -> None:
    result = python("-c", SCRIPT.format(method=method), timeout=60)

    assert (0, "forked elsewhere\n") == (result.returncode, result.stdout), result.stderr


FORKSERVER_FIRST = textwrap.dedent(
    """
    import multiprocessing, os, signal
    import rr_actors as rr

    def forker_preload(registrar):
        # in the manager process: what the process that forked it imported beforehand
        with open(f"/proc/{os.getppid()}/cmdline", "rb") as f:
            command = f.read().decode(errors="replace")
        with open(f"/proc/{os.getppid()}/maps") as f:
            maps = f.read()
        return ("rr_actors._process.child" in command, "_sqlite3" in maps)

    def main():
        program = multiprocessing.get_context("forkserver")  # the program's, first
        first = program.Process(target=os.getpid)
        first.start()
        first.join(30)
        sup = rr.Supervisor([rr.ManagerSpec("m", lambda r: None, isolation="process")])
        with sup:
            print("started", sup.run_in("m", forker_preload))
            os.kill(sup.child("m").pid, signal.SIGKILL)
            sup.wait_restarted("m", timeout=30)
            print("restarted", sup.run_in("m", forker_preload))
        again = program.Process(target=os.getpid)
        again.start()
        again.join(30)
        print("the program's forkserver still forks:", again.exitcode == 0)

    if __name__ == "__main__":
        main()
    """
)


@linux_trick
@pytest.mark.skipif(
    "forkserver" not in multiprocessing.get_all_start_methods(), reason="needs a forkserver"
)
def test_managers_are_forked_preloaded_when_the_program_started_its_forkserver_first() -> None:
    """Issue 34 item 6: the program's forkserver, started first, never got rr_actors'
    preload, and managers were forked from it: each (re)start imported rr_actors."""
    result = python("-c", FORKSERVER_FIRST, timeout=90)

    assert (0, result.stdout.splitlines()) == (
        result.returncode,
        [
            "started (True, True)",
            "restarted (True, True)",
            "the program's forkserver still forks: True",
        ],
    ), result.stderr


READY_FIRST = textwrap.dedent(
    """
    import os
    from rr_actors._process import control
    from rr_actors.testing import start_forkserver

    control.preload(["imported_last"])  # (after rr_actors' own preload, in the server)
    start_forkserver()
    print("imported" if os.path.exists({marker!r}) else "not yet")
    """
)


@pytest.mark.skipif(
    "forkserver" not in multiprocessing.get_all_start_methods(), reason="needs a forkserver"
)
def test_start_forkserver_returns_once_the_server_has_imported_its_preload(
    tmp_path: pathlib.Path,
) -> None:
    """Issue 69 goal 3: it returned once the server was spawned, so the first manager
    (a benchmark's clock) still waited for the server's imports."""
    marker = tmp_path / "imported"
    (tmp_path / "imported_last.py").write_text(f"open({str(marker)!r}, 'w').close()\n")
    script = READY_FIRST.format(marker=str(marker))
    path = os.pathsep.join([str(tmp_path), *sys.path])  # (the server's imports: its env's)

    result = python("-c", script, timeout=180, env={**os.environ, "PYTHONPATH": path})

    assert (0, "imported\n") == (result.returncode, result.stdout), result.stderr
