"""Running the thesis's mission (`rr_actors_lab.mission.run`): `run_mission` and `rr-actors demo`,
in --fast mode, for real, and the command line's errors, Ctrl-C and `--out`.

Every run starts three manager processes under a supervisor and the robot's programs as
OS processes, and injects its faults with SIGKILL. The full mission runs once for the
module; each fault also runs alone.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors_lab.mission import FAULTS, MissionError, MissionReport
from rr_actors_lab.mission.action import Mission
from rr_actors_lab.mission.config import MissionConfig
from rr_actors_lab.mission.faults import fault_points
from rr_actors_lab.mission.output import (
    PlainOutput,
    Progress,
    timeline,
)
from rr_actors_lab.mission.programs import start_time
from rr_actors_lab.mission.run import (
    _hooks,
    _mission_clock,
    config_from_args,
    lock_out,
    main,
    parser,
    prepare_out,
    run_mission,
)
from tests.support.demos import (
    assert_nothing_left,
    assert_one_trace_per_step,
    interrupt_demo,
    one_line_after_the_story,
    report_with_everything,
)
from tests.support.observing import request
from tests.support.python import python
from tests.support.small_disk import mounted, remount_read_only
from tests.support.waiting import wait_for

ROOT = Path(__file__).resolve().parents[2]
REPORT_KEYS = {"mission_time_s", "distance_m", "faults", "leaked_processes", "catalog_entries_left"}
FAULT_KEYS = {"id", "injected_at_s", "detected_after_s", "recovered_after_s", "robot_stopped_s"}


def living_programs(out: Path) -> list[int]:
    """Pids of this run's programs that are still alive (pid and creation time match)."""
    alive = []
    for path in (out / "bus" / "pids").glob("*.json"):
        record = json.loads(path.read_text())
        if start_time(record["pid"]) == record["start_time"]:
            alive.append(record["pid"])
    return alive


def programs_started(out: Path) -> list[dict[str, Any]]:
    """Every program the run started, from their pid files."""
    return [json.loads(p.read_text()) for p in (out / "bus" / "pids").glob("*.json")]


@pytest.fixture(scope="module")
def full_quiet_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[int, Path, str]:
    """`rr-actors demo --fast --quiet`, all five faults: (exit code, output directory, stdout)."""
    out = tmp_path_factory.mktemp("mission")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main(["--fast", "--quiet", "--out", str(out)])
    return code, out, printed.getvalue()


@pytest.fixture(scope="module")
def full_run(full_quiet_run: tuple[int, Path, str]) -> tuple[int, Path]:
    """The full run: (exit code, output directory)."""
    return full_quiet_run[0], full_quiet_run[1]


@pytest.fixture(scope="module")
def full_report(full_run: tuple[int, Path]) -> dict[str, Any]:
    """The full run's report.json."""
    report: dict[str, Any] = json.loads((full_run[1] / "report.json").read_text())
    return report


