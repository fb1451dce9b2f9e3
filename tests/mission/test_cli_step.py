"""`rr-actors demo --step` on an 80-column terminal: rich output, and pauses left out of time.

A class takes its time before pressing Enter: here each Enter comes `PAUSE` seconds
after the prompt. None of that may count as mission time (the story's stamps, the
timeline, the totals) or as the robot standing still (the plot's shading).
"""

from __future__ import annotations

import io
import json
import re
import sys
import threading
from pathlib import Path

import pytest

from rr_actors.mission.run import parser, run

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
PAUSE = 1.5
"""Seconds the class takes before each Enter."""


class FakeTerminal(io.StringIO):
    """A stream that says it is a terminal (as `rr-actors demo` on a real one sees it)."""

    def isatty(self) -> bool:
        return True


class SlowClass(io.StringIO):
    """Standard input where every Enter comes `PAUSE` seconds after it is waited for."""

    def __init__(self) -> None:
        super().__init__()
        self.enters = 0

    def readline(self, size: int | None = -1) -> str:  # type: ignore[override]
        del size
        threading.Event().wait(PAUSE)  # a person, not a synchronisation
        self.enters += 1
        return "\n"


@pytest.mark.usefixtures("process_helpers")
@pytest.mark.timeout(120)
def test_step_on_an_80_column_terminal_fits_and_leaves_the_pauses_out_of_every_time(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("COLUMNS", "80")
    monkeypatch.delenv("NO_COLOR", raising=False)
    stdin = SlowClass()
    monkeypatch.setattr(sys, "stdin", stdin)
    terminal = FakeTerminal()
    args = parser().parse_args(["--fast", "--step", "--out", str(tmp_path)])

    code = run(args, terminal)
    text = "\n".join(ANSI.sub("", terminal.getvalue()).splitlines())  # \r: live redraws
    report = json.loads((tmp_path / "report.json").read_text())
    stamps = [float(m) for m in re.findall(r"^\[\s*([0-9.]+) s\]", text, re.MULTILINE)]
    arrived = re.search(r"^\[\s*([0-9.]+) s\] goal reached after ([0-9.]+) s", text, re.M)

    assert 0 == code
    assert 5 == stdin.enters
    assert max(len(line) for line in text.splitlines()) <= 80  # rich wrapped the long lines
    assert 5 * PAUSE <= report["paused_for_enter_s"] < 5 * PAUSE + 2.0
    assert 5 == len(report["pauses_at_s"])
    assert "paused for Enter 5 time(s)" in text
    # No time shown counts a pause: not the drive, not a stop, not a stamp.
    assert report["mission_time_s"] < report["nominal_time_s"] + PAUSE
    assert all(b - a < PAUSE / 2 for a, b in report["stops"])
    assert all(f["robot_stopped_s"] < PAUSE / 2 for f in report["faults"])
    assert stamps[-1] < report["drive_started_at_s"] + report["mission_time_s"] + PAUSE
    # One clock: the story's "goal reached" stamp is where the report's drive ends.
    assert arrived is not None
    assert float(arrived[1]) == pytest.approx(
        report["drive_started_at_s"] + report["mission_time_s"], abs=0.1
    )
    assert float(arrived[2]) == pytest.approx(report["mission_time_s"], abs=0.01)
