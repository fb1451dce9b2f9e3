"""The plan reader's generic decode and its rules: messages that name what is allowed."""

from __future__ import annotations

import pytest

from rr_actors.experiments import PlanError, _lines, parse_plan
from rr_actors.experiments._lines import key_lines

BASE = """\
name = "t"
description = '''
a text of
[several] lines
'''
duration = 2.0

[tree]

[[tree.children]]
name = "db"
setup = "rr_actors.experiments.services:service"

[[faults]]
kind = "kill_manager"
target = "db"
at = 1.0
"""


def plan_error(text: str) -> PlanError:
    with pytest.raises(PlanError) as caught:
        parse_plan(text, source="plan.toml")
    return caught.value


def test_a_fault_key_of_another_kind_names_the_kinds_it_goes_with() -> None:
    error = plan_error(BASE + "for = 1.0\n")

    assert (18, "faults[0].for") == (error.line, error.key)
    only = "'hang_manager' or 'load_error' or 'cut' or 'partition' or 'freeze'"
    assert f"does not go with kind 'kill_manager' (only {only})" == error.problem


def test_a_trigger_status_of_the_wrong_type_names_the_statuses() -> None:
    error = plan_error(BASE.replace("at = 1.0", 'after = { event = "StatusSent", status = 3 }'))

    assert (17, "faults[0].after.status") == (error.line, error.key)
    assert error.problem.startswith("must be one of 'OK', 'UPDATE', 'WARNING', 'ERROR', 'FATAL'")


def test_a_key_after_a_multi_line_string_has_its_own_line() -> None:
    error = plan_error(BASE.replace("duration = 2.0", "duration = -2.0"))

    assert (6, "duration") == (error.line, error.key)
    assert 2 == key_lines(BASE)[("description",)]


def test_a_name_is_unique_in_the_whole_tree_the_top_supervisor_included() -> None:
    text = BASE.replace(
        '[[tree.children]]\nname = "db"',
        '[[tree.children]]\nname = "mid"\n\n[[tree.children.children]]\nname = "top"',
    )
    error = plan_error(text.replace("[tree]", '[tree]\nname = "top"'))

    assert (15, "tree.children[0].children[0].name") == (error.line, error.key)
    assert "the name 'top' is used twice in the tree" == error.problem


def test_an_error_deep_in_a_long_plan_names_its_line_in_a_few_parses(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    padding = "".join(f"# note {n}\n" for n in range(20_000))
    text = BASE.replace("[tree]\n", f"[tree]\n{padding}").replace("at = 1.0", 'at = "soon"')
    expected_line = text.splitlines().index('at = "soon"') + 1
    tries: list[int] = []  # the number of lines of each text the reader parses to find the line
    holds = _lines._holds

    def counted(rows: list[str], path: _lines.KeyPath) -> bool:
        tries.append(len(rows))
        return holds(rows, path)

    monkeypatch.setattr(_lines, "_holds", counted)

    with pytest.raises(PlanError) as info:
        parse_plan(text)

    assert expected_line == info.value.line
    # bisection: at most log2(20,030) < 15 tries for each of the 3 key paths
    # ("faults", 0, "at") and its starts, not one try per line
    assert 0 < len(tries) <= 3 * 15, len(tries)
