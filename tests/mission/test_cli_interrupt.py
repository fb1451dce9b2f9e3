"""Ctrl-C in `rr-actors demo`, in a real terminal: one line, exit code 130, nothing left.

A terminal's Ctrl-C sends SIGINT to its whole foreground process group: the demo, the
forkserver, every manager and spare process. Here the demo runs in a session of its own
on a pseudo-terminal, and the test sends SIGINT to that group (`os.killpg`), as the
terminal would. Only the demo may act on it: it unloads everything, stops the managers
in order and says so in one line.
"""

from __future__ import annotations

import json
import os
import re
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
LINE = re.compile(r"^interrupted at \d+\.\d s: unloading\.\.\. everything unloaded$")
STORY = re.compile(r"^\[\s*\d+\.\d+ s\] ")  # a line of the story ("[  0.77 s] driving ...")
PROMPT = "press Enter to inject it"  # --step's prompt, redrawn as the terminal's lines settle


def one_line_after_the_story(after: str) -> bool:
    """Whether the output after the SIGINT is the one line, after at most story lines.

    A story line the demo was printing as the signal came (its printer thread does not
    wait for the prompt), or the rest of the prompt's line, may still land first on a
    loaded machine.
    """
    *story, last = after.splitlines() or [""]
    return bool(LINE.match(last)) and all(
        STORY.match(line) or line.startswith(PROMPT) for line in story
    )


def interrupt_demo(tmp_path: Path, when: bytes, *options: str) -> tuple[int, str, str, list]:
    """Run the demo on a pty, SIGINT its process group once `when` shows; wait for its end.

    Returns:
        The exit code, the output before the SIGINT, the output after it, and the
        processes of the demo's tree when it was sent.
    """
    master, slave = os.openpty()
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES", "NO_COLOR")}
    demo = subprocess.Popen(
        [sys.executable, "-m", "rr_actors", "demo", "--fast", *options],
        cwd=tmp_path,
        stdin=slave,
        stdout=slave,
        stderr=slave,
        env={**env, "TERM": "xterm-256color"},
        start_new_session=True,  # its own process group, as a terminal's foreground job
    )
    os.close(slave)
    before = after = b""
    tree: list[psutil.Process] = []
    deadline = time.monotonic() + 90
    try:
        while time.monotonic() < deadline:
            readable, _, _ = select.select([master], [], [], 1.0)
            if readable:
                try:
                    chunk = os.read(master, 65536)
                except OSError:  # the demo ended: its side of the terminal closed
                    break
                if not chunk:
                    break
                if tree:
                    after += chunk
                else:
                    before += chunk
            if not tree and when in before:
                tree = psutil.Process(demo.pid).children(recursive=True)
                os.killpg(demo.pid, signal.SIGINT)  # what Ctrl-C in its terminal does
        code = demo.wait(30)
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait(10)
        os.close(master)
    return code, clean(before), clean(after), tree


def clean(output: bytes) -> str:
    """The text a reader sees: no colours, no redrawn progress lines, no blank lines."""
    text = ANSI.sub("", output.decode(errors="replace"))
    lines = (line.rsplit("\r", 1)[-1].strip() for line in text.replace("\r\n", "\n").split("\n"))
    return "\n".join(line for line in lines if line and "━" not in line)


def assert_nothing_left(tmp_path: Path, tree: list[psutil.Process]) -> None:
    """Every process of the demo's tree ends (bounded), and no program of the mission lives."""
    assert tree  # the managers were running
    _, alive = psutil.wait_procs(tree, timeout=20)  # the forkserver ends after the demo
    assert [] == alive
    for record in (tmp_path / "rr-actors-demo" / "bus" / "pids").glob("*.json"):
        pid = json.loads(record.read_text())["pid"]
        assert not psutil.pid_exists(pid) or psutil.Process(pid).status() == "zombie"


@pytest.mark.usefixtures("process_helpers")
@pytest.mark.timeout(150)
def test_ctrl_c_while_the_robot_drives_prints_one_line_and_exits_130(tmp_path: Path) -> None:
    code, before, after, tree = interrupt_demo(tmp_path, b"driving")

    assert "driving" in before
    assert 130 == code, after
    assert one_line_after_the_story(after), after  # the one line, and nothing else
    assert "Traceback" not in after
    assert_nothing_left(tmp_path, tree)


@pytest.mark.usefixtures("process_helpers")
@pytest.mark.timeout(150)
def test_ctrl_c_at_the_step_prompt_prints_one_line_and_exits_130(tmp_path: Path) -> None:
    code, before, after, tree = interrupt_demo(tmp_path, b"press Enter", "--step")

    assert "press Enter" in before
    assert 130 == code, after
    assert one_line_after_the_story(after), after
    assert "Traceback" not in after
    assert_nothing_left(tmp_path, tree)
