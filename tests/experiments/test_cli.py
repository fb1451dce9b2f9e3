"""The experiment's command line (`rr_actors_lab.experiments.cli`): `rr-actors experiment`: bad
input is refused before anything starts (exit code 2), a run prints its summary, and Ctrl-C (a
real SIGINT) stops every process and keeps finished runs."""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import sysconfig
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

import psutil
import pytest

import rr_actors as rr
import rr_actors_lab.observe
from rr_actors_lab.__main__ import main
from rr_actors_lab.experiments import Progress, RunResult, parse_plan
from rr_actors_lab.experiments.cli import Display, fault_line, summary_lines
from rr_actors_lab.experiments.results import FaultRecord, Results
from tests.support.python import python
from tests.support.small_disk import fill, mounted
from tests.support.terminal import FakeTerminal, on_a_terminal

SERVICE = "rr_actors_lab.experiments.services:service"

PLAN = f"""\
name = "tiny"
duration = {{duration}}

[tree]
max_restarts = 20

[[tree.children]]
name = "db"
setup = "{SERVICE}"

[workload]
clients = 1
rate = 10.0

[[workload.calls]]
manager = "db"
server = "resource"

[[faults]]
kind = "kill_manager"
target = "db"
at = 0.5
"""


def write_plan(tmp_path: Path, text: str | None = None, duration: float = 1.0) -> Path:
    path = tmp_path / "plan.toml"
    path.write_text(text if text is not None else PLAN.format(duration=duration))
    return path


def refused(
    capsys: pytest.CaptureFixture[str], plan: Path, out: Path, *extra: str
) -> tuple[int, str]:
    code = main(["experiment", str(plan), "--out", str(out), *extra])
    captured = capsys.readouterr()
    assert "" == captured.out
    return code, captured.err


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (("max_restarts = 20", "max_restart = 20"), "plan.toml:5: tree.max_restart: unknown key"),
        (
            (SERVICE, "rr_actors.nothing_here:setup"),
            "plan.toml:9: tree.children[0].setup: 'rr_actors.nothing_here:setup' does not "
            "import: No module named 'rr_actors.nothing_here'",
        ),
        (
            ('target = "db"', 'target = "erm"'),
            "plan.toml:21: faults[0].target: no manager 'erm' in the tree (managers: db)",
        ),
        (("at = 0.5", "at = -0.5"), "plan.toml:22: faults[0].at: must be seconds >= 0, got -0.5"),
    ],
    ids=["unknown key", "setup does not import", "fault names no manager", "negative time"],
)
def test_a_bad_plan_exits_2_naming_file_line_and_key_before_anything_starts(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    change: tuple[str, str],
    message: str,
) -> None:
    plan = write_plan(tmp_path, PLAN.format(duration=1.0).replace(*change))
    out = tmp_path / "out"

    code, err = refused(capsys, plan, out)

    assert 2 == code
    assert err.startswith(f"rr-actors experiment: {plan.parent}/{message}")
    assert 1 == len(err.splitlines())
    assert not out.exists()


def test_a_plan_file_that_does_not_exist_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, err = refused(capsys, tmp_path / "missing.toml", tmp_path / "out")

    assert 2 == code
    assert "missing.toml: cannot be read" in err


