"""The fault schedule (`rr_actors_lab.experiments.schedule`): a pure function of the plan and the
seed."""

from __future__ import annotations

import dataclasses

import pytest

from rr_actors.errors import ConfigError
from rr_actors_lab.experiments import fault_schedule, parse_plan
from rr_actors_lab.experiments.plan import FaultPlan

SERVICE = "rr_actors_lab.experiments.services:service"

TREE = f"""\
duration = 10.0

[tree]
[[tree.children]]
name = "a"
setup = "{SERVICE}"
[[tree.children]]
name = "b"
setup = "{SERVICE}"
"""


def schedule(faults: str, seed: int = 1) -> list[tuple[str, str | None, float | None]]:
    plan = parse_plan(TREE + faults)
    return [(f.kind, f.target, f.at) for f in fault_schedule(plan, seed)]


RANDOM = (
    '[[faults]]\nkind = "kill_manager"\ntarget = ["a", "b"]\nevery = { min = 0.5, max = 1.5 }\n'
)


def test_the_same_seed_gives_the_same_schedule() -> None:
    assert schedule(RANDOM, seed=7) == schedule(RANDOM, seed=7)


def test_another_seed_gives_another_schedule() -> None:
    assert schedule(RANDOM, seed=7) != schedule(RANDOM, seed=8)


def test_random_intervals_stay_within_their_bounds_and_the_run() -> None:
    times = [at for _, _, at in schedule(RANDOM, seed=3)]
    assert all(at is not None for at in times)
    gaps = [b - a for a, b in zip([0.0, *times[:-1]], times, strict=True)]  # type: ignore[operator]

    assert all(0.5 <= gap <= 1.5 for gap in gaps)
    assert times[-1] < 10.0  # type: ignore[operator]
    assert len(times) >= 6


def test_a_fixed_interval_starts_one_interval_after_start_and_stops_at_stop() -> None:
    faults = (
        '[[faults]]\nkind = "kill_manager"\ntarget = "a"\nevery = 1.0\nstart = 0.5\nstop = 4.0\n'
    )

    assert [0.5 + 1.0 * n for n in range(1, 4)] == [at for _, _, at in schedule(faults)]


def test_count_limits_the_injections_of_a_fault() -> None:
    faults = '[[faults]]\nkind = "kill_manager"\ntarget = "a"\nevery = 1.0\ncount = 2\n'

    assert [1.0, 2.0] == [at for _, _, at in schedule(faults)]


def test_adding_a_fault_does_not_move_the_others() -> None:
    extra = '[[faults]]\nkind = "load_error"\ntarget = "b"\nevery = { min = 0.1, max = 0.2 }\n'

    alone = schedule(RANDOM, seed=5)
    together = [s for s in schedule(RANDOM + extra, seed=5) if s[0] == "kill_manager"]

    assert alone == together


def test_faults_of_several_entries_are_sorted_by_time() -> None:
    faults = (
        '[[faults]]\nkind = "kill_manager"\ntarget = "a"\nat = [3.0, 1.0]\n'
        '[[faults]]\nkind = "cut_connections"\ntarget = "b"\nat = 2.0\n'
    )

    assert [1.0, 2.0, 3.0] == [at for _, _, at in schedule(faults)]


def test_a_triggered_fault_has_its_trigger_and_no_time() -> None:
    faults = (
        '[[faults]]\nkind = "kill_manager"\ntarget = "a"\n'
        'after = { event = "ChildRestarted", child = "b", nth = 2 }\ndelay = 2.0\n'
    )
    plan = parse_plan(TREE + faults)

    (only,) = fault_schedule(plan, 1)

    assert (None, 2.0) == (only.at, only.delay)
    assert only.trigger is not None
    assert ("ChildRestarted", {"child": "b"}, 2) == (
        only.trigger.event,
        dict(only.trigger.match),
        only.trigger.nth,
    )


def test_a_plan_built_by_hand_with_a_tiny_interval_is_refused_not_scheduled_forever() -> None:
    plan = parse_plan(TREE)
    tiny = dataclasses.replace(
        plan, faults=(FaultPlan(kind="kill_manager", targets=("a",), every=1e-6),)
    )

    with pytest.raises(ConfigError, match=r"faults\[0\] could inject more than 100000 times"):
        fault_schedule(tiny, 1)


def test_an_interval_of_a_millisecond_over_a_long_run_ends() -> None:
    plan = parse_plan(TREE.replace("duration = 10.0", "duration = 1e6"))
    fault = FaultPlan(kind="kill_manager", targets=("a",), every=0.001, start=999_990.0)

    times = fault_schedule(dataclasses.replace(plan, faults=(fault,)), 1)

    assert 9999 <= len(times) <= 10000
    assert all(999_990.0 < f.at < 1e6 for f in times if f.at is not None)
