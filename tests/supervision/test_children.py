"""What happens when a child exits on its own: OTP's restart types and strategies, decided
in one place (`decide`), against OTP's `supervisor.erl` table."""

from __future__ import annotations

import pytest

from rr_actors._supervision.children import Decision, decide

TREE = [("a", "permanent"), ("b", "transient"), ("c", "temporary"), ("d", "permanent")]


@pytest.mark.parametrize(
    ("crashed", "normal", "stays_down"),
    [
        ("a", True, False),  # permanent: always back
        ("a", False, False),
        ("b", True, True),  # transient: back after an abnormal exit only
        ("b", False, False),
        ("c", True, True),  # temporary: never
        ("c", False, True),
    ],
)
def test_the_crashed_child_s_restart_type_and_exit_decide_whether_anything_comes_back(
    crashed: str, normal: bool, stays_down: bool
) -> None:
    decision = decide("one_for_one", TREE, crashed, normal=normal)

    if stays_down:
        assert Decision((), frozenset()) == decision
    else:
        assert Decision((crashed,), frozenset({crashed})) == decision


@pytest.mark.parametrize(
    ("strategy", "group", "back"),
    [
        ("one_for_one", ("b",), {"b"}),
        ("one_for_all", ("a", "b", "c", "d"), {"a", "b", "d"}),  # (c, temporary: for good)
        ("rest_for_one", ("b", "c", "d"), {"b", "d"}),
    ],
)
def test_the_strategy_takes_down_a_group_in_start_order_of_which_all_but_temporary_come_back(
    strategy: str, group: tuple[str, ...], back: set[str]
) -> None:
    decision = decide(strategy, TREE, "b", normal=False)  # type: ignore[arg-type]

    assert Decision(group, frozenset(back)) == decision


def test_a_classroom_s_group_step_chooses_the_group_kept_in_start_order() -> None:
    def reversed_rest(strategy: str, names: object, crashed: str) -> list[str]:
        return ["d", "c", crashed]  # (any order: the decision keeps start order)

    decision = decide("one_for_one", TREE, "c", normal=False, group=reversed_rest)
    assert Decision((), frozenset()) == decision  # (temporary: the step is not asked)
    decision = decide("one_for_one", TREE, "a", normal=False, group=reversed_rest)
    assert Decision(("a", "c", "d"), frozenset({"a", "d"})) == decision