def faults_by_id(report: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {f["id"]: f for f in report["faults"]}


def test_the_demo_exits_zero_after_the_full_mission(full_run: tuple[int, Path]) -> None:
    assert 0 == full_run[0]


def test_the_report_holds_every_field_and_all_five_faults(full_report: dict[str, Any]) -> None:
    assert REPORT_KEYS <= set(full_report)
    assert list(FAULTS) == [f["id"] for f in full_report["faults"]]
    for fault in full_report["faults"]:
        assert FAULT_KEYS <= set(fault)


def test_every_fault_of_the_full_mission_is_detected_and_recovered(
    full_report: dict[str, Any],
) -> None:
    for fault in full_report["faults"]:
        assert fault["detected_after_s"] is not None, fault
        assert fault["recovered_after_s"] is not None, fault
        assert fault["detected_after_s"] <= fault["recovered_after_s"], fault


def test_killing_the_managers_does_not_stop_the_robot(full_report: dict[str, Any]) -> None:
    stopped = {f: faults_by_id(full_report)[f]["robot_stopped_s"] for f in ("F3", "F4", "F5")}

    assert {"F3": 0.0, "F4": 0.0, "F5": 0.0} == stopped


def test_losing_the_lidar_or_the_driver_stops_the_robot_for_a_while(
    full_report: dict[str, Any],
) -> None:
    faults = faults_by_id(full_report)

    assert faults["F1"]["robot_stopped_s"] > 0
    assert faults["F2"]["robot_stopped_s"] > 0


def test_the_robot_reaches_the_goal_in_the_full_mission(full_report: dict[str, Any]) -> None:
    assert full_report["distance_m"] >= MissionConfig.fast().distance_m
    assert full_report["mission_time_s"] >= MissionConfig.fast().nominal_time_s


def test_the_full_mission_leaves_no_process_and_no_catalog_entry(
    full_run: tuple[int, Path], full_report: dict[str, Any]
) -> None:
    started = programs_started(full_run[1])

    assert (0, 0) == (full_report["leaked_processes"], full_report["catalog_entries_left"])
    assert {"erm": 0, "cm": 0, "rm": 0, "mission": 0} == full_report["catalog_entries_by_registrar"]
    assert [] == living_programs(full_run[1])
    assert 5 == len(started)  # driver, navigation, LiDAR 1, LiDAR 2, the restarted driver


def test_quiet_prints_the_timeline_and_the_paths_and_no_story(
    full_quiet_run: tuple[int, Path, str],
) -> None:
    lines = full_quiet_run[2].splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("fault  what"))

    assert [] == [line for line in lines if line.startswith("[")]  # no story line
    assert lines[header + 1].startswith("-----  ")
    assert list(FAULTS) == [line.split()[0] for line in lines[header + 2 : header + 7]]
    assert any(line.startswith("mission time ") for line in lines)
    assert any(line.startswith("report: ") for line in lines)


def test_the_full_mission_draws_its_plot(full_run: tuple[int, Path]) -> None:
    if importlib.util.find_spec("matplotlib") is None:
        pytest.skip("matplotlib is not installed")

    assert (full_run[1] / "mission.png").stat().st_size > 0


@pytest.mark.parametrize("fault", FAULTS)
def test_each_fault_alone_is_recovered_and_leaves_nothing_behind(
    fault: str, tmp_path: Path
) -> None:
    report: MissionReport = run_mission(MissionConfig.fast(faults=(fault,)), tmp_path)
    (result,) = report.faults

    assert fault == result.id
    assert result.recovered_after_s is not None
    assert (0, 0) == (report.leaked_processes, report.catalog_entries_left)
    assert [] == living_programs(tmp_path)
    if fault in ("F3", "F4", "F5"):
        assert 0.0 == result.robot_stopped_s


def test_without_faults_the_robot_drives_through_and_the_demo_explains_the_missing_plot(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "rr_actors_lab.mission.plot", None)  # as without matplotlib

    code = main(["--fast", "--no-faults", "--distance", "2", "--out", str(tmp_path)])
    report = json.loads((tmp_path / "report.json").read_text())

    assert 0 == code
    assert [] == report["faults"]
    assert "mission.png needs an extra: pip install" in capsys.readouterr().out
    assert not (tmp_path / "mission.png").exists()


def test_trace_exports_one_trace_per_mission_step_where_the_otel_variables_say(
    tmp_path: Path,
) -> None:
    env = {**os.environ, "OTEL_TRACES_EXPORTER": "console", "OTEL_SERVICE_NAME": "the robot"}
    argv = ["--fast", "--faults", "F4", "--distance", "2", "--quiet", "--trace"]
    done = python(
        "-m", "rr_actors_lab", "demo", *argv, "--out", str(tmp_path), timeout=300, env=env
    )

    assert 0 == done.returncode, done.stderr[-2000:]
    spans = assert_one_trace_per_step(done.stdout)
    assert all("the robot" == span["resource"]["attributes"]["service.name"] for span in spans)


