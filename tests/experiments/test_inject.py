"""The injector (`rr_actors_lab.experiments.inject`) when its loop fails: the faults it could not
fire are recorded, not lost."""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, cast

import rr_actors as rr
from rr_actors_lab.experiments import parse_plan
from rr_actors_lab.experiments.inject import Injector
from rr_actors_lab.experiments.plan import Trigger
from rr_actors_lab.experiments.schedule import ScheduledFault

PLAN = """\
duration = 2.0

[tree]
[[tree.children]]
name = "db"
setup = "rr_actors_lab.experiments.services:service"
"""


class _Signal(logging.Handler):
    """Sets `seen` when the injector logs that it stopped."""

    def __init__(self) -> None:
        super().__init__()
        self.seen = threading.Event()

    def emit(self, record: logging.LogRecord) -> None:
        if record.getMessage() == "the injector stopped":
            self.seen.set()


def test_faults_the_injector_could_not_wait_for_are_recorded_as_skipped() -> None:
    # A plan read by `parse_plan` cannot say this (seconds stop at 1e6); a wait this long
    # overflows `threading` (OverflowError) and used to kill the injector silently.
    never = ScheduledFault(fault=0, n=0, kind="kill_manager", target="db", at=1e10, pick=0.5)
    waiting = ScheduledFault(
        fault=1, n=0, kind="kill_manager", target="db", at=None, pick=0.5,
        trigger=Trigger(event="ChildRestarted"),
    )  # fmt: skip
    signal = _Signal()
    logging.getLogger("rr_actors.experiments").addHandler(signal)
    sup = cast("rr.Supervisor", cast("Any", None))  # never used: nothing comes due
    injector = Injector(
        sup, parse_plan(PLAN), (never, waiting), t0=time.monotonic(), wall_t0=time.time()
    )
    try:
        injector.start()
        assert signal.seen.wait(5)
    finally:
        injector.stop(timeout=5)
        logging.getLogger("rr_actors.experiments").removeHandler(signal)

    assert [(0, 1e10, True), (1, None, True)] == [
        (r.fault, r.scheduled_s, r.skipped) for r in injector.records
    ]
    assert injector.records[0].detail.startswith("not fired: the injector failed (OverflowError")