def test_a_misspelt_shipped_plan_exits_2_saying_which_was_meant(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, err = refused(capsys, Path("frist"), tmp_path / "out")

    assert (2, 1) == (code, len(err.splitlines())), err
    assert "frist: no such file, and no shipped plan of that name; did you mean 'first'?" in err
    assert "'strategies'" in err  # every shipped plan listed


def test_an_output_directory_that_is_not_empty_exits_2_without_force(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")

    code, err = refused(capsys, write_plan(tmp_path), out)

    assert 2 == code
    assert f"--out '{out}' exists and is not empty" in err
    assert ["notes.txt"] == [p.name for p in out.iterdir()]


def test_observe_without_the_observe_extra_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "rr_actors_lab.observe._server", None)  # as if not installed
    monkeypatch.delattr(rr_actors_lab.observe, "_server", raising=False)

    code, err = refused(capsys, write_plan(tmp_path), tmp_path / "out", "--observe")

    assert 2 == code
    [line] = err.splitlines()
    assert line.startswith("rr-actors experiment: --observe needs an extra: pip install")
    assert line.endswith('[observe]"')
    assert len(line) <= 80
    assert not (tmp_path / "out").exists()


def test_trace_with_an_exporter_not_installed_exits_2_before_any_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("OTEL_TRACES_EXPORTER", "console,nosuch")

    code, err = refused(capsys, write_plan(tmp_path), tmp_path / "out", "--trace")

    assert 2 == code
    assert "OTEL_TRACES_EXPORTER names 'nosuch', which is not installed" in err
    assert not (tmp_path / "out" / "events.jsonl").exists()


WITHOUT_MSGSPEC = (
    "import sys; sys.modules['msgspec'] = None; "  # as with only the demo extra installed
    "from rr_actors_lab.__main__ import main; sys.exit(main(sys.argv[1:]))"
)


@pytest.mark.parametrize("argv", [["--list"], ["first", "--out", "x"], ["--bogus"]])
def test_without_the_experiments_extra_every_use_names_it_with_exit_code_2(
    argv: list[str], tmp_path: Path
) -> None:
    result = python("-c", WITHOUT_MSGSPEC, "experiment", *argv, cwd=tmp_path, timeout=60)

    assert (2, "") == (result.returncode, result.stdout)
    assert result.stderr.startswith("rr-actors experiment needs an extra: pip install")
    assert '[experiments]"' in result.stderr
    assert "unrecognized arguments" not in result.stderr
    assert not (tmp_path / "x").exists()


def test_an_unknown_option_of_another_command_is_still_a_usage_error(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit) as exited:
        main(["demo", "--bogus"])

    assert 2 == exited.value.code
    assert "rr-actors demo: error: unknown option --bogus\n" in capsys.readouterr().err


def test_with_force_it_runs_into_a_used_directory_and_prints_a_summary(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "runs.csv").write_text("an old experiment's rows\n")

    code = main(["experiment", str(write_plan(tmp_path)), "--out", str(out), "--force"])
    printed = capsys.readouterr().out

    assert 0 == code
    assert "mine" == (out / "notes.txt").read_text()
    with (out / "runs.csv").open(newline="") as rows:
        assert ["1"] == [row["run"] for row in csv.DictReader(rows)]
    assert "run 1/1 seed 0: " in printed
    assert "one_for_one" in printed
    shown = " ".join(printed.split())  # (a long path wraps at words: lines of 80 at most)
    assert f"written to {out}/: events.jsonl, runs.csv, faults.csv" in shown


NEVER_TRIGGERED = """
[[faults]]
kind = "kill_manager"
target = "db"
after = { event = "ChildRestarted", child = "db", nth = 1000 }
"""


def test_the_summary_says_how_late_the_faults_were_injected_and_why_one_was_skipped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The kill at 0.5 s fires (a little late: the injector's own error); the kill after
    db's 1000th restart never does (issue 44 item 8)."""
    plan = write_plan(tmp_path, PLAN.format(duration=1.0) + NEVER_TRIGGERED)

    code = main(["experiment", str(plan), "--out", str(tmp_path / "out")])
    shown = " ".join(capsys.readouterr().out.split())  # (wrapped at words to 80 columns)

    assert 0 == code
    late = r"\d+(\.\d+)? m?s"  # one fault: one value (faults.csv's late_ms), in ms or s
    expected = (
        rf"faults: 1 injected, {late} late; 1 skipped "
        r"\(run 1: its trigger did not happen in the run\) verdicts: "
    )
    assert re.search(expected, shown), shown


def fault(n: int, late_s: float | None, detail: str = "SIGKILL pid 1") -> FaultRecord:
    """Fault `n` of a run: fired `late_s` after its due time (1.0 s), or skipped."""
    injected = None if late_s is None else 1.0 + late_s
    return FaultRecord(0, n, "kill_manager", "db", 1.0, injected, detail, late_s is None)


def results_with(*faults_per_run: tuple[FaultRecord, ...]) -> Results:
    runs = tuple(
        dataclasses.replace(finished_run(), run=number, faults=faults)
        for number, faults in enumerate(faults_per_run, start=1)
    )
    return Results(plan=parse_plan(PLAN.format(duration=1.0)), runs=runs)


@pytest.mark.parametrize(
    ("faults_per_run", "expected"),
    [
        (((fault(0, 0.6), fault(1, 1.0)),), "faults: 2 injected, 0.6-1.0 s late; none skipped"),
        (
            ((fault(0, 0.00002), fault(1, 0.00006)),),
            "faults: 2 injected, 0.02-0.06 ms late; none skipped",
        ),
        (((fault(0, 0.02), fault(1, 0.31)),), "faults: 2 injected, 20-310 ms late; none skipped"),
        (((fault(0, 0.003),),), "faults: 1 injected, 3.0 ms late; none skipped"),
        (
            (
                (fault(0, 0.0001), fault(1, None, "pid 812 had just exited (ESRCH)")),
                (fault(0, None, "db was not running (restarting)"), fault(1, 0.0002)),
                (fault(0, None, "pid 907 had just exited (ESRCH)"),),
            ),
            "faults: 2 injected, 0.10-0.20 ms late; 3 skipped (run 1: pid 812 had just exited "
            "(ESRCH) (+1 like it); run 2: db was not running (restarting))",
        ),
        (
            ((*(fault(n, None, f"reason {chr(97 + n)}") for n in range(5)),),),
            "faults: 0 injected; 5 skipped (run 1: reason a; run 1: reason b; run 1: reason c; "
            "2 other reason(s) in faults.csv)",
        ),
    ],
    ids=["seconds", "microseconds", "milliseconds", "one", "skips-counted", "many-reasons"],
)
def test_the_fault_line_gives_the_lateness_in_a_unit_that_reads_and_every_skip_reason(
    faults_per_run: tuple[tuple[FaultRecord, ...], ...], expected: str
) -> None:
    assert expected == fault_line(results_with(*faults_per_run))


def test_without_faults_there_is_no_fault_line() -> None:
    assert fault_line(results_with(())) is None


def test_ctrl_c_stops_every_process_and_keeps_the_runs_finished_so_far(
    tmp_path: Path, eventually: Callable[..., bool]
) -> None:
    out = tmp_path / "out"
    script = Path(sysconfig.get_path("scripts")) / "rr-actors"
    command = [str(script), "experiment", str(write_plan(tmp_path, duration=2.0))]
    cli = subprocess.Popen(
        [*command, "--out", str(out), "--repeat", "5"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert eventually(lambda: len(rows(out / "runs.csv")) >= 1, timeout=40)
        assert eventually(lambda: len(alive(f"{cli.pid}-")) > 0, timeout=20)

        cli.send_signal(signal.SIGINT)  # what Ctrl-C in a terminal sends
        stdout, stderr = cli.communicate(timeout=40)
    finally:
        if cli.poll() is None:
            cli.kill()
            cli.communicate()

    assert 130 == cli.returncode, stderr
    assert 1 <= len(rows(out / "runs.csv")) < 5
    assert [] == alive(f"{cli.pid}-")
    assert "interrupted: " in stdout
    assert (out / "recovery.png").exists()
    assert "Traceback" not in stderr


def finished_run() -> RunResult:
    return RunResult(
        plan="tiny",
        setting="tree.strategy",
        value="one_for_all",
        run=1,
        repeat=1,
        seed=7,
        version=rr.__version__,
        started_at=0.0,
        duration_s=1.0,
        calls_ok=9,
        calls_failed=1,
        calls_retried=2,
        unavailable_s={"db": 0.25},
        restarts=3,
        gave_up=False,
        recovery_median_s=0.125,
        recovery_p90_s=0.25,
        unrecovered=0,
        leaked_processes=0,
        catalog_entries_left=0,
        events=10,
        events_dropped=0,
    )


@pytest.mark.parametrize("stream", [FakeTerminal(), io.StringIO()], ids=["terminal", "pipe"])
def test_progress_draws_a_bar_on_a_terminal_and_one_line_per_run_everywhere(
    stream: io.StringIO,
) -> None:
    with Display(stream, quiet=False) as display:
        for elapsed in (0.25, 0.5, 1.0):
            display(Progress(1, 2, "tree.strategy", "one_for_all", 7, elapsed, 1.0))
        display(Progress(1, 2, "tree.strategy", "one_for_all", 7, 1.0, 1.0, finished_run()))

    line = "run 1/2 one_for_all seed 7: 9 calls ok, 1 failed, 3 restarts, rec. p50 125 ms"
    assert line in " ".join(stream.getvalue().split())  # (a terminal's has control codes)
    assert (display.bar is not None) == isinstance(stream, FakeTerminal)


@pytest.mark.parametrize(
    "changes",
    [
        {"value": "rest_for_one"},  # the tutorial's first experiment
        {"run": 12, "value": "rest_for_one", "calls_ok": 1234, "calls_failed": 123},
        {
            "run": 100,
            "seed": 100,
            "value": "x" * 60,
            "calls_ok": 12345,
            "calls_failed": 1234,
            "restarts": 100,
            "recovery_median_s": 12.345,
            "gave_up": True,
        },
    ],
    ids=["tutorial", "long-run", "everything-long"],
)
def test_a_piped_run_line_is_at_most_80_columns(changes: dict[str, object]) -> None:
    stream = io.StringIO()
    result = dataclasses.replace(finished_run(), **changes)  # type: ignore[arg-type]

    with Display(stream, quiet=False) as display:
        display(Progress(1, 100, "tree.strategy", result.value, 7, 1.0, 1.0, result))
    lines = stream.getvalue().splitlines()

    assert [] == [line for line in lines if len(line) > 80]
    assert lines[0].startswith(f"run {result.run}/100 ")


def test_a_run_that_fails_exits_1_quoting_its_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "broken_managers.py").write_text(
        "def setup(registrar):\n    raise RuntimeError('the driver is missing')\n"
    )
    plan = write_plan(tmp_path, PLAN.format(duration=1.0).replace(SERVICE, "broken_managers:setup"))

    code = main(["experiment", str(plan), "--out", str(tmp_path / "out")])

    assert 1 == code
    err = capsys.readouterr().err
    assert err.startswith("rr-actors experiment: run 1 failed (exit code 1):")
    assert "the driver is missing" in err


STOPPED_PLAN = PLAN.replace("clients = 1\nrate = 10.0", "clients = 2\nrate = 20.0")
"""`PLAN` with twice the calls: a stop finds some in flight."""

CODE = "import sys; from rr_actors_lab.__main__ import main; sys.exit(main(sys.argv[1:]))"


def start(tmp_path: Path, out: Path, *extra: str) -> tuple[subprocess.Popen[str], Path]:
    """The command as a program of its own, with its own temporary directory."""
    plan = tmp_path / "plan.toml"
    plan.write_text(STOPPED_PLAN.format(duration=2.0))
    temp = tmp_path / "temp"
    temp.mkdir()
    cli = subprocess.Popen(
        [sys.executable, "-c", CODE, "experiment", str(plan), "--out", str(out), *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1", "TMPDIR": str(temp)},
    )
    return cli, temp


def rows(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with path.open(newline="") as file:
        return list(csv.DictReader(file))


def alive(token_prefix: str) -> list[int]:
    wanted = f"RR_ACTORS_EXPERIMENT={token_prefix}".encode()
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            environ = (entry / "environ").read_bytes().split(b"\0")
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if state != "Z" and any(item.startswith(wanted) for item in environ):
            found.append(int(entry.name))
    return found


def finish(cli: subprocess.Popen[str]) -> tuple[str, str]:
    try:
        return cli.communicate(timeout=60)
    finally:
        if cli.poll() is None:
            cli.kill()
            cli.communicate()


class TestStopped:
    """`rr-actors experiment` stopped by signals and by a full disk (issue 21: bug 8 and a
    weakness).

    A second Ctrl-C lands while the finished runs are plotted: no traceback. A SIGTERM stops
    the experiment as a Ctrl-C does (exit 143) and leaves no `rr-experiment-*` directory in
    the temporary directory; so does a SIGHUP (exit 129; issue 29, item 11), and no process.
    A full disk under `--out`: one line, exit 1, and files that agree.
    """

    @pytest.fixture
    def tmp_path(self) -> Iterator[Path]:
        """A short temporary directory (pytest's own, under pytest-xdist, is too long).

        The command's run processes start a forkserver whose socket lives under their
        temporary directory, which is under this one: an AF_UNIX path has at most 107 bytes.
        """
        short = Path(tempfile.mkdtemp(prefix="rr-", dir="/tmp"))
        try:
            yield short
        finally:
            shutil.rmtree(short, ignore_errors=True)

    @pytest.mark.timeout(180)
    def test_a_second_ctrl_c_while_the_runs_are_plotted_prints_no_traceback(
        self, tmp_path: Path, eventually: Callable[..., bool]
    ) -> None:
        out = tmp_path / "out"
        cli, temp = start(tmp_path, out, "--repeat", "5")
        try:
            assert eventually(lambda: len(rows(out / "runs.csv")) >= 1, timeout=40)
            assert eventually(lambda: len(alive(f"{cli.pid}-")) > 0, timeout=20)
            cli.send_signal(signal.SIGINT)
            assert eventually(lambda: [] == alive(f"{cli.pid}-"), timeout=30)  # it is cleaning up
            while cli.poll() is None:  # Ctrl-C again and again, while it plots and ends
                cli.send_signal(signal.SIGINT)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    cli.wait(timeout=0.05)
        finally:
            stdout, stderr = finish(cli)

        assert 130 == cli.returncode, stderr
        assert "Traceback" not in stderr
        assert "interrupted: " in stdout
        assert (out / "recovery.png").exists()
        assert [] == list(temp.glob("rr-experiment-*"))

    @pytest.mark.timeout(180)
    def test_sigterm_stops_it_like_ctrl_c_and_leaves_no_work_directory(
        self, tmp_path: Path, eventually: Callable[..., bool]
    ) -> None:
        out = tmp_path / "out"
        cli, temp = start(tmp_path, out, "--repeat", "5")
        try:
            assert eventually(lambda: len(list(temp.glob("rr-experiment-*"))) == 1, timeout=20)
            assert eventually(lambda: len(alive(f"{cli.pid}-")) > 0, timeout=20)
            cli.send_signal(signal.SIGTERM)
        finally:
            stdout, stderr = finish(cli)

        assert 143 == cli.returncode, stderr
        assert "Traceback" not in stderr
        assert [] == list(temp.glob("rr-experiment-*"))
        assert [] == alive(f"{cli.pid}-")
        assert "interrupted: " in stdout

    @pytest.mark.timeout(180)
    @pytest.mark.parametrize(
        ("signum", "code"), [(signal.SIGHUP, 129), (signal.SIGTERM, 143)], ids=["SIGHUP", "SIGTERM"]
    )
    def test_a_hangup_or_sigterm_leaves_no_work_directory_and_no_process(
        self, tmp_path: Path, eventually: Callable[..., bool], signum: int, code: int
    ) -> None:
        out = tmp_path / "out"
        cli, temp = start(tmp_path, out, "--repeat", "5")
        try:
            assert eventually(lambda: len(list(temp.glob("rr-experiment-*"))) == 1, timeout=20)
            assert eventually(lambda: len(alive(f"{cli.pid}-")) > 0, timeout=20)
            started = psutil.Process(cli.pid).children(recursive=True)  # the run's processes
            cli.send_signal(signum)
        finally:
            stdout, stderr = finish(cli)
        _, left = psutil.wait_procs(started, timeout=10)

        assert code == cli.returncode, stderr
        assert [] == list(temp.glob("rr-experiment-*"))
        assert ([], []) == (left, alive(f"{cli.pid}-"))
        assert "interrupted: " in stdout

    @pytest.mark.timeout(180)
    def test_a_full_disk_under_out_is_one_line_exit_1_and_files_that_agree(
        self, tmp_path: Path
    ) -> None:
        with mounted(tmp_path / "disk", size="1m") as disk:
            filler = fill(disk)
            os.truncate(
                filler, filler.stat().st_size - 8192
            )  # 8 KiB left: less than a run's events
            out = disk / "out"
            cli, temp = start(tmp_path, out, "--repeat", "2")
            stdout, stderr = finish(cli)

            events = (out / "events.jsonl").read_bytes() if (out / "events.jsonl").exists() else b""
            listed = {row["run"] for row in rows(out / "runs.csv")}
            logged = {str(json.loads(line)["run"]) for line in events.splitlines()}
            faulted = {row["run"] for row in rows(out / "faults.csv")}
            leftovers = sorted(p.name for p in out.iterdir() if p.name.endswith((".tmp", ".png")))

        assert 1 == cli.returncode, stderr
        assert 1 == len(stderr.splitlines()), stderr
        assert stderr.startswith(f"rr-actors experiment: cannot write to {out}/ (No space left")
        assert "run 1 was not added; the files hold the 0 run(s) before it" in stderr
        assert events == b"" or events.endswith(b"\n")  # no run's events cut mid-line
        assert listed == logged == faulted == set()
        assert [] == leftovers
        assert [] == list(temp.glob("rr-experiment-*"))
        assert "Traceback" not in stdout + stderr

    @pytest.mark.timeout(180)
    def test_a_disk_that_fills_up_after_a_run_keeps_that_run_in_every_file(
        self, tmp_path: Path
    ) -> None:
        measure = tmp_path / "measure"
        measured, _ = start(tmp_path, measure, "--repeat", "1")
        assert 0 == measured.wait(timeout=60)
        finish(measured)
        one_run = sum(p.stat().st_size for p in measure.iterdir() if not p.name.endswith(".png"))
        (tmp_path / "temp").rename(tmp_path / "measured-temp")
        with mounted(tmp_path / "disk", size="4m") as disk:
            filler = fill(disk)
            room = (one_run * 3 // 2 // 4096 + 1) * 4096  # run 1 fits (same seed), run 2 does not
            os.truncate(filler, max(0, filler.stat().st_size - room))
            out = disk / "out"
            cli, temp = start(tmp_path, out, "--repeat", "2")
            stdout, stderr = finish(cli)

            events = (out / "events.jsonl").read_bytes()
            listed = {row["run"] for row in rows(out / "runs.csv")}
            logged = {str(json.loads(line)["run"]) for line in events.splitlines()}
            faulted = {row["run"] for row in rows(out / "faults.csv")}

        assert 1 == cli.returncode, stdout + stderr
        # One line says what was lost; a plot that no longer fits either (how much room the
        # run left depends on how many events it had, which a loaded machine changes) says so
        # in one line of its own.
        said = stderr.splitlines()
        assert 1 == len([line for line in said if "run 2 was not added" in line]), stderr
        assert "run 2 was not added; the files hold the 1 run(s) before it" in stderr
        assert all(
            "run 2 was not added" in line
            or line.endswith(".png not drawn: No space left on device")
            for line in said
        ), stderr
        assert events.endswith(b"\n")
        assert listed == logged == faulted == {"1"}
        assert [] == list(temp.glob("rr-experiment-*"))


WIDE_PLAN = f"""\
name = "tiny"
duration = 1.0

[tree]
max_restarts = 20

[[tree.children]]
name = "a_manager_with_a_rather_long_name"
setup = "{SERVICE}"

[workload]
clients = 1
rate = 10.0

[[workload.calls]]
manager = "a_manager_with_a_rather_long_name"
server = "resource"

[[faults]]
kind = "kill_manager"
target = "a_manager_with_a_rather_long_name"
at = 0.5

[compare]
setting = "tree.children.a_manager_with_a_rather_long_name.heartbeat"
values = [0.25, 0.5]
"""


class TestOnAn80ColumnTerminal:
    """`rr-actors experiment` on an 80-column terminal draws nothing wider (issue 24, item 7).

    The command runs as a real program whose standard output is a pseudo-terminal, as in a
    shell, with `COLUMNS=80`; the summary is a `rich` table that shows `calls_retried`.
    """

    @pytest.mark.timeout(150)
    def test_on_an_80_column_terminal_the_experiment_draws_nothing_wider(
        self, tmp_path: Path
    ) -> None:
        plan = tmp_path / "plan.toml"
        plan.write_text(WIDE_PLAN)
        code = "import sys; from rr_actors_lab.__main__ import main; sys.exit(main(sys.argv[1:]))"
        out = tmp_path / "out"

        status, text = on_a_terminal(
            [sys.executable, "-c", code, "experiment", str(plan), "--out", str(out)],
            columns=80,
            timeout=90,
        )

        assert 0 == status, text
        drawn = [
            piece for line in text.split("\n") for piece in line.split("\r")
        ]  # each from column 0
        assert max(len(piece) for piece in drawn) <= 80, max(drawn, key=len)
        lines = [piece for piece in drawn if piece.strip()]
        assert any("retried" in line for line in lines)
        assert any(line.startswith("run 2/2 ") for line in lines)
        assert any("written to" in line for line in lines)

    def test_the_plain_summary_fits_80_columns_and_shows_the_retried_calls(self) -> None:
        plan = parse_plan(WIDE_PLAN)
        run = dataclasses.replace(
            finished_run(),
            setting=plan.setting_label(),
            value=0.25,
            seed=0,
            version="0",
            calls_ok=9999,
            calls_failed=1234,
            calls_retried=4321,
            unavailable_s={"a": 1234.5},
        )

        lines = summary_lines(Results(plan=plan, runs=(run,), out=None))

        assert "tree.children.a_manager_with_a_rather_long_name.heartbeat" == lines[0]  # whole
        assert "retried" in lines[1].split()  # (the header's cells, under it)
        assert "4321.0" in lines[2].split()
        assert all(len(line) <= 80 for line in lines), lines
