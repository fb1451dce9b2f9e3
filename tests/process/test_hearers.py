"""Which manager processes hear a registrar's (re)start (`rr_actors._process.hearers`): the
parent's index of its manager processes' monitors."""

from __future__ import annotations

from rr_actors._core import runtime
from rr_actors._process.hearers import Hearers


class Handle:
    """A manager process's handle as the index sees it: the starts it was told, in order."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.exited = runtime.Event()
        self.told: list[str] = []

    def tell_started(self, name: str) -> None:
        self.told.append(name)


def test_a_start_is_told_to_the_processes_that_monitor_it_and_those_hearing_everything() -> None:
    index = Hearers()
    caller, restored, idle = Handle("caller"), Handle("restored"), Handle("idle")
    index.monitoring(caller, ("x",), at=runtime.monotonic())
    index.hears_all(restored, on=True, at=runtime.monotonic())
    index.monitoring(idle, ("y",), at=runtime.monotonic())
    assert [caller, restored] == index.announce("x")


def test_a_report_stamped_before_an_announcement_it_arrives_after_is_told_of_it_once() -> None:
    index = Hearers()
    late = Handle("late")
    stamp = runtime.monotonic()  # (read by its process before it recorded the monitor)
    assert [] == index.announce("x")
    index.monitoring(late, ("x", "y"), at=stamp)
    assert ["x"] == late.told
    assert [late] == index.announce("x")


def test_a_report_stamped_after_the_last_announcement_is_told_nothing_old() -> None:
    index = Hearers()
    index.announce("x")
    later = Handle("later")
    index.monitoring(later, ("x",), at=runtime.monotonic() + 1.0)
    index.hears_all(later, on=True, at=runtime.monotonic() + 1.0)
    assert [] == later.told


def test_a_process_that_ended_is_told_nothing_even_when_its_report_is_read_after() -> None:
    index = Hearers()
    gone = Handle("gone")
    index.monitoring(gone, ("x",), at=runtime.monotonic())
    index.hears_all(gone, on=True, at=runtime.monotonic())
    gone.exited.set()
    index.forget(gone)
    index.monitoring(gone, ("z",), at=runtime.monotonic())  # (read from its pipe after)
    assert [] == index.announce("x")
    assert [] == index.announce("z")


def test_a_process_that_no_longer_hears_everything_hears_only_what_it_monitors() -> None:
    index = Hearers()
    swept = Handle("swept")
    index.hears_all(swept, on=True, at=runtime.monotonic())
    index.monitoring(swept, ("x",), at=runtime.monotonic())
    index.hears_all(swept, on=False, at=runtime.monotonic())
    assert ([], [swept]) == (index.announce("y"), index.announce("x"))
