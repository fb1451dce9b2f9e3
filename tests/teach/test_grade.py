"""A check of a student's folder (`rr_actors_lab.teach.grade`), in this process: the report,
the failure told (the rule, the violating event, a story of at most 20 steps), the
student's modules read afresh, a setup that raises said as such."""

from __future__ import annotations

from pathlib import Path

import pytest

from rr_actors_lab.experiments import check
from rr_actors_lab.teach import grade, kit
from rr_actors_lab.teach.rules import RULES


def solve(name: str, folder: Path) -> None:
    for file, text in kit.solution_files(kit.exercise(name)).items():
        (folder / file).write_text(text, encoding="utf-8")


def test_a_failure_is_told_with_its_rule_event_and_a_short_story(tmp_path: Path) -> None:
    _chosen, folder = kit.start("camera", tmp_path / "cam")

    report = grade.check_folder(folder, seeds=2)

    assert (report.passed, report.seeds, report.seeds_run) == (False, 2, 1)
    failure = report.failure
    assert failure is not None
    assert (failure.seed, failure.rule) == (1, "dependency")
    assert failure.words == kit.exercise("camera").rule
    assert failure.first_event is not None
    assert failure.first_event.endswith(
        "actions: call " + failure.message.split()[4] + " to camera/resource answered"
    )
    assert 1 <= failure.story_events <= grade.STORY
    assert failure.story[-1].endswith(f"[dependency] {failure.message}")
    assert ">>" in failure.story[-2]  # the violating step, marked
    assert failure.replay == f"rr-actors teach check {folder} --seed 1 --story"
    assert failure.run_events > failure.story_events


def test_the_students_module_is_read_again_for_each_check(tmp_path: Path) -> None:
    # The same module name (actions) in two folders, and changed in one between checks.
    _chosen, first = kit.start("camera", tmp_path / "a")
    _chosen, second = kit.start("camera", tmp_path / "b")
    solve("camera", second)

    assert not grade.check_folder(first, seeds=1).passed
    assert grade.check_folder(second, seeds=2).passed
    assert not grade.check_folder(first, seeds=1).passed
    solve("camera", first)
    report = grade.check_folder(first, seeds=2)

    assert (report.passed, report.seeds_run, report.interleavings) == (True, 2, 2)
    assert report.failure is None
    assert report.as_dict()["events"] == report.events > 0


def test_a_setup_that_raises_is_a_failure_that_says_so(tmp_path: Path) -> None:
    _chosen, folder = kit.start("camera", tmp_path / "cam")
    (folder / "actions.py").write_text(
        "def setup(registrar):\n    raise ValueError('no camera here')\n", encoding="utf-8"
    )

    report = grade.check_folder(folder, seeds=3)

    assert report.failure is not None
    assert report.failure.rule == "setup"
    assert "the tree did not start" in report.failure.message
    assert "no camera here" in report.failure.message
    assert report.seeds_run == 1


def test_one_seed_replays_its_whole_story(tmp_path: Path) -> None:
    _chosen, folder = kit.start("restarts", tmp_path / "r")

    lines = grade.replay_story(folder, 1)

    assert any("[survives]" not in line and "gave up" in line for line in lines)
    assert len(lines) > grade.STORY


@pytest.mark.timeout(180)  # (a shrink of 200 runs in the check's child: 20 CPU s)
def test_a_checkers_finding_is_told_on_the_run_shrunk_unless_asked_not_to(tmp_path: Path) -> None:
    _chosen, folder = kit.start("climb", tmp_path / "climb")

    whole = grade.check_folder(folder, seeds=1, shrink_budget=0).failure
    assert whole is not None
    assert (whole.shrunk_seed, whole.shrunk_events) == (None, None)
    assert not (folder / grade.SHRUNK).exists()
    shrunk = grade.check_folder(folder, seeds=1).failure

    assert shrunk is not None
    assert shrunk.rule == whole.rule == "status-reached"
    assert shrunk.shrunk_events is not None
    assert shrunk.shrunk_events < shrunk.run_events == whole.run_events
    assert (folder / grade.SHRUNK).read_text().startswith("# plan.toml's seed 1 shrunk")
    replayed = grade.check_folder(
        folder, seed=shrunk.shrunk_seed, plan_file=folder / grade.SHRUNK, shrink_budget=0
    ).failure
    assert replayed is not None
    assert replayed.rule == "status-reached"
    assert replayed.run_events == shrunk.shrunk_events
    solve("climb", folder)
    assert grade.check_folder(folder, seeds=1).passed
    assert not (folder / grade.SHRUNK).exists()  # (the fixed failure's plan: gone)


