"""The exercises and a student's folder (`rr_actors_lab.teach.kit`)."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest

from rr_actors import ConfigError
from rr_actors_lab.experiments.reading import load_plan
from rr_actors_lab.teach import STEPS, kit
from rr_actors_lab.teach.rules import RULES


@pytest.mark.parametrize("chosen", kit.exercises(), ids=lambda e: e.name)
def test_each_exercise_is_whole(chosen: kit.Exercise, tmp_path: Path) -> None:
    # A README, a plan the simulation runs, hints, the rules and step it names known, a
    # solution that changes something, every Python file of it parsing.
    assert chosen.readme().startswith(f"# Exercise: {chosen.name}\n")
    assert "plan.toml" in chosen.starter()
    assert chosen.hints
    assert chosen.seeds >= 200
    assert set(chosen.rules) <= set(RULES)
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
