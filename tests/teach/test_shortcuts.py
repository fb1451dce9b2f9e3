"""Answers that skip the exercise do not pass (issue 70): what a student may not change is
the shipped one when checked (a change refused in one line naming it); each exercise's
rules judge what it teaches (an action's resource holds the camera, the faults happen, a
recalibration warns); a student's code cannot reach the kit (its grader, the registrar's
own steps, the solutions) nor put another step in its place. Every shortcut, on every
exercise it applies to."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest

from rr_actors import ConfigError
from rr_actors_lab.experiments.shrink import dump_plan
from rr_actors_lab.teach import grade, kit

EXERCISES = kit.exercises()
NAMES = [e.name for e in EXERCISES]
PROTOCOL = [e.name for e in EXERCISES if e.kind == "protocol"]
MODULES = [e.name for e in EXERCISES if e.kind == "use" and e.yours.files]
TREES = [e.name for e in EXERCISES if "tree" in e.yours.plan]


def solved(name: str, folder: Path) -> Path:
    """`name` started in `folder` and solved (its shipped solution's files written)."""
    kit.start(name, folder)
    for file, text in kit.solution_files(kit.exercise(name)).items():
        (folder / file).write_text(text, encoding="utf-8")
    return folder


def edit_plan(folder: Path, change: dict[str, object], *, drop: str | None = None) -> None:
    data = tomllib.loads((folder / "plan.toml").read_text(encoding="utf-8"))
    data |= change
    if drop is not None:
        data.pop(drop, None)
    (folder / "plan.toml").write_text(dump_plan(data), encoding="utf-8")


def refused(folder: Path, match: str) -> None:
    with pytest.raises(ConfigError, match=match) as raised:
        grade.check_folder(folder, seeds=2, shrink_budget=0)
    assert "\n" not in str(raised.value)  # (one line)


# -- the four, each as it was reported -----------------------------------------------


def test_camera_actions_that_never_hold_the_camera_fail_naming_holds(tmp_path: Path) -> None:
    folder = solved("camera", tmp_path / "camera")
    text = (folder / "actions.py").read_text()
    text = text.replace('camera = registrar.call("camera", "resource", "front")', "")
    text = text.replace("camera.response", '"front"')
    (folder / "actions.py").write_text(text)

    report = grade.check_folder(folder, seeds=3, shrink_budget=0)

    assert not report.passed
    assert report.failure is not None
    assert report.failure.rule == "holds"
    assert "made no call to camera" in report.failure.message


def test_restarts_with_its_faults_deleted_and_the_starter_tree_kept_is_refused(
    tmp_path: Path,
) -> None:
    folder = tmp_path / "restarts"
    kit.start("restarts", folder)
    edit_plan(folder, {}, drop="faults")

    refused(
        folder,
        r"^\S+: plan.toml: \[\[faults\]\] is missing \(the shipped exercise has it\); only "
        r"\[tree\] of plan.toml is yours to change",
    )


def test_refcount_with_the_starters_bug_and_nothing_shared_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "refcount"
    kit.start("refcount", folder)
    plan = (folder / "plan.toml").read_text()
    (folder / "plan.toml").write_text(plan.replace("shared = 1.0", "shared = 0.0"))

    refused(
        folder,
        r"plan.toml: \[\[workload.calls\]\] shared differs from the shipped exercise; only "
        r"step.py is yours to change",
    )


def test_a_step_that_borrows_the_registrars_own_through_shipped_step_is_refused(
    tmp_path: Path,
) -> None:
    folder = tmp_path / "refcount"
    kit.start("refcount", folder)
    (folder / "step.py").write_text(
        "from rr_actors_lab.teach import shipped_step\n\nunloads = shipped_step('unloads')\n"
    )

    refused(folder, r"step.py does not import: ImportError: rr_actors_lab.teach is the classroom")


# -- on every exercise -----------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_a_shorter_run_or_a_workload_of_ones_own_is_refused(name: str, tmp_path: Path) -> None:
    folder = solved(name, tmp_path / name)
    data = tomllib.loads((folder / "plan.toml").read_text())
    edit_plan(folder, {"duration": 0.1})

    refused(folder, r"plan.toml: duration differs from the shipped exercise; only ")
    if "workload" in data:
        edit_plan(folder, {"duration": data["duration"], "workload": {"clients": 0}})
        refused(folder, r"plan.toml: \[workload\] clients differs from the shipped exercise")


@pytest.mark.parametrize(
    "name", [e.name for e in EXERCISES if "faults" in tomllib.loads(e.starter()["plan.toml"])]
)
def test_a_plan_without_its_faults_is_refused(name: str, tmp_path: Path) -> None:
    folder = solved(name, tmp_path / name)
    edit_plan(folder, {}, drop="faults")

    refused(folder, r"plan.toml: \[\[faults\]\] is missing \(the shipped exercise has it\)")


@pytest.mark.parametrize(
    "name", [e.name for e in EXERCISES if len(e.starter()) > 1 + len(e.yours.files)]
)
def test_a_given_module_changed_or_deleted_is_refused(name: str, tmp_path: Path) -> None:
    chosen = kit.exercise(name)
    given = next(f for f in chosen.starter() if f != "plan.toml" and f not in chosen.yours.files)
    folder = solved(name, tmp_path / name)
    (folder / given).write_text(chosen.starter()[given] + "\nSHORTCUT = True\n")

    refused(folder, rf"{given} differs from the shipped exercise; only \S+ is yours")
    (folder / given).unlink()
    refused(folder, rf"{given} is missing: it is the shipped exercise's")


@pytest.mark.parametrize("name", TREES)
def test_a_tree_whose_managers_load_something_else_is_refused(name: str, tmp_path: Path) -> None:
    # [tree] is the student's: its supervisors, their order and restart types; a manager's
    # setup and options are the exercise's (a setup that loads nothing skips it).
    folder = solved(name, tmp_path / name)
    text = (folder / "plan.toml").read_text()
    first = re.search(r'^setup = "[^"]+"', text, flags=re.MULTILINE)
    assert first is not None
    (folder / "plan.toml").write_text(text.replace(first.group(0), 'setup = "mine:setup"', 1))

    refused(folder, r"plan.toml: \[\[tree.children\]\] \w+'s setup differs from the shipped")


@pytest.mark.parametrize("name", PROTOCOL)
def test_a_protocol_step_cannot_borrow_the_shipped_one(name: str, tmp_path: Path) -> None:
    step = kit.exercise(name).step
    folder = tmp_path / name
    kit.start(name, folder)
    (folder / "step.py").write_text(
        "import rr_actors_lab.teach as kit\n\n"
        f"def {step}(*args):\n    return kit.STEPS[{step!r}](*args)\n"
    )

    refused(folder, r"step.py does not import: ImportError: rr_actors_lab.teach is the classroom")


@pytest.mark.parametrize("name", PROTOCOL)
def test_a_protocol_step_cannot_import_the_kit_when_called_either(
    name: str, tmp_path: Path
) -> None:
    # Past the import statement: importlib, at a call, finds the kit gone. (The step then
    # does its own work, the solution's: a step that raises is told apart, elsewhere.)
    step = kit.exercise(name).step
    folder = solved(name, tmp_path / name)
    text = (folder / "step.py").read_text()
    (folder / "step.py").write_text(
        f"{text}\n\nimport importlib\nimport pathlib\n_mine = {step}\n\n\n"
        f"def {step}(*args):\n"
        "    try:\n"
        "        kit = importlib.import_module('rr_actors_lab.teach')\n"
        f"        return kit.shipped_step({step!r})(*args)\n"
        "    except ImportError as exc:\n"
        "        pathlib.Path(__file__).with_name('refused.txt').write_text(str(exc))\n"
        "    return _mine(*args)\n"
    )

    report = grade.check_folder(folder, seeds=2, shrink_budget=0)

    assert report.passed, report.failure
    assert (
        (folder / "refused.txt")
        .read_text()
        .startswith(
            "rr_actors_lab.teach is the classroom kit: a check runs your code where the kit"
        )
    )


@pytest.mark.timeout(300)  # (refcount, reconcile: about a minute alone at load 7)
@pytest.mark.parametrize("name", PROTOCOL)
def test_a_protocol_step_that_reaches_for_a_global_slot_finds_none_and_fails(
    name: str, tmp_path: Path
) -> None:
    # The student's copy is a value the run's config holds: there is no slot to empty.
    chosen = kit.exercise(name)
    folder = solved(name, tmp_path / name)
    text = (folder / "step.py").read_text()
    (folder / "step.py").write_text(
        text + "\n\nfrom rr_actors._core import runtime as _runtime\n"
        f"_mine = {chosen.step}\n\n\ndef {chosen.step}(*args):\n"
        f"    setattr(_runtime.steps, {chosen.step!r}, None)\n    return _mine(*args)\n"
    )

    report = grade.check_folder(folder, seeds=3, shrink_budget=0)

    assert report.failure is not None
    assert "AttributeError" in report.failure.message, report.failure


@pytest.mark.parametrize("name", MODULES)
def test_a_module_of_the_student_cannot_import_the_kit(name: str, tmp_path: Path) -> None:
    chosen = kit.exercise(name)
    folder = solved(name, tmp_path / name)
    mine = next(iter(chosen.yours.files))
    text = (folder / mine).read_text()
    (folder / mine).write_text("from rr_actors_lab.teach import kit as _kit\n" + text)

    refused(folder, r"rr_actors_lab.teach is the classroom kit")


def test_a_policy_module_of_the_student_cannot_import_the_kit(tmp_path: Path) -> None:
    folder = solved("cut", tmp_path / "cut")
    (folder / "policy.py").write_text(
        "from rr_actors_lab.teach import rules\n\n\ndef keep(first, second):\n    return first\n"
    )
    plan = (folder / "plan.toml").read_text()
    (folder / "plan.toml").write_text(re.sub(r'resolve = "\w+"', 'resolve = "policy:keep"', plan))

    refused(folder, r"rr_actors_lab.teach is the classroom kit")


@pytest.mark.parametrize(
    ("name", "file", "old", "new", "rule"),
    [
        ("request", "actions.py", 'registrar.call("camera", "stream", FRONT)',
         'type("Q", (), {"response": FRONT})()', "holds"),
        ("warn", "camera.py", "registrar.send_status(query.id, rr.Status.WARNING, "
         '"recalibrating")', "pass", "warns"),
        ("restarts", "plan.toml", 'name = "lidar"', 'name = "lidar"\nrestart = "temporary"',
         "back"),
        ("dispense", "plan.toml", 'name = "dispenser"',
         'name = "dispenser"\nrestart = "temporary"', "back"),
    ],
)  # fmt: skip
def test_an_answer_that_does_nothing_of_what_is_taught_fails(
    name: str, file: str, old: str, new: str, rule: str, tmp_path: Path
) -> None:
    folder = solved(name, tmp_path / name)
    text = (folder / file).read_text()
    assert old in text
    (folder / file).write_text(text.replace(old, new))

    report = grade.check_folder(folder, seeds=4, shrink_budget=0)

    assert not report.passed
    assert report.failure is not None
    assert report.failure.rule == rule, report.failure


@pytest.mark.timeout(240)  # (a shrink of 60 runs: 40 s at load 17)
def test_the_shrunk_story_of_a_tree_exercise_keeps_the_students_tree(tmp_path: Path) -> None:
    # restarts' starter: at most 2 restarts in 5.0 s, one_for_all. The shrink cuts the
    # faults, the workload and the managers' options, never the tree the student wrote.
    folder = tmp_path / "restarts"
    kit.start("restarts", folder)
    mine = tomllib.loads((folder / "plan.toml").read_text())["tree"]

    failure = grade.check_folder(folder, seeds=1, shrink_budget=60).failure

    assert failure is not None
    assert failure.rule == "survives"
    assert failure.shrunk_events is not None
    assert failure.shrunk_events < failure.run_events
    tree = tomllib.loads((folder / grade.SHRUNK).read_text())["tree"]
    assert (tree["strategy"], tree["max_restarts"], tree["period"]) == ("one_for_all", 2, 5.0)
    assert {k: v for k, v in tree.items() if k != "children"} == {
        k: v for k, v in mine.items() if k != "children"
    }
    assert [c["name"] for c in tree["children"]] == [c["name"] for c in mine["children"]]