@pytest.mark.timeout(180)  # (a shrink of 200 runs in the check's child: 20 CPU s)
def test_a_kit_rules_finding_is_told_on_the_run_shrunk_which_breaks_it_again(
    tmp_path: Path,
) -> None:
    # survive's starter breaks `alone`, a kit rule the checker does not judge: the shrink
    # keeps a plan that breaks it (judged by the kit's rules too), and its replay does.
    _chosen, folder = kit.start("survive", tmp_path / "s")

    whole = grade.check_folder(folder, seeds=1, shrink_budget=0).failure
    shrunk = grade.check_folder(folder, seeds=1).failure

    assert whole is not None
    assert shrunk is not None
    assert shrunk.rule == whole.rule == "alone"
    assert shrunk.shrunk_events is not None
    assert shrunk.shrunk_events < whole.run_events == shrunk.run_events
    assert shrunk.story_events < whole.story_events
    assert shrunk.story[-1].endswith(f"[alone] {shrunk.message}")
    assert shrunk.replay.endswith(
        f"--plan {folder / grade.SHRUNK} --seed {shrunk.shrunk_seed} --story"
    )
    replayed = grade.check_folder(
        folder, seed=shrunk.shrunk_seed, plan_file=folder / grade.SHRUNK, shrink_budget=0
    ).failure
    assert replayed is not None
    assert (replayed.rule, replayed.message) == ("alone", shrunk.message)
    assert replayed.run_events == shrunk.shrunk_events


@pytest.mark.timeout(180)  # (a shrink of 200 runs in the check's child: 20 CPU s)
def test_a_survive_tree_that_never_restarts_a_killed_manager_fails_naming_back(
    tmp_path: Path,
) -> None:
    # The solution's strategy and intensity, but cm temporary: F4 kills it for good and
    # the mission drives on without its LiDAR; no supervisor gives up, no sibling stops.
    _chosen, folder = kit.start("survive", tmp_path / "s")
    solve("survive", folder)
    plan = (folder / "plan.toml").read_text()
    cm = 'name = "cm"\n'
    (folder / "plan.toml").write_text(plan.replace(cm, cm + 'restart = "temporary"\n'))

    report = grade.check_folder(folder, seeds=2)

    assert report.failure is not None
    assert report.failure.rule == "back"
    assert report.failure.first_event is not None
    assert "cm exited: killed by SIGKILL" in report.failure.first_event
    assert "restart type is 'temporary'" in report.failure.message


def test_an_intensity_too_high_to_stop_a_crash_loop_fails_before_any_run(
    tmp_path: Path,
) -> None:
    _chosen, folder = kit.start("restarts", tmp_path / "r")
    solve("restarts", folder)
    plan = (folder / "plan.toml").read_text()
    (folder / "plan.toml").write_text(plan.replace("max_restarts = 20 ", "max_restarts = 26 "))

    report = grade.check_folder(folder, seeds=5)

    assert (report.passed, report.seeds_run) == (False, 0)
    assert report.failure is not None
    assert report.failure.rule == "intensity-bound"
    assert "allows 26 restarts within 1 s (26 a second): above 25 a second" in (
        report.failure.message
    )


def test_a_step_that_raises_or_returns_the_wrong_type_is_said_first(tmp_path: Path) -> None:
    _chosen, folder = kit.start("climb", tmp_path / "c")
    (folder / "step.py").write_text(
        "def climb(parent, resources, status):\n"
        "    if parent is None:\n"
        "        raise KeyError('no parent')\n"
        "    return parent\n",
        encoding="utf-8",
    )

    report = grade.check_folder(folder, seeds=2, shrink_budget=0)

    assert report.failure is not None
    assert report.failure.rule == "step-raised"
    message = report.failure.message
    assert message.startswith("your climb raised ")
    assert (
        "KeyError: 'no parent' (step.py, line 3)" in message
        or "TypeError: it must return a list of resource ids (str), not '" in message
    )


def test_a_release_order_that_leaves_a_dependency_out_is_said_as_such(tmp_path: Path) -> None:
    # Every dependency and "unload", each once: one left out would be held for ever.
    _chosen, folder = kit.start("order", tmp_path / "o")
    (folder / "step.py").write_text(
        "def release_order(dependencies):\n    return ['unload']\n", encoding="utf-8"
    )

    report = grade.check_folder(folder, seeds=1, shrink_budget=0)

    assert report.failure is not None
    assert report.failure.rule == "step-raised"
    assert 'a list of every dependency id and "unload", each once' in report.failure.message


WRONG = [e.name for e in kit.exercises() if e.wrong()]


@pytest.mark.parametrize("name", WRONG)
def test_a_wrong_answer_a_student_may_write_fails_naming_the_rule_it_breaks(
    name: str, tmp_path: Path
) -> None:
    # Each exercise's second bug (its `wrong/`), beside the starter's: the check catches
    # it too, and names a rule (the checker's or the kit's), not a crash.
    chosen, folder = kit.start(name, tmp_path / name)
    for file, text in chosen.wrong().items():
        (folder / file).write_text(text, encoding="utf-8")

    report = grade.check_folder(folder, seeds=5, shrink_budget=0)

    assert not report.passed
    assert report.failure is not None
    assert report.failure.rule in (*check.RULES, *RULES), report.failure
    assert report.failure.first_event is not None
