"""`rr-actors demo` as a newcomer meets it: its output on a terminal or a pipe, its errors.

The mission itself is tested in `test_mission.py`; here: what is printed (and that it
fits an 80-column terminal), `--quiet`, and the command-line errors (exit code 2, one
line on standard error, no traceback).
"""

from __future__ import annotations

import contextlib
import io
import itertools
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from rich.console import Console

from rr_actors.mission import FAULTS, FaultResult, MissionError, MissionReport, UnplannedRestart
from rr_actors.mission.config import MissionConfig
from rr_actors.mission.output import (
    PlainOutput,
    Progress,
    RichOutput,
    make_output,
    progress_table,
    timeline,
)
from rr_actors.mission.run import _hooks, _mission_clock, main, parser, run, run_mission
from tests.support.small_disk import mounted, remount_read_only
from tests.support.terminal import on_a_terminal

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def report_with_everything() -> MissionReport:
    """A report of a long mission: all five faults and an unplanned restart of each manager."""
    faults = tuple(
        FaultResult(f, "x" * 40, 100.0 + i, 12.345, 123.456, 99.999) for i, f in enumerate(FAULTS)
    )
    restarts = tuple(UnplannedRestart(m, 200.0, 4_194_304) for m in ("erm", "cm", "rm"))
    return MissionReport(
        mission_time_s=1234.5,
        distance_m=160.0,
        nominal_time_s=320.0,
        faults=faults,
        leaked_processes=0,
        catalog_entries_left=0,
        catalog_entries_by_registrar={},
        trace=(),
        stops=(),
        unplanned_restarts=restarts,
    )


def widest(text: str) -> int:
    return max(len(line) for line in ANSI.sub("", text).splitlines())


class FakeTerminal(io.StringIO):
    """A stream that says it is a terminal (as `rr-actors demo` on a real one sees it)."""

    def isatty(self) -> bool:
        return True


# -- fitting 80 columns --------------------------------------------------------------------


def test_the_plain_timeline_fits_80_columns() -> None:
    text = timeline(report_with_everything())

    assert widest(text) <= 80
    assert 5 + 3 == sum(1 for line in text.splitlines() if re.match(r"(F\d|-) ", line))


def test_the_rich_timeline_fits_an_80_column_terminal() -> None:
    console = Console(file=io.StringIO(), width=80, record=True, force_terminal=True)

    RichOutput(console, quiet=True).summary(report_with_everything(), ["report: x/report.json"])
    text = console.export_text()

    assert widest(text) <= 80
    assert "erm exited, no fault" in text
    assert "leaked processes: 0; catalog entries left: 0" in text


@pytest.mark.parametrize("status", ["", "F3: external resource manager killed" * 3])
def test_the_progress_line_is_one_line_of_at_most_80_columns(status: str) -> None:
    console = Console(file=io.StringIO(), width=80, record=True, force_terminal=True)

    console.print(progress_table(Progress(1234.56, 123.45, 160.0, True, status)))
    lines = console.export_text().splitlines()

    assert 1 == len(lines)
    assert len(lines[0]) <= 80


def test_a_long_story_line_wraps_under_its_text_on_a_terminal() -> None:
    console = Console(file=io.StringIO(), width=40, record=True, force_terminal=True)

    RichOutput(console).story("[  1.23 s] " + "word " * 12)
    lines = console.export_text().splitlines()

    assert len(lines) > 1
    assert all(line.startswith(" " * 11) for line in lines[1:])


# -- choosing the output -------------------------------------------------------------------


def test_a_pipe_gets_plain_lines_and_a_terminal_gets_rich() -> None:
    assert isinstance(make_output(io.StringIO()), PlainOutput)
    assert isinstance(make_output(FakeTerminal()), RichOutput)


def test_a_terminal_without_rich_gets_plain_lines(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rich.console", None)

    assert isinstance(make_output(FakeTerminal()), PlainOutput)


@pytest.mark.usefixtures("process_helpers")
def test_on_an_80_column_terminal_the_demo_draws_nothing_wider(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("COLUMNS", "80")
    monkeypatch.delenv("NO_COLOR", raising=False)
    terminal = FakeTerminal()
    args = parser().parse_args(
        ["--fast", "--faults", "F1", "--distance", "2", "--out", str(tmp_path)]
    )

    code = run(args, terminal)
    text = terminal.getvalue()

    assert 0 == code
    assert widest(text) <= 80
    assert "F1 injected" in ANSI.sub("", text)
    assert "LiDAR 1 disconnected" in ANSI.sub("", text)


MANAGER_WRITES = textwrap.dedent(
    """
    import logging, sys
    import rr_actors as rr
    from rr_actors.mission.output import Progress, make_output

    def setup(erm):  # in the manager's process, logging not configured: to its stderr
        logging.getLogger("rr_actors").warning(
            "manager %s: %s", erm.name, "a line of a manager's process " * 6
        )
        erm.register_server("echo", load=lambda r: r, unload=lambda r, s: None)

    if __name__ == "__main__":
        with make_output(sys.stdout) as output:
            output.progress(Progress(1.0, 2.0, 16.0, True, "F3: cm killed"))
            with rr.Supervisor([rr.ManagerSpec("erm", setup, isolation="process")]):
                output.story("[  1.00 s] erm is up")
    """
)


@pytest.mark.timeout(120)
def test_a_line_another_process_writes_under_the_progress_line_starts_a_line_and_wraps(
    tmp_path: Path,
) -> None:
    """A manager process writes to the demo's terminal while the progress line shows
    (its WARNING, before its setup sends the log to the run's file): the line goes above
    the progress line and wraps at words, instead of running on from the progress line's
    end, 80 columns plus its own (121 in a loaded CI run of `--step`; issue 44 item 2)."""
    code, text = on_a_terminal(
        [sys.executable, "-c", MANAGER_WRITES], columns=80, timeout=90, cwd=tmp_path
    )

    lines = text.splitlines()  # (at \r too: the progress line is redrawn after one)
    wide = [f"[{len(line)}] {line}" for line in lines if len(line) > 80]
    assert 0 == code, text
    assert [] == wide, "lines over 80 columns:\n" + "\n".join(wide)
    start = next(i for i, line in enumerate(lines) if line.startswith("WARNING rr_actors: "))
    record = [
        lines[start],
        *itertools.takewhile(lambda x: x.startswith("    "), lines[start + 1 :]),
    ]
    said = "WARNING rr_actors: manager erm: " + "a line of a manager's process " * 6
    assert " ".join(said.split()) == " ".join(" ".join(record).split())
    assert any(line.startswith("[  1.00 s] erm is up") for line in lines)


# -- --quiet -------------------------------------------------------------------------------


def test_quiet_help_says_it_prints_only_the_timeline() -> None:
    help_text = " ".join(parser().format_help().split())

    assert "--quiet no story and no progress line: print only the timeline" in help_text


# -- errors --------------------------------------------------------------------------------


def demo(*argv: str) -> subprocess.CompletedProcess[str]:
    """`rr-actors demo ARGV` as a separate program (60 s at most)."""
    return subprocess.run(
        [sys.executable, "-m", "rr_actors", "demo", *argv],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


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

    def observe(self, **_: object) -> ClockedObserver:
        return self.observer


def test_the_page_calls_its_clock_the_mission_clock_and_only_the_total_is_mission_time() -> None:
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
