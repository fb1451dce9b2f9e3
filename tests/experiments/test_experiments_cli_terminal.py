"""`rr-actors experiment` on an 80-column terminal draws nothing wider (issue 24, item 7).

The command runs as a real program whose standard output is a pseudo-terminal, as in a
shell, with `COLUMNS=80`; the summary is a `rich` table that shows `calls_retried`.
"""

from __future__ import annotations

import os
import pty
import re
import select
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rr_actors.experiments import parse_plan
from rr_actors.experiments.cli import summary_lines
from rr_actors.experiments.results import Results, RunResult

SERVICE = "rr_actors.experiments.services:service"
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07]*\x07")

PLAN = f"""\
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


def on_a_terminal(argv: list[str], *, columns: int, timeout: float) -> tuple[int, str]:
    """Run `argv` with a pseudo-terminal as its standard output; its exit code and text."""
    parent, child = pty.openpty()
    env = {**os.environ, "COLUMNS": str(columns), "TERM": "xterm-256color"}
    env.pop("NO_COLOR", None)
    process = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=child, stderr=child, env=env)
    os.close(child)
    chunks: list[bytes] = []
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            ready, _, _ = select.select([parent], [], [], 1.0)
            if not ready:
                continue
            try:
                chunk = os.read(parent, 65536)
            except OSError:  # EIO: the program closed the terminal
                break
            if not chunk:
                break
            chunks.append(chunk)
        code = process.wait(timeout=max(1.0, deadline - time.monotonic()))
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        os.close(parent)
    return code, ANSI.sub("", b"".join(chunks).decode(errors="replace"))


@pytest.mark.timeout(150)
def test_on_an_80_column_terminal_the_experiment_draws_nothing_wider(tmp_path: Path) -> None:
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN)
    code = "import sys; from rr_actors.__main__ import main; sys.exit(main(sys.argv[1:]))"
    out = tmp_path / "out"

    status, text = on_a_terminal(
        [sys.executable, "-c", code, "experiment", str(plan), "--out", str(out)],
        columns=80,
        timeout=90,
    )

    assert 0 == status, text
    drawn = [piece for line in text.split("\n") for piece in line.split("\r")]  # each from column 0
    assert max(len(piece) for piece in drawn) <= 80, max(drawn, key=len)
    lines = [piece for piece in drawn if piece.strip()]
    assert any("retried" in line for line in lines)
    assert any(line.startswith("run 2/2 ") for line in lines)
    assert any("written to" in line for line in lines)


def test_the_plain_summary_fits_80_columns_and_shows_the_retried_calls() -> None:
    plan = parse_plan(PLAN)
    run = RunResult(
        plan="tiny",
        setting=plan.setting_label(),
        value=0.25,
        run=1,
        repeat=1,
        seed=0,
        version="0",
        started_at=0.0,
        duration_s=1.0,
        calls_ok=9999,
        calls_failed=1234,
        calls_retried=4321,
        unavailable_s={"a": 1234.5},
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

    lines = summary_lines(Results(plan=plan, runs=(run,), out=None))

    assert "tree.children.a_manager_with_a_rather_long_name.heartbeat" == lines[0]  # whole
    assert "retried" in lines[1].split()  # (the header's cells, under it)
    assert "4321.0" in lines[2].split()
    assert all(len(line) <= 80 for line in lines), lines
