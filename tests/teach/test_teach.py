"""The kit's public seam (`rr_actors_lab.teach`): a protocol step replaced inside a block,
the registrar's own code back after it; the shipped steps as functions."""

from __future__ import annotations

import pytest

from rr_actors import ConfigError, Status
from rr_actors.config import Steps
from rr_actors_lab.teach import STEPS, replaced_step, shipped_step


def test_the_shipped_climb_goes_to_the_parent_it_serves_whatever_the_status() -> None:
    climb = shipped_step("climb")

    for status in Status:
        assert list(climb("r1", {"r1", "r2"}, status)) == ["r1"]
    assert list(climb("gone", {"r1"}, Status.FATAL)) == []
    assert list(climb(None, {"r1"}, Status.WARNING)) == []


def test_the_shipped_share_test_matches_equal_live_requests_loading_or_not() -> None:
    shares = shipped_step("shares")

    assert shares({"scan": 1}, {"scan": 1}, True, False)
    assert shares("front", "front", False, False)
    assert not shares("front", "front", False, True)  # reported FATAL: never again
    assert not shares("front", "back", False, False)


def test_the_shipped_group_is_the_supervisors_own_for_every_strategy() -> None:
    from rr_actors._supervision.children import affected  # noqa: PLC0415 - the supervisor's

    group = shipped_step("group")
    names = ("a", "b", "c")

    for strategy in ("one_for_one", "one_for_all", "rest_for_one"):
        for crashed in names:
            expected = affected(strategy, names, crashed)  # type: ignore[arg-type]
            assert tuple(group(strategy, names, crashed)) == expected
    assert tuple(group("rest_for_one", names, "b")) == ("b", "c")


def test_the_shipped_unloads_unloads_when_no_consumer_id_is_left() -> None:
    unloads = shipped_step("unloads")

    assert unloads(frozenset())
    assert not unloads(frozenset({"q1"}))
    assert not unloads(frozenset({"q1", "q2"}))


def test_the_shipped_in_doubt_is_every_row_not_committed_loaded() -> None:
    in_doubt = shipped_step("in_doubt")

    assert [in_doubt(s) for s in ("loading", "loaded", "unloading")] == [True, False, True]


def test_the_shipped_reconcile_releases_what_the_consumer_dropped_and_names_what_was_lost() -> None:
    reconcile = shipped_step("reconcile")

    release, unknown = reconcile(frozenset({"a", "b"}), frozenset({"b", "c", "d"}), {"d"})

    assert (release, unknown) == ({"a"}, {"c"})  # d: its load is under way here


def test_the_shipped_release_order_releases_every_dependency_before_the_unload() -> None:
    assert shipped_step("release_order")(("q1", "q2")) == ["q1", "q2", "unload"]


def test_the_shipped_recent_counts_the_restarts_within_the_period_this_one_included() -> None:
    from rr_actors._supervision.policy import RestartIntensity  # noqa: PLC0415 - its own

    recent = shipped_step("recent")
    times = (0.0, 0.3, 0.6, 0.7, 1.05)
    clock = iter(times)
    intensity = RestartIntensity(2, 0.5, clock=lambda: next(clock))

    for i, now in enumerate(times):
        assert intensity.add() == (recent(times[: i + 1], now, 0.5) <= 2)
        assert recent(times[: i + 1], now, 0.5) == intensity.recent
    assert recent((0.0, 0.5), 0.5, 0.5) == 1  # (0.5 s old: out of a 0.5 s period)


def test_a_replaced_step_is_a_record_handed_to_the_simulated_runs_of_its_block_only() -> None:
    from rr_actors_lab.experiments.simulate import steps_now  # noqa: PLC0415 - what runs read

    def mine(parent: str | None, resources: object, status: Status) -> list[str]:
        return []

    with replaced_step("climb", mine) as steps:
        assert (steps.climb, steps_now()) == (mine, steps)
        with pytest.raises(ConfigError, match="is replaced already"), replaced_step("climb", mine):
            pass
        with replaced_step("unloads", lambda left: not left) as both:
            assert (both.climb, both.unloads is not None) == (mine, True)
    assert steps_now() == Steps()
    with pytest.raises(RuntimeError), replaced_step("shares", lambda *a: True):
        raise RuntimeError
    assert steps_now() == Steps()


def test_bad_steps_are_refused() -> None:
    with pytest.raises(
        ConfigError, match=r"no protocol step 'clim'; did you mean 'climb'\? \(known: "
    ):
        shipped_step("clim")
    with pytest.raises(ConfigError, match=r"must be a function"), replaced_step("climb", 3):  # type: ignore[arg-type]
        pass
    assert set(STEPS) == {
        "climb",
        "group",
        "in_doubt",
        "recent",
        "reconcile",
        "release_order",
        "shares",
        "unloads",
    }
