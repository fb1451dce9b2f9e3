"""`rr-actors teach` (`rr_actors_lab.teach.cli`), run as a student runs it: a real
`python -m rr_actors_lab` process per command. Each exercise's starter fails its check and its
solution passes (on a few seeds: the benchmark runs the exercises' 200); the JSON report;
hints remembered in the folder; the solution behind `--teacher`; bad input said; an exit
code per outcome and the progress a grading script sees (issue 70); a folder's files read
within bounds (issue 68)."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import pty
import re
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from rr_actors_lab.teach import cli, grade, kit
from tests.support.observing import request
from tests.support.python import python

ROOT = Path(__file__).resolve().parents[2]


def teach(*argv: str | Path, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return python("-m", "rr_actors_lab", "teach", *map(str, argv), env=env, cwd=cwd, timeout=300)


NAMES = [e.name for e in kit.exercises()]

PROGRESS = re.compile(
    r"(seeds: \d+/\d+ run|seed \d+ broke a rule: shrinking its run to a shorter story "
    r"\(at most \d+ runs\)|shrink: \d+/\d+ runs) \(\d+ s\)"
)
"""A line of a check's progress on a pipe."""


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
    assert all(PROGRESS.fullmatch(line) for line in failed.stderr.splitlines()), failed.stderr
    # (progress only, no framework warnings: the story tells them)
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


@pytest.mark.timeout(180)  # (climb's check shrinks its failure: 92 s of it at load 13)
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
    assert refused.returncode == 2
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

    assert refused.returncode == 2
    assert "the solution is for a teacher: add --teacher" in refused.stderr
    assert by_name.returncode == 0
    assert by_name.stdout == by_folder.stdout
    assert by_name.stdout.startswith("# ---- step.py ----\n")
    assert (kit.EXERCISES / "share" / "solution" / "step.py").read_text() in by_name.stdout


def test_an_unknown_exercise_is_refused_with_the_closest_names(tmp_path: Path) -> None:
    done = teach("start", "camra", tmp_path / "x")

    assert done.returncode == 2
    assert "no exercise 'camra'; did you mean 'camera'?" in done.stderr
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("command", ["check", "hint"])
def test_a_folder_that_is_not_an_exercise_is_refused(command: str, tmp_path: Path) -> None:
    done = teach(command, tmp_path)

    assert done.returncode == 2
    assert f"{tmp_path} is not an exercise's folder (it has no .teach.json)" in done.stderr


def test_a_step_py_without_its_function_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "c"
    teach("start", "climb", folder)
    (folder / "step.py").write_text("def clmb(parent, resources, status):\n    return []\n")

    done = teach("check", folder, "--seeds", "1")

    assert done.returncode == 3
    assert "has no function 'climb': the step you fix" in done.stderr


def test_story_needs_a_seed(tmp_path: Path) -> None:
    folder = tmp_path / "c"
    teach("start", "climb", folder)

    done = teach("check", folder, "--story")

    assert done.returncode == 2
    assert "--story tells one seed: add --seed S" in done.stderr


@pytest.mark.parametrize("by_plan", [False, True], ids=["folder", "plan"])
def test_replay_serves_the_seed_at_its_first_step_until_ctrl_c(
    tmp_path: Path, by_plan: bool
) -> None:
    _chosen, folder = kit.start("camera", tmp_path / "cam")
    argv = ["--plan", folder / "plan.toml"] if by_plan else [folder]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    command = [
        sys.executable,
        "-m",
        "rr_actors_lab",
        "teach",
        "replay",
        *map(str, argv),
        "--seed",
        "2",
    ]
    with subprocess.Popen(command, stdout=subprocess.PIPE, text=True, env=env) as child:
        assert child.stdout is not None
        line = child.stdout.readline()  # (the run, then the page: its URL)
        try:
            assert line.startswith("replay of camera, seed 2 ("), line
            assert "; the check: FAILED, [dependency] at step " in line  # (its folder's rules)
            url = next(word for word in line.split() if word.startswith("http://"))
            status, _, body = request(url, "/api/state")
            state = json.loads(body)
            assert (200, "replay") == (status, state["hello"]["mode"])
            assert (1, 2) == (
                state["sections"]["replay"]["step"],
                state["sections"]["replay"]["seed"],
            )
            check = state["sections"]["replay"]["check"]
            assert ("FAILED", "dependency") == (check["outcome"], check["rule"])
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


# -- what a grading script reads: the exit code, the progress (issue 70 items 4, 5) ----------


def solved(name: str, folder: Path) -> Path:
    kit.start(name, folder)
    for file, text in kit.solution_files(kit.exercise(name)).items():
        (folder / file).write_text(text, encoding="utf-8")
    return folder


def broken_step(folder: Path) -> None:
    kit.start("climb", folder)
    (folder / "step.py").write_text("def climb(parent, resources, status):\n    return [\n")


def raising_setup(folder: Path) -> None:
    kit.start("camera", folder)
    (folder / "actions.py").write_text("def setup(registrar):\n    raise ValueError('no lens')\n")


