"""The trigger process (`rr_actors_lab.experiments._trigger`): signals leave at their due time,
through the pidfd they were given."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator

import pytest

from rr_actors_lab.experiments.inject import Trigger


@pytest.fixture
def trigger() -> Iterator[Trigger]:
    made = Trigger()
    yield made
    made.close(timeout=5.0)


@pytest.fixture
def sleeper() -> Iterator[subprocess.Popen[bytes]]:
    body = "import time; time.sleep(30)"  # allowed: the target lives until killed; no wait
    process = subprocess.Popen([sys.executable, "-c", body])
    yield process
    process.kill()
    process.wait()


def sent(trigger: Trigger, due: float, signum: int, pidfd: int) -> tuple[float, int]:
    """Ask the trigger to send `signum` through `pidfd` at `due`; wait for its reply."""
    replies: list[tuple[float, int]] = []
    done = threading.Event()

    def on_sent(at: float, code: int) -> None:
        replies.append((at, code))
        done.set()

    trigger.send(due, signum, pidfd, on_sent)
    assert done.wait(5.0)
    return replies[0]


def test_a_signal_leaves_at_its_due_time_not_before(
    trigger: Trigger, sleeper: subprocess.Popen[bytes]
) -> None:
    due = time.monotonic() + 0.05
    pidfd = os.pidfd_open(sleeper.pid)
    try:
        at, code = sent(trigger, due, signal.SIGKILL, pidfd)
    finally:
        os.close(pidfd)

    assert 0 == code
    assert due <= at < due + 1.0  # never early; how late depends on the machine (benchmarks)
    assert -signal.SIGKILL == sleeper.wait(5.0)


def test_a_signal_for_a_process_that_is_gone_comes_back_as_an_error(
    trigger: Trigger, sleeper: subprocess.Popen[bytes]
) -> None:
    pidfd = os.pidfd_open(sleeper.pid)  # keeps meaning that process, even once reaped
    try:
        sleeper.kill()
        sleeper.wait(5.0)

        reply = sent(trigger, time.monotonic(), signal.SIGKILL, pidfd)
    finally:
        os.close(pidfd)

    assert (0.0, errno.ESRCH) == reply