def test_trace_with_an_exporter_not_installed_exits_2(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("OTEL_TRACES_EXPORTER", "nosuch")

    code = main(["--fast", "--trace", "--out", str(tmp_path / "out")])

    assert 2 == code
    assert "OTEL_TRACES_EXPORTER names 'nosuch', which is not installed" in capsys.readouterr().err


def test_the_example_script_runs_the_mission(tmp_path: Path) -> None:
    result = python(
        str(ROOT / "examples" / "jackal_mission.py"),
        "--fast",
        "--faults",
        "F1",
        "--distance",
        "3",
        "--out",
        str(tmp_path),
        timeout=50,
    )

    assert (0, "") == (result.returncode, result.stderr)
    assert "F1     LiDAR 1 disconnected" in result.stdout
    assert "leaked processes: 0; catalog entries left: 0" in result.stdout


def test_an_unknown_fault_is_a_command_line_error(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["--faults", "F9", "--out", "unused"])

    assert 2 == code
    assert "F9" in capsys.readouterr().err


@pytest.mark.parametrize(("wrong", "meant"), [("F33", "F3"), ("FF2", "F2")])
@pytest.mark.parametrize("option", ["--faults", "--fault-at"])
def test_a_mistyped_fault_is_answered_with_the_closest_one(
    option: str, wrong: str, meant: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--fault-at F33=0.2` was taken and ignored: the demo ran without saying so."""
    given = f"F1,{wrong}" if option == "--faults" else f"{wrong}=0.2"

    assert 2 == main([option, given, "--out", str(tmp_path / "out")])

    field = option.removeprefix("--").replace("-", "_")
    assert f"{field}: unknown fault(s) ['{wrong}']; did you mean '{meant}'? (known: ['F1'," in (
        capsys.readouterr().err
    )


# -- a manager killed by hand while the mission runs ---------------------------------------


@pytest.mark.usefixtures("process_helpers")  # the forkserver predates the leak check
@pytest.mark.parametrize("manager", ["erm", "cm", "rm"])
@pytest.mark.timeout(150)  # a whole mission and a restart: 29-42 s at load 17-19, as full runs
def test_a_manager_killed_by_hand_mid_run_is_waited_for_and_shown_in_the_timeline(
    manager: str, tmp_path: Path
) -> None:
    killed: list[int] = []
    mission: Mission | None = None

    def say(line: str) -> None:  # on the mission's thread, right after F1 was recovered
        if "LiDAR 2 loaded" in line and not killed:
            assert mission is not None
            supervisor = mission.supervisor
            assert supervisor is not None
            pid = supervisor.child(manager).pid
            assert pid is not None
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
            # the next fault waits for a manager the supervisor sees down (F2 injected
            # before it saw the kill killed the driver while rm was down: never recovered)
            assert wait_for(lambda: supervisor.child(manager).pid != pid, timeout=30)

    mission = Mission(MissionConfig.fast(), prepare_out(tmp_path), say=say)
    report = mission.run()

    assert 1 == len(killed)
    assert list(FAULTS) == [f.id for f in report.faults]
    assert [] == [f.id for f in report.faults if f.recovered_after_s is None]
    assert [manager] == [r.manager for r in report.unplanned_restarts]
    assert (0, 0) == (report.leaked_processes, report.catalog_entries_left)
    assert [] == living_programs(tmp_path)
    assert f"-      {manager} exited, no fault" in timeline(report)
    [exit] = report.unplanned_restarts
    assert exit.restarted_after_s is not None  # its restart, from the supervisor's events
    assert 0.0 < exit.restarted_after_s < 10.0


@pytest.mark.usefixtures("process_helpers")  # (the resource tracker: not this test's leak)
def test_the_story_is_told_in_the_order_of_its_stamps_when_the_goal_comes_mid_recovery(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """F5 injected at 98 % of the path (99.35 % with seed 0's jitter): the robot reaches the
    goal about 0.02 s later, while rm restarts; the goal's line is told then, not after
    "F5 recovered" with an earlier stamp (issue 44)."""
    argv = ["--fast", "--faults", "F5", "--fault-at", "F5=0.98", "--seed", "0"]
    point = fault_points(config_from_args(parser().parse_args(argv)))["F5"]
    assert 0.98 < point <= 1.0  # the premise: on the path's last 2 %, never past the goal

    code = main([*argv, "--out", str(tmp_path / "out")])

    story = [line for line in capsys.readouterr().out.splitlines() if line.startswith("[")]
    stamps = [float(line[1:].split(" s]")[0]) for line in story]
    told = [line.split("] ", 1)[1].split(":")[0].split(" after")[0] for line in story]
    assert 0 == code
    assert sorted(stamps) == stamps, "\n".join(story)
    assert told.index("goal reached") < told.index("F5 recovered"), "\n".join(story)


# -- --quiet -------------------------------------------------------------------------------


def test_quiet_help_says_it_prints_only_the_timeline() -> None:
    help_text = " ".join(parser().format_help().split())

    assert "--quiet no story and no progress line: print only the timeline" in help_text


# -- errors --------------------------------------------------------------------------------


def demo(*argv: str) -> subprocess.CompletedProcess[str]:
    """`rr-actors demo ARGV` as a separate program (60 s at most)."""
    return python("-m", "rr_actors_lab", "demo", *argv, timeout=60)


@pytest.mark.parametrize(
    ("field", "value"), [("speed", float("nan")), ("distance_m", float("inf"))]
)
def test_a_speed_or_distance_that_is_no_finite_number_is_refused(field: str, value: float) -> None:
    """`rr-actors demo --speed nan` (or `--distance inf`) drove for ever: the mission never
    reaches its goal and the demo never ends. Refused as `-1` is, naming the field."""
    with pytest.raises(rr.ConfigError, match=f"{field} must be a positive number"):
        MissionConfig(**{field: value})


def test_out_pointing_at_a_file_is_a_clear_error_with_exit_code_2(tmp_path: Path) -> None:
    target = tmp_path / "a-file"
    target.write_text("not a directory\n")

    result = demo("--fast", "--out", str(target))

    assert (2, "") == (result.returncode, result.stdout)
    assert f"rr-actors demo: --out '{target}' is a file, not a directory\n" == result.stderr


def test_out_below_a_file_is_a_clear_error_with_exit_code_2(tmp_path: Path) -> None:
    (tmp_path / "a-file").write_text("")
    target = tmp_path / "a-file" / "sub"

    result = demo("--fast", "--out", str(target))

    assert 2 == result.returncode
    assert result.stderr.startswith(f"rr-actors demo: --out '{target}': cannot write there (")
    assert "Traceback" not in result.stderr


def test_out_in_a_read_only_directory_is_a_clear_error_with_exit_code_2(tmp_path: Path) -> None:
    # Root writes through file modes: as root (CI) the directory is a read-only tmpfs.
    with contextlib.ExitStack() as stack:
        if os.geteuid() == 0:
            read_only = stack.enter_context(mounted(tmp_path / "ro", size="64k"))
            remount_read_only(read_only)
            why = "Read-only file system"
        else:
            read_only = tmp_path
            read_only.chmod(0o500)
            stack.callback(read_only.chmod, 0o700)
            why = "Permission denied"
        result = demo("--fast", "--out", str(read_only / "out"))

    assert 2 == result.returncode
    assert f"cannot write there ({why})" in result.stderr
    assert "Traceback" not in result.stderr


def test_without_pidfds_the_demo_says_it_needs_linux_with_exit_code_2(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.delattr(os, "pidfd_open")

    code = main(["--fast", "--out", str(tmp_path)])

    assert 2 == code
    assert "needs Linux" in capsys.readouterr().err
    assert [] == list(tmp_path.iterdir())  # nothing was started or written


def test_without_pidfds_run_mission_raises_a_mission_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delattr(os, "pidfd_open")

    with pytest.raises(MissionError, match="needs Linux"):
        run_mission(MissionConfig.fast(), tmp_path)


# -- one name per figure -------------------------------------------------------------------


class ClockedObserver:
    """Stands in for the observer `--observe` opens: records what its clock is called."""

    url = "http://127.0.0.1:1/"

    def __init__(self) -> None:
        self.labels: list[str] = []

    def set_clock(self, origin: float, label: str = "") -> None:
        del origin
        self.labels.append(label)


class ObservedSupervisor:
    def __init__(self, observer: ClockedObserver) -> None:
        self.observer = observer


def test_the_page_calls_its_clock_the_mission_clock_and_only_the_total_is_mission_time(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr("rr_actors_lab.observe.observe", lambda sup, **_: sup.observer)
    observer = ClockedObserver()
    observers: list[object] = []
    args = parser().parse_args(["--observe"])
    on_supervisor, _ = _hooks(args, PlainOutput(io.StringIO()), io.StringIO(), observers)  # type: ignore[arg-type]
    assert on_supervisor is not None
    on_supervisor(ObservedSupervisor(observer))  # type: ignore[arg-type]
    _mission_clock(lambda _: None, observers)(Progress(12.34, 1.0, 6.0, True, ""))  # type: ignore[arg-type]
    totals = timeline(report_with_everything()).splitlines()
    named = [line for line in totals if "mission time" in line]  # one figure under that name

    assert ["mission clock", "mission clock"] == observer.labels
    assert 1 == len(named)
    assert named[0].startswith("mission time 1234.50 s (the drive")


class TestCtrlC:
    """Ctrl-C in `rr-actors demo`, in a real terminal: one line, exit code 130, nothing left.

    A terminal's Ctrl-C sends SIGINT to its whole foreground process group: the demo, the
    forkserver, every manager and spare process. Here the demo runs in a session of its own
    on a pseudo-terminal, and the test sends SIGINT to that group (`os.killpg`), as the
    terminal would. Only the demo may act on it: it unloads everything, stops the managers
    in order and says so in one line.
    """

    @pytest.mark.usefixtures("process_helpers")
    @pytest.mark.timeout(150)
    def test_ctrl_c_while_the_robot_drives_prints_one_line_and_exits_130(
        self, tmp_path: Path
    ) -> None:
        code, before, after, tree = interrupt_demo(tmp_path, b"driving")

        assert "driving" in before
        assert 130 == code, after
        assert one_line_after_the_story(after), after  # the one line, and nothing else
        assert "Traceback" not in after
        assert_nothing_left(tmp_path, tree)

    @pytest.mark.usefixtures("process_helpers")
    @pytest.mark.timeout(150)
    def test_ctrl_c_at_the_step_prompt_prints_one_line_and_exits_130(self, tmp_path: Path) -> None:
        code, before, after, tree = interrupt_demo(tmp_path, b"press Enter", "--step")

        assert "press Enter" in before
        assert 130 == code, after
        assert one_line_after_the_story(after), after
        assert "Traceback" not in after
        assert_nothing_left(tmp_path, tree)


class TestOutAndPort:
    """`rr-actors demo --port` and `--out`: refused before anything starts or is removed.

    `--port` without `--observe` used to be ignored silently (the mission ran, no page), and
    a port out of range was refused only after the managers had started. `--out` a folder
    whose `state/`, `bus/` (or `certs/`, on two hosts) a demo never wrote (`--out ~`) used
    to have them emptied.
    """

    @pytest.mark.parametrize(
        ("argv", "says"),
        [
            (["--port", "8080"], "--port needs --observe (it is the observer's port)"),
            (["--observe", "--port", "-5"], "--port must be from 0 to 65535, got -5"),
            (["--observe", "--port", "70000"], "--port must be from 0 to 65535, got 70000"),
            (["--linger", "5"], "--linger needs --observe (it keeps the page served)"),
            (["--allow-faults"], "--allow-faults needs --observe (its buttons are on the page)"),
        ],
        ids=["without-observe", "negative", "too-big", "linger", "allow-faults"],
    )
    def test_a_port_or_an_observer_option_the_demo_cannot_use_is_a_usage_error_at_once(
        self, tmp_path: Path, argv: list[str], says: str
    ) -> None:
        out = tmp_path / "out"

        result = demo("--fast", "--out", str(out), *argv)

        assert (2, "", f"rr-actors demo: {says}\n") == (
            result.returncode,
            result.stdout,
            result.stderr,
        )
        assert not out.exists()  # nothing started, nothing written

    @pytest.mark.parametrize("sub", ["state", "bus", "certs"])
    def test_a_folder_whose_state_bus_or_certs_no_demo_wrote_is_refused_and_kept(
        self, tmp_path: Path, sub: str
    ) -> None:
        mine = tmp_path / sub / "notes.txt"  # `--out ~` with the user's own ~/state
        mine.parent.mkdir()
        mine.write_text("mine\n")

        result = demo("--fast", "--out", str(tmp_path))

        assert (2, "") == (result.returncode, result.stdout)
        assert f"holds a {sub}/ that no mission wrote" in result.stderr
        assert ("mine\n", [sub]) == (mine.read_text(), sorted(p.name for p in tmp_path.iterdir()))


def demo_process(out: Path) -> subprocess.Popen[str]:
    """`rr-actors demo --fast --out OUT` as a separate program, its output in pipes."""
    return subprocess.Popen(
        [sys.executable, "-m", "rr_actors_lab", "demo", "--fast", "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


class TestOneDemoPerOut:
    """Two demos in one `--out` folder: the second refuses at once, the first is untouched."""

    @pytest.mark.timeout(120)
    def test_a_second_demo_in_the_same_folder_refuses_and_the_first_completes(
        self,
        tmp_path: Path,
    ) -> None:
        out = tmp_path / "demo"
        first = demo_process(out)
        try:
            assert first.stdout is not None
            # Its first line of story comes after it took the lock and emptied state/ and bus/.
            assert "starting the managers" in first.stdout.readline()

            second = python("-m", "rr_actors_lab", "demo", "--fast", "--out", str(out), timeout=60)
            rest, errors = first.communicate(timeout=90)
        finally:
            if first.poll() is None:
                first.kill()
                first.wait(10)

        assert (2, "") == (second.returncode, second.stdout)
        assert (
            f"rr-actors demo: {str(out)!r} is in use by another demo (pid {first.pid}); wait for "
            "it to end, or give this one another folder with --out\n"
        ) == second.stderr
        assert (0, "") == (first.returncode, errors), rest
        assert "leaked processes: 0; catalog entries left: 0" in rest

    def test_the_lock_is_free_again_after_a_mission(self, tmp_path: Path) -> None:
        with lock_out(tmp_path):
            pass

        with lock_out(tmp_path):  # would raise if the first were still held
            pass


def test_demo_observe_serves_the_final_state_until_ctrl_c_and_says_so(
    process_helpers: Any, tmp_path: Path
) -> None:
    command = ["demo", "--fast", "--observe", "--quiet", "--out", str(tmp_path)]
    with subprocess.Popen(
        [sys.executable, "-m", "rr_actors_lab", *command],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    ) as demo:
        try:
            assert demo.stdout is not None
            lines = []
            for line in demo.stdout:
                lines.append(line)
                if "press Ctrl-C" in line:
                    break
            url = next(x for x in lines if x.startswith("observer: http")).split()[1]
            serving = request(url, "/api/state")[0]
            demo.send_signal(signal.SIGINT)
            code = demo.wait(30)
        finally:
            if demo.poll() is None:
                demo.kill()
                demo.wait(10)

    # The last thing said, wrapped at words to 80 columns: the mission ended, until Ctrl-C.
    last = next(i for i, line in enumerate(lines) if line.startswith("observer: the mission"))
    said = " ".join(line.strip() for line in lines[last:])
    assert said.startswith("observer: the mission ended;"), said
    assert said.endswith("(press Ctrl-C to stop)"), said
    assert (200, 0) == (serving, code)
    with pytest.raises(ConnectionRefusedError):
        request(url, "/", timeout=2.0)


def test_allow_faults_without_observe_is_a_usage_error(tmp_path: Path) -> None:
    from rr_actors_lab.mission import run as demo  # noqa: PLC0415

    args = demo.parser().parse_args(["--fast", "--allow-faults", "--out", str(tmp_path)])

    assert 2 == demo.run(args, io.StringIO())


# -- the demo ---------------------------------------------------------------------------------


def test_demo_observe_prints_the_url_and_serves_for_the_whole_run(
    tmp_path: Path, process_helpers: Any
) -> None:
    from rr_actors_lab.mission import run as demo  # noqa: PLC0415

    args = demo.parser().parse_args(
        ["--fast", "--observe", "--linger", "0", "--out", str(tmp_path), "--quiet"]
    )
    out = io.StringIO()
    code = demo.run(args, out)

    assert 0 == code
    url = next(line for line in out.getvalue().splitlines() if line.startswith("observer: "))
    with pytest.raises(ConnectionRefusedError):  # --linger 0: closed with the mission
        request(url.split()[1], "/", timeout=2.0)


def test_demo_observe_on_a_port_in_use_fails_before_the_mission(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import socket  # noqa: PLC0415

    from rr_actors_lab.mission import run as demo  # noqa: PLC0415

    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    try:
        port = str(taken.getsockname()[1])
        args = demo.parser().parse_args(
            ["--fast", "--observe", "--port", port, "--out", str(tmp_path)]
        )
        code = demo.run(args, io.StringIO())
    finally:
        taken.close()

    assert 2 == code
    assert "in use" in capsys.readouterr().err
