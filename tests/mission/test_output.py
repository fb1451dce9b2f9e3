"""What `rr-actors demo` shows (`rr_actors_lab.mission.output`): the story, the progress line and
the timeline, on a pipe or a terminal, within 80 columns."""

from __future__ import annotations

import io
import re
import sys
from pathlib import Path

import pytest
from rich.console import Console

from rr_actors_lab.mission.output import (
    PlainOutput,
    Progress,
    RichOutput,
    make_output,
    progress_table,
    timeline,
)
from rr_actors_lab.mission.run import parser, run
from tests.support.demos import ANSI, report_with_everything
from tests.support.terminal import FakeTerminal


def widest(text: str) -> int:
    return max(len(line) for line in ANSI.sub("", text).splitlines())


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
