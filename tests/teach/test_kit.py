"""The exercises and a student's folder (`rr_actors_lab.teach.kit`)."""

from __future__ import annotations

import ast
import json
import tomllib
from pathlib import Path

import pytest

from rr_actors import ConfigError
from rr_actors_lab.experiments.reading import load_plan
from rr_actors_lab.experiments.shrink import dump_plan
from rr_actors_lab.teach import STEPS, kit
from rr_actors_lab.teach.rules import FAULTS, RULES


@pytest.mark.parametrize("chosen", kit.exercises(), ids=lambda e: e.name)
def test_each_exercise_is_whole(chosen: kit.Exercise, tmp_path: Path) -> None:
    # A README, a plan the simulation runs, hints, the rules and step it names known, a
    # solution that changes something, every Python file of it parsing.
    assert chosen.readme().startswith(f"# Exercise: {chosen.name}\n")
    assert "plan.toml" in chosen.starter()
    assert chosen.hints
    assert chosen.seeds >= 200
    assert set(chosen.rules) <= {*RULES, FAULTS}
    assert set(chosen.options) <= set(chosen.rules)
    assert set(kit.solution_files(chosen)) <= {
        *chosen.yours.files,
        *(["plan.toml"] if chosen.yours.plan else []),
    }  # (the solution changes only what is the student's)
    assert (chosen.step in STEPS) if chosen.kind == "protocol" else chosen.step is None
    changed = kit.solution_files(chosen)
    assert changed
    assert all(chosen.starter()[name] != text for name, text in changed.items())
    for name, text in chosen.solution().items():
        (tmp_path / name).write_text(text, encoding="utf-8")
        if name.endswith(".py"):
            ast.parse(text)
    load_plan(tmp_path / "plan.toml")
    wrong = chosen.wrong()  # (optional) a second bug: neither the starter nor the solution
    assert not wrong or (wrong != chosen.starter() and wrong != chosen.solution())
    for name, text in wrong.items():
        if name.endswith(".py"):
            ast.parse(text)


def test_an_unknown_name_says_the_closest_ones_and_the_list() -> None:
    with pytest.raises(ConfigError, match=r"no exercise 'shar'; did you mean 'share'"):
        kit.exercise("shar")
    with pytest.raises(ConfigError, match=r"no exercise 'zzz' \(`rr-actors teach list`"):
        kit.exercise("zzz")


def test_start_writes_the_state_and_refuses_a_file(tmp_path: Path) -> None:
    chosen, folder = kit.start("climb", tmp_path / "c")

    state = json.loads((folder / kit.STATE).read_text())
    assert state == {"exercise": "climb", "hints_shown": 0}
    assert kit.folder_exercise(folder)[0] == chosen
    (tmp_path / "file").write_text("x")
    with pytest.raises(ConfigError, match="exists and is not an empty folder"):
        kit.start("climb", tmp_path / "file")


def test_a_broken_state_file_is_said(tmp_path: Path) -> None:
    (tmp_path / kit.STATE).write_text("{not json")

    with pytest.raises(ConfigError, match=r"not JSON .*: not an exercise's state file"):
        kit.folder_exercise(tmp_path)


def test_the_hints_run_out_without_counting_further(tmp_path: Path) -> None:
    _chosen, folder = kit.start("camera", tmp_path / "c")
    count = len(kit.exercise("camera").hints)

    said = [kit.next_hint(folder)[1:] for _ in range(count + 2)]

    assert [n for n, _ in said] == [*range(1, count + 1), count, count]
    assert [t for _, t in said][-2:] == [None, None]
    assert json.loads((folder / kit.STATE).read_text())["hints_shown"] == count


def test_a_state_file_whose_count_is_no_count_is_said(tmp_path: Path) -> None:
    (tmp_path / kit.STATE).write_text('{"exercise": "camera", "hints_shown": "x"}')

    with pytest.raises(ConfigError, match=r"hints_shown is not a count: 'x'"):
        kit.next_hint(tmp_path)


def test_a_folder_as_started_or_solved_changed_nothing_that_is_not_the_students(
    tmp_path: Path,
) -> None:
    for chosen in kit.exercises():
        _chosen, folder = kit.start(chosen.name, tmp_path / chosen.name)
        assert kit.changed(chosen, folder) is None
        for name, text in kit.solution_files(chosen).items():
            (folder / name).write_text(text, encoding="utf-8")
        assert kit.changed(chosen, folder) is None, chosen.name


def test_a_plans_comments_layout_and_the_students_tree_are_free_the_rest_is_not(
    tmp_path: Path,
) -> None:
    chosen, folder = kit.start("survive", tmp_path / "s")
    plan = folder / "plan.toml"
    text = plan.read_text()
    plan.write_text("# mine\n" + text.replace(" = ", "=").replace('"one_for_all"', '"one_for_one"'))
    assert kit.changed(chosen, folder) is None
    data = tomllib.loads(text)
    tree = data["tree"]
    tree["children"] = [  # (nested, in another order, a restart type: the student's)
        {"name": "inner", "strategy": "one_for_all", "children": tree["children"][1:]},
        {**tree["children"][0], "restart": "transient"},
    ]
    plan.write_text(dump_plan(data))
    assert kit.changed(chosen, folder) is None
    tree["children"][1]["heartbeat"] = False
    plan.write_text(dump_plan(data))
    assert kit.changed(chosen, folder) == (
        "plan.toml: [[tree.children]] erm's heartbeat differs from the shipped exercise (a "
        "manager's restart and place are yours); only [tree] of plan.toml is yours to change "
        "(`rr-actors teach start survive FOLDER` shows it)"
    )
    del tree["children"][1]
    plan.write_text(dump_plan(data))
    assert kit.changed(chosen, folder).startswith(
        "plan.toml: [[tree.children]] erm is missing (the shipped exercise has it)"
    )


def test_a_change_is_named_by_its_table_and_key(tmp_path: Path) -> None:
    chosen, folder = kit.start("cut", tmp_path / "c")
    plan = folder / "plan.toml"
    data = tomllib.loads(plan.read_text())
    tail = "; only [hosts] resolve of plan.toml is yours to change (`rr-actors teach start cut"
    cases = [
        ({"hosts": {**data["hosts"], "resolve": "majority"}}, None),
        ({"hosts": {**data["hosts"], "lease": 5.0}}, "plan.toml: [hosts] lease differs"),
        ({"duration": 9.0}, "plan.toml: duration differs"),
        ({"faults": [{**data["faults"][0], "for": 0.1}]}, "plan.toml: [[faults]] for differs"),
        ({"faults": []}, "plan.toml: [[faults]] differs"),
        (
            {"compare": {"setting": "x", "values": [1]}},
            "plan.toml: [compare] is not in the shipped",
        ),
    ]
    for change, said in cases:
        plan.write_text(dump_plan(data | change))
        found = kit.changed(chosen, folder)
        assert found == said if said is None else (found or "").startswith(said), found
        assert said is None or tail in (found or "")
    (folder / "plan.toml").write_text("[tree\n")  # (no plan at all: its reading names the line)
    assert kit.changed(chosen, folder) is None