def bad_plan(folder: Path) -> None:
    kit.start("camera", folder)
    (folder / "plan.toml").write_text("duration = [[[\n")


OUTCOMES = {  # a folder as a student may leave it: the exit code, and what is said where
    "passed": (lambda f: solved("camera", f), 0, "stdout", "camera: PASSED: 1 seeds"),
    "a rule broken": (
        lambda f: kit.start("camera", f),
        1,
        "stdout",
        "camera: FAILED on seed 1 (0 seeds held before it)",
    ),
    "not an exercise": (Path.mkdir, 2, "stderr", "is not an exercise's folder"),
    "step.py does not import": (broken_step, 3, "stderr", "step.py does not import: SyntaxError"),
    "plan.toml not a plan": (bad_plan, 3, "stderr", "plan.toml: is not valid TOML"),
    "the setup raises": (
        raising_setup,
        3,
        "stdout",
        "camera: NOT CHECKED: seed 1: the tree did not start",
    ),
}


@pytest.mark.timeout(120)
@pytest.mark.parametrize("case", list(OUTCOMES))
def test_each_outcome_of_a_check_has_its_own_exit_code(case: str, tmp_path: Path) -> None:
    make, code, where, said = OUTCOMES[case]
    folder = tmp_path / "work"
    make(folder)

    done = teach("check", folder, "--seeds", "1", "--quiet")

    assert code == done.returncode, done.stdout + done.stderr
    assert said in getattr(done, where), done.stdout + done.stderr
    if where == "stderr":  # one line, and no report
        assert (1, "") == (len(done.stderr.splitlines()), done.stdout), done.stderr
        assert done.stderr.startswith("rr-actors teach check: ")
    else:
        assert "" == done.stderr  # (--quiet: no progress)


def test_bad_arguments_exit_2(tmp_path: Path) -> None:
    folder = kit.start("camera", tmp_path / "cam")[1]

    for argv in (["--seeds", "0"], ["--seed", "x"], ["--story"]):
        done = teach("check", folder, *argv)

        assert 2 == done.returncode, (argv, done.stderr)
        assert "" == done.stdout


def test_a_check_that_raises_exits_4_with_its_traceback_never_0_or_1(tmp_path: Path) -> None:
    folder = solved("camera", tmp_path / "cam")
    raising = (  # (the kit broken on purpose: its check raises once a seed ran)
        "import sys\n"
        "from rr_actors_lab.teach import grade\n"
        "def broken(*args, **kwargs):\n"
        "    raise RuntimeError('a bug of the kit')\n"
        "grade.check_folder = broken\n"
        "from rr_actors_lab.__main__ import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONHASHSEED": "0"}

    done = python(
        "-c", raising, "teach", "check", str(folder), "--seeds", "1", env=env, timeout=120
    )

    assert 4 == done.returncode, done.stderr
    assert "RuntimeError: a bug of the kit" in done.stderr
    assert "the check itself raised (above): neither passed nor failed (exit 4)" in done.stderr
    assert "" == done.stdout


@pytest.mark.timeout(180)
def test_a_check_stopped_by_ctrl_c_exits_130_and_says_so(tmp_path: Path) -> None:
    folder = solved("camera", tmp_path / "cam")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    command = [sys.executable, "-m", "rr_actors_lab", "teach", "check", str(folder)]
    with subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    ) as child:
        assert child.stderr is not None
        first = child.stderr.readline()  # (a seed ran: the check is under way)
        assert first.startswith("seeds: 1/200 run"), first
        child.send_signal(signal.SIGINT)
        _out, err = child.communicate(timeout=120)

    assert 130 == child.returncode, err
    assert "rr-actors teach check: stopped by SIGINT" in err
    assert "Traceback" not in err


@pytest.mark.timeout(120)
def test_progress_on_a_pipe_is_a_line_after_the_first_and_the_last_seed(tmp_path: Path) -> None:
    folder = solved("camera", tmp_path / "cam")

    done = teach("check", folder, "--seeds", "3")

    assert 0 == done.returncode, done.stderr
    lines = done.stderr.splitlines()
    assert ["seeds: 1/3 run", "seeds: 3/3 run"] == [line.split(" (")[0] for line in lines]
    assert all(PROGRESS.fullmatch(line) for line in lines), lines
    assert done.stdout.startswith("camera: PASSED: 3 seeds")  # (the report: stdout alone)


def test_a_pipe_gets_a_line_every_progress_every_seeds(tmp_path: Path) -> None:
    """(`PROGRESS_EVERY` seeds at a time, in this process: a check of 41 seeds on a pipe
    would take a minute at load.)"""
    stream = io.StringIO()
    progress = cli._Progress(stream, "camera", 41, quiet=False)

    for number in range(1, 42):
        progress.seed(number)

    said = [line.split(" (")[0] for line in stream.getvalue().splitlines()]
    assert ["seeds: 1/41 run", "seeds: 20/41 run", "seeds: 40/41 run", "seeds: 41/41 run"] == said


