"""The kit's own rules (`rr_actors.teach.rules`): `dependency` and `survives`, each on
events built here, the line numbers as a history's."""

from __future__ import annotations

from rr_actors import events
from rr_actors.teach.rules import RULES, dependency, survives


def test_a_managers_call_without_a_parent_breaks_dependency_at_its_line() -> None:
    history = [
        (1, events.CallAnswered("actions", "q-own", "camera", "resource")),
        (2, events.CallAnswered("actions", "q-dep", "camera", "resource", parent="r1")),
        (3, events.CallAnswered("client-0", "q-client", "actions", "look")),  # a client's
    ]

    found = dependency(history, {"camera", "actions"})

    assert [(f.rule, f.kind, f.lines) for f in found] == [("dependency", "violation", (1,))]
    assert "actions holds camera/resource query q-own as a call of its own" in found[0].message


def test_calls_made_while_loading_hold_dependency() -> None:
    history = [(1, events.CallAnswered("actions", "q", "camera", "resource", parent="r1"))]

    assert dependency(history, {"camera", "actions"}) == []


def test_a_give_up_breaks_survives_and_names_the_managers_for_the_story() -> None:
    gave_up = events.SupervisorGaveUp("root", "more than 2 restart(s) within 5 s", 2, 5.0)
    history = [(1, events.CallAnswered("client-0", "q", "lidar", "resource")), (7, gave_up)]

    found = survives(history, ["lidar", "planner"])

    assert [(f.rule, f.lines, f.registrars) for f in found] == [
        ("survives", (7,), ("root", "lidar", "planner"))
    ]
    assert survives(history[:1], ["lidar"]) == []


def test_the_rules_are_listed_by_name() -> None:
    assert RULES == {"dependency": dependency, "survives": survives}
