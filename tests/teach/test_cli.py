"""`rr-actors teach` (`rr_actors_lab.teach.cli`), run as a student runs it: a real
`python -m rr_actors` process per command. Each exercise's starter fails its check and its
solution passes (on a few seeds: the benchmark runs the exercises' 200); the JSON report;
hints remembered in the folder; the solution behind `--teacher`; bad input said."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from rr_actors_lab.teach import cli, grade, kit
from tests.support.observing import request

ROOT = Path(__file__).resolve().parents[2]


def teach(*argv: str | Path, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-m", "rr_actors", "teach", *map(str, argv)],
        capture_output=True,
        text=True,
        env=env,
        cwd=cwd,
        timeout=300,
        check=False,
    )


NAMES = [e.name for e in kit.exercises()]


def test_list_names_each_exercise_on_a_line_with_its_kind_level_and_topic() -> None:
    done = teach("list")

    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert [line.split()[0] for line in lines] == NAMES
    for line, chosen in zip(lines, kit.exercises(), strict=True):
        assert f"{chosen.kind}" in line
        assert f"level {chosen.level}" in line
        assert chosen.topic in line
    assert {e.kind for e in kit.exercises()} == set(kit.KINDS)  # at least one of each kind


@pytest.mark.timeout(180)  # (two checks, the failed one shrunk: 45 s at load 10, past 60 at 15)
@pytest.mark.parametrize("name", NAMES)
def test_the_starter_fails_its_check_and_the_solution_passes(name: str, tmp_path: Path) -> None:
    starter, solved = tmp_path / "starter", tmp_path / "solved"
    assert teach("start", name, starter).returncode == 0
    assert teach("start", name, solved).returncode == 0
    for file, text in kit.solution_files(kit.exercise(name)).items():
        (solved / file).write_text(text, encoding="utf-8")

    failed = teach("check", starter, "--seeds", "3", "--json", tmp_path / "failed.json")
    passed = teach("check", solved, "--seeds", "3", "--json", tmp_path / "passed.json")

    assert failed.returncode == 1, failed.stdout + failed.stderr
    assert "FAILED on seed" in failed.stdout
    assert f"the rule: {kit.exercise(name).rule}" in failed.stdout
    assert "first violating event: #" in failed.stdout
    assert f"replay it whole: rr-actors teach check {starter} " in failed.stdout
    assert failed.stderr == ""  # (no framework warnings: the story tells them)
    report = json.loads((tmp_path / "failed.json").read_text())
    assert report["passed"] is False
    assert report["exercise"] == name
    assert 1 <= report["failure"]["story_events"] <= 20
    assert len(report["failure"]["story"]) <= 21  # the steps and the violation's line
    if kit.exercise(name).kind == "protocol":  # (the checker's rules: shrunk)
        shrunk, whole = report["failure"]["shrunk_events"], report["failure"]["run_events"]
        # (intensity's starter gives up at its fourth kill: a run of 17 events, all needed)
        assert shrunk < whole or (name == "intensity" and shrunk == whole <= 20)
        assert (starter / "shrunk.toml").is_file()
        assert f"--plan {starter / 'shrunk.toml'}" in report["failure"]["replay"]
    assert passed.returncode == 0, passed.stdout + passed.stderr
    assert "PASSED: 3 seeds, 3 interleavings" in passed.stdout
    report = json.loads((tmp_path / "passed.json").read_text())
    assert (report["passed"], report["seeds_run"], report["failure"]) == (True, 3, None)


@pytest.mark.timeout(180)  # (a check shrunk in its child, then a replay: 60 s at load 8, -n 2)
def test_a_failures_replay_command_tells_that_seeds_whole_story(tmp_path: Path) -> None:
    folder = tmp_path / "climb"
    teach("start", "climb", folder)
    report = tmp_path / "report.json"
    teach("check", folder, "--seeds", "2", "--json", report)
    failure = json.loads(report.read_text())["failure"]

    told = teach(*failure["replay"].split()[2:])

    assert told.returncode == 0, told.stderr
    lines = told.stdout.splitlines()
    assert len(lines) > failure["story_events"]  # the whole run, not the cut
    assert any("[status-reached]" in line for line in lines)
    assert len(lines) < failure["run_events"]  # (the shrunk plan's story)


def test_start_writes_the_readme_and_starter_and_refuses_a_folder_in_use(tmp_path: Path) -> None:
    folder = tmp_path / "cam"
    done = teach("start", "camera", folder)

    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in folder.iterdir()) == [
        ".teach.json",
        "README.md",
        "actions.py",
        "plan.toml",
    ]
    refused = teach("start", "camera", folder)
    assert refused.returncode == 1
    assert "exists and is not an empty folder" in refused.stderr


def test_start_without_a_folder_writes_one_named_after_the_exercise(tmp_path: Path) -> None:
    assert teach("start", "share", cwd=tmp_path).returncode == 0
    assert (tmp_path / "share" / "step.py").is_file()


def test_hints_come_one_at_a_time_and_the_folder_remembers_them(tmp_path: Path) -> None:
    folder = tmp_path / "r"
    teach("start", "restarts", folder)
    hints = kit.exercise("restarts").hints

    said = [teach("hint", folder).stdout for _ in range(len(hints) + 1)]

    for number, (line, text) in enumerate(zip(said, hints, strict=False), 1):
        assert line == f"hint {number} of {len(hints)}: {text}\n"
    assert said[-1] == f"restarts: no more hints (all {len(hints)} shown)\n"
    state = json.loads((folder / ".teach.json").read_text())
    assert state == {"exercise": "restarts", "hints_shown": len(hints)}


def test_the_solution_is_shown_to_a_teacher_only(tmp_path: Path) -> None:
    folder = tmp_path / "s"
    teach("start", "share", folder)

    refused = teach("solution", folder)
    by_name = teach("solution", "share", "--teacher")
    by_folder = teach("solution", folder, "--teacher")

    assert refused.returncode == 1
    assert "the solution is for a teacher: add --teacher" in refused.stderr
    assert by_name.returncode == 0
    assert by_name.stdout == by_folder.stdout
    assert by_name.stdout.startswith("# ---- step.py ----\n")
    assert (kit.EXERCISES / "share" / "solution" / "step.py").read_text() in by_name.stdout


def test_an_unknown_exercise_is_refused_with_the_closest_names(tmp_path: Path) -> None:
    done = teach("start", "camra", tmp_path / "x")

    assert done.returncode == 1
    assert "no exercise 'camra'; did you mean 'camera'?" in done.stderr
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("command", ["check", "hint"])
def test_a_folder_that_is_not_an_exercise_is_refused(command: str, tmp_path: Path) -> None:
    done = teach(command, tmp_path)

    assert done.returncode == 1
    assert f"{tmp_path} is not an exercise's folder (it has no .teach.json)" in done.stderr


def test_a_step_py_without_its_function_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "c"
    teach("start", "climb", folder)
    (folder / "step.py").write_text("def clmb(parent, resources, status):\n    return []\n")

    done = teach("check", folder, "--seeds", "1")

    assert done.returncode == 1
    assert "has no function 'climb': the step you fix" in done.stderr


def test_story_needs_a_seed(tmp_path: Path) -> None:
    folder = tmp_path / "c"
    teach("start", "climb", folder)

    done = teach("check", folder, "--story")

    assert done.returncode == 1
    assert "--story tells one seed: add --seed S" in done.stderr


@pytest.mark.parametrize("by_plan", [False, True], ids=["folder", "plan"])
def test_replay_serves_the_seed_at_its_first_step_until_ctrl_c(
    tmp_path: Path, by_plan: bool
) -> None:
    _chosen, folder = kit.start("camera", tmp_path / "cam")
    argv = ["--plan", folder / "plan.toml"] if by_plan else [folder]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    command = [sys.executable, "-m", "rr_actors", "teach", "replay", *map(str, argv), "--seed", "2"]
    with subprocess.Popen(command, stdout=subprocess.PIPE, text=True, env=env) as child:
        assert child.stdout is not None
        line = child.stdout.readline()  # (the run, then the page: its URL)
        try:
            assert line.startswith("replay of camera, seed 2 ("), line
            url = next(word for word in line.split() if word.startswith("http://"))
            status, _, body = request(url, "/api/state")
            state = json.loads(body)
            assert (200, "replay") == (status, state["hello"]["mode"])
            assert (1, 2) == (
                state["sections"]["replay"]["step"],
                state["sections"]["replay"]["seed"],
            )
        finally:
            child.send_signal(signal.SIGINT)
            assert 0 == child.wait(timeout=60)


def test_a_story_not_shrunk_or_shrunk_to_more_than_20_events_says_so() -> None:
    failure = grade.Failure(1, "kept", "words", "what broke", None, ("a step",), 1, 916, "r", 1, 26)
    report = grade.Report("cut", False, 1, 1, 1, 916, 1.0, failure)

    above = cli._told(report)
    whole = cli._told(dataclasses.replace(report, failure=dataclasses.replace(
        failure, shrunk_seed=None, shrunk_events=None
    )))  # fmt: skip
    short = cli._told(dataclasses.replace(report, failure=dataclasses.replace(
        failure, shrunk_events=15
    )))  # fmt: skip

    assert "(the shrink stopped at 26 events, not 20:" in above
    assert "(not shrunk:" in whole
    assert "the 15 events of the run shrunk from 916" in short
    assert "not shrunk" not in short
    assert "stopped at" not in short
