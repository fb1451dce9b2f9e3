"""The platform tricks and their plain fallback (`rr_actors._platform`): the one chosen.

`PLATFORM` is `linux` on Linux and `portable` elsewhere or with
`RR_ACTORS_PLATFORM=portable`. Every test that uses manager processes must pass on both:
`tests/core/test_base.py` runs those modules (this one too) again, in a
subprocess on the portable platform, as part of the normal run. Tests of what only a
trick does are marked `linux_trick` (see `supervising.py`) and skipped there.
"""

from __future__ import annotations

import multiprocessing.connection
import multiprocessing.forkserver
import os
import signal
import sys
import threading
import time
from pathlib import Path

import pytest

from rr_actors._platform import PLATFORM, forkserver

_FORCED = os.environ.get("RR_ACTORS_PLATFORM") == "portable"


def test_the_platform_is_the_one_the_environment_asks_for() -> None:
    expected = "portable" if _FORCED or not sys.platform.startswith("linux") else "linux"

    assert expected == PLATFORM.name


@pytest.mark.skipif(not forkserver.SUPPORTED, reason="rr_actors' forkserver: CPython 3.11-3.13")
def test_a_start_through_a_stopped_forkserver_gives_up_within_its_bound(tmp_path: Path) -> None:
    """`forkserver.start_within`: with rr_actors' forkserver stopped (SIGSTOP: a debugger,
    a hang), a start raises `TimeoutError` once its bound ran out, not waiting for ever
    for the fork; once the server runs again it forks the next process, and the process
    that timed out never runs (its late fork is given nothing to run)."""
    ctx = forkserver.context(())
    server = forkserver.server_pid(ctx)
    assert server
    late = ctx.Process(target=(tmp_path / "late").touch, daemon=True)
    os.kill(server, signal.SIGSTOP)
    try:
        started = time.monotonic()
        with pytest.raises(TimeoutError):
            forkserver.start_within(late, 0.5)
        took = time.monotonic() - started
    finally:
        os.kill(server, signal.SIGCONT)
    then = ctx.Process(target=(tmp_path / "then").touch, daemon=True)
    forkserver.start_within(then, 30.0)
    then.join(30.0)

    assert (True, None, 0, False) == (
        0.4 <= took < 3.0,
        late.pid,
        then.exitcode,
        (tmp_path / "late").exists(),
    ), took


@pytest.mark.skipif(not forkserver.SUPPORTED, reason="rr_actors' forkserver: CPython 3.11-3.13")
def test_a_killed_process_whose_exit_two_threads_poll_at_once_was_killed_not_exit_255(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """CI of main 82548e2b, a real `simways` run: db, SIGKILLed, "ended by itself: exit
    code 255". The forkserver writes a child's exit code once, on its sentinel. Forced
    here: a join found the sentinel readable and, before it read, another thread polled
    the process (as `multiprocessing` does at every process start, the spare filler's)
    and read the code; the join then read EOF, which CPython takes for a dead server
    (255). One thread reads it: the join gets the signal."""
    ctx = forkserver.context(())
    process = ctx.Process(target=signal.pause, daemon=True)
    forkserver.start_within(process, 30.0)
    os.kill(process.pid, signal.SIGKILL)
    assert multiprocessing.connection.wait([process.sentinel], 30.0)  # (reaped, code written)
    read_signed = multiprocessing.forkserver.read_signed
    joining = threading.current_thread()

    def polled_meanwhile(fd: int) -> int:
        if threading.current_thread() is joining:  # the join is about to read: a poll first
            poller = threading.Thread(target=process.is_alive, name="test-poller")
            poller.start()
            poller.join(30.0)
            assert not poller.is_alive()
        return read_signed(fd)

    monkeypatch.setattr(multiprocessing.forkserver, "read_signed", polled_meanwhile)
    try:
        process.join(30.0)
        exitcode = process.exitcode
    finally:
        monkeypatch.undo()
        process.join(30.0)
        process.close()

    assert -signal.SIGKILL == exitcode
