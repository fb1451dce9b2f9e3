"""The control pipe's vocabulary: every message pickles, and each end handles what it gets."""

from __future__ import annotations

import pickle
import typing

import pytest

from rr_actors._process import child, control, manager
from rr_actors.config import RegistrarConfig

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
