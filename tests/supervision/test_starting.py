"""Starting a supervisor's children (`rr_actors._supervision.starting`): in start order, and
a failed start stops those already started, in reverse order."""

from __future__ import annotations

from collections.abc import Callable

import pytest

import rr_actors as rr
from tests.support.supervising import (
    logging_consumer,
)

# -- ordered start, reverse-ordered stop ----------------------------------------------------------


def test_a_failed_start_stops_the_children_already_started_in_reverse_order(
    supervisors: Callable[..., rr.Supervisor],
    uid: str,
    log_provider: tuple[rr.ResourceRegistrar, list[str]],
) -> None:
    provider, events = log_provider
    a, b, c = f"a-{uid}", f"b-{uid}", f"c-{uid}"

    def broken(_: rr.ResourceRegistrar) -> None:
        raise ValueError("no camera")

    setup = logging_consumer(provider.name, events)
    sup = supervisors(
        [rr.ManagerSpec(a, setup), rr.ManagerSpec(b, setup), rr.ManagerSpec(c, broken)]
    )

    with pytest.raises(rr.SupervisorGaveUpError, match="no camera"):
        sup.start()
    assert [f"start {a}", f"start {b}", f"unload {b}", f"unload {a}"] == events
