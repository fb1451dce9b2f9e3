"""A manager that fails to start is reported with its own error, whatever woke the wait.

The manager process sends the events it forwarded, then its `Failed` report, then exits.
A loaded parent can wake to the exit and the pipe at once: what the process sent before it
ended must still be read, in order, before its exit is taken for a death without a word.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._process.control import Events, Failed
from rr_actors._process.manager import _await_ready
from rr_actors._process.received import Received

pytestmark = pytest.mark.usefixtures("process_helpers")  # the forkserver, before the leak check


def _events_then_failed(conn: multiprocessing.connection.Connection) -> None:
    """What a manager whose setup raised sends before it exits (`_process/child.py`)."""
    conn.send(Events(["an event forwarded before the setup raised"]))
    conn.send(Failed("Traceback (most recent call last):\nValueError: no camera on this bench\n"))
    conn.close()


def test_a_failed_report_behind_events_is_read_when_the_exit_wakes_the_wait_too() -> None:
    context = multiprocessing.get_context("forkserver")
    parent_end, child_end = context.Pipe()
    process = context.Process(target=_events_then_failed, args=(child_end,), daemon=True)
    process.start()
    child_end.close()
    process.join(30)  # it ended: its exit and both messages are there at once
    assert 0 == process.exitcode
    delivered: list[Any] = []

    with pytest.raises(rr.RegistrarUnavailableError, match="no camera on this bench"):
        _await_ready("mine", process, parent_end, 30.0, Received(delivered.extend, None))

    assert ["an event forwarded before the setup raised"] == delivered