@pytest.mark.timeout(180)
def test_a_failing_checks_shrink_shows_its_progress_on_a_pipe(tmp_path: Path) -> None:
    folder = tmp_path / "climb"
    kit.start("climb", folder)

    done = teach("check", folder, "--seeds", "1")

    assert 1 == done.returncode, done.stderr
    lines = [line.split(" (")[0] for line in done.stderr.splitlines()]
    assert lines[0] == "seed 1 broke a rule: shrinking its run to a shorter story"
    assert "shrink: 20/200 runs" in lines
    assert lines[-1] == "seeds: 1/1 run"


@pytest.mark.timeout(120)
def test_progress_on_a_terminal_is_a_bar_and_the_report_stays_on_stdout(tmp_path: Path) -> None:
    folder = solved("camera", tmp_path / "cam")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TERM": "xterm", "COLUMNS": "100"}
    command = [sys.executable, "-m", "rr_actors_lab", "teach", "check", str(folder), "--seeds", "3"]
    terminal, its_end = pty.openpty()
    with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=its_end, env=env) as child:
        os.close(its_end)
        shown = b""
        with contextlib.suppress(OSError):  # (EIO: the child closed its end)
            while chunk := os.read(terminal, 65536):
                shown += chunk
        out, _ = child.communicate(timeout=60)
    os.close(terminal)

    assert 0 == child.returncode
    assert out.decode().startswith("camera: PASSED: 3 seeds")
    text = shown.decode()
    assert "\N{BOX DRAWINGS HEAVY HORIZONTAL}" in text  # the bar
    assert "3/3" in text
    assert "seeds: " not in text  # (not the lines of a pipe)


# -- the folder's files, read within bounds (issue 68 item 3) ---------------------------------


def fifo(path: Path) -> None:
    os.mkfifo(path)


def dev_zero(path: Path) -> None:
    path.symlink_to("/dev/zero")


def deep(depth: int) -> Callable[[Path], None]:
    return lambda path: path.write_text("[" * depth + "]" * depth)


def sparse(size: int) -> Callable[[Path], None]:
    def make(path: Path) -> None:
        with path.open("wb") as file:
            file.truncate(size)

    return make


STATE_FILES = {  # .teach.json: what it is, and what the one line says
    "linked to /dev/zero": (dev_zero, "not a regular file (a character device): refused"),
    "a FIFO": (fifo, "not a regular file (a pipe): refused"),
    "100k deep": (deep(100_000), f"bigger than {kit.STATE_LIMIT} bytes"),
    "10k deep": (deep(10_000), "nested too deeply to read: not an exercise's state file"),
}

PLAN_FILES = {  # plan.toml
    "linked to /dev/zero": (dev_zero, "not a regular file (a character device): refused"),
    "a FIFO": (fifo, "not a regular file (a pipe): refused"),
    "200 MB": (sparse(200 * 1024 * 1024), "bigger than 4194304 bytes: not a plan"),
}


def bounded(*argv: str | Path) -> tuple[subprocess.CompletedProcess[str], int]:
    """`rr-actors ARGV`'s outcome and the most memory (KiB) it or a child of it took."""
    measure = (
        "import resource, subprocess, sys\n"
        "done = subprocess.run(sys.argv[1:], capture_output=True, text=True, timeout=60)\n"
        "sys.stderr.write(done.stderr)\n"
        "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)\n"
        "sys.exit(done.returncode)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = python(
        "-c", measure, sys.executable, "-m", "rr_actors_lab", *map(str, argv), env=env, timeout=90
    )
    return done, int(done.stdout.split()[-1])


@pytest.mark.timeout(120)
@pytest.mark.parametrize("command", ["check", "replay", "hint"])
@pytest.mark.parametrize("kind", list(STATE_FILES))
def test_a_state_file_that_is_no_state_file_is_refused_in_one_line(
    command: str, kind: str, tmp_path: Path
) -> None:
    make, said = STATE_FILES[kind]
    folder = kit.start("camera", tmp_path / "cam")[1]
    (folder / kit.STATE).unlink()
    make(folder / kit.STATE)

    done, kib = bounded("teach", command, folder)

    assert 2 == done.returncode, done.stderr
    assert 1 == len(done.stderr.splitlines()), done.stderr
    assert done.stderr.startswith(f"rr-actors teach {command}: {folder / kit.STATE}: ")
    assert said in done.stderr
    assert kib < 400 * 1024  # (MiB: 2.9 GiB before, from /dev/zero)


@pytest.mark.timeout(120)
@pytest.mark.parametrize("command", ["check", "replay"])
@pytest.mark.parametrize("kind", list(PLAN_FILES))
def test_a_plan_that_is_no_plan_file_is_refused_in_one_line(
    command: str, kind: str, tmp_path: Path
) -> None:
    make, said = PLAN_FILES[kind]
    folder = kit.start("camera", tmp_path / "cam")[1]
    (folder / "plan.toml").unlink()
    make(folder / "plan.toml")

    done, kib = bounded("teach", command, folder, "--seed", "1")

    assert 3 == done.returncode, done.stderr
    assert [f"rr-actors teach {command}: {folder / 'plan.toml'}: {said}"] == (
        done.stderr.splitlines()
    )
    assert kib < 400 * 1024
