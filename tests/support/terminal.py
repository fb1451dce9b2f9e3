"""Run a program on a pseudo-terminal of a given width, as in a user's shell.

The program's standard output and error are the terminal (`pty.openpty`), whose window
size is set with `TIOCSWINSZ` and `COLUMNS` both (`rich` and `argparse` read one or the
other); what it wrote comes back without its control codes, split where the terminal
would start a line again (`\\n` and `\\r`).
"""

from __future__ import annotations

import fcntl
import io
import os
import pty
import re
import struct
import subprocess
import termios
import time
from collections.abc import Callable
from pathlib import Path

from tests.support import selecting

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07]*\x07")


def on_a_terminal(
    argv: list[str], *, columns: int, timeout: float, cwd: Path | None = None
) -> tuple[int, str]:
    """Run `argv` with a `columns`-wide pseudo-terminal as its output; its exit code and text."""
    parent, child = pty.openpty()
    fcntl.ioctl(child, termios.TIOCSWINSZ, struct.pack("HHHH", 40, columns, 0, 0))
    env = {**os.environ, "COLUMNS": str(columns), "LINES": "40", "TERM": "xterm-256color"}
    env.pop("NO_COLOR", None)
    process = subprocess.Popen(
        argv, stdin=subprocess.DEVNULL, stdout=child, stderr=child, env=env, cwd=cwd
    )
    os.close(child)
    chunks: list[bytes] = []
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            ready, _, _ = selecting.select([parent], [], [], 1.0)
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


class FakeTerminal(io.StringIO):
    """A stream that says it is a terminal (as a command on a real one sees it)."""

    def isatty(self) -> bool:
        return True


def drawn(text: str) -> list[str]:
    """Each piece of `text` a terminal draws from column 0 (split at `\\n` and `\\r`)."""
    return [piece for line in text.split("\n") for piece in line.split("\r")]


class Terminal:
    """A program on a `columns`-wide pseudo-terminal that a test talks to while it runs.

    As `on_a_terminal`, but its standard input is a pipe the test writes to (`send`), and
    the test can wait for a text to appear (`wait_for`) before it acts (starves one of the
    program's processes, say). `finish` ends the input and returns the exit code and all
    the text, without control codes.
    """

    def __init__(self, argv: list[str], *, columns: int, cwd: Path | None = None) -> None:
        self._parent, child = pty.openpty()
        fcntl.ioctl(child, termios.TIOCSWINSZ, struct.pack("HHHH", 40, columns, 0, 0))
        env = {**os.environ, "COLUMNS": str(columns), "LINES": "40", "TERM": "xterm-256color"}
        env.pop("NO_COLOR", None)
        self.process = subprocess.Popen(
            argv, stdin=subprocess.PIPE, stdout=child, stderr=child, env=env, cwd=cwd
        )
        os.close(child)
        self._chunks: list[bytes] = []
        self._ended = False

    @property
    def text(self) -> str:
        """What the program wrote so far, without control codes."""
        return ANSI.sub("", b"".join(self._chunks).decode(errors="replace"))

    def _read(self, timeout: float) -> None:
        """Read what the terminal holds, waiting `timeout` s at most for something."""
        if self._ended:
            return
        ready, _, _ = selecting.select([self._parent], [], [], timeout)
        if not ready:
            return
        try:
            chunk = os.read(self._parent, 65536)
        except OSError:  # EIO: the program closed the terminal
            chunk = b""
        if chunk:
            self._chunks.append(chunk)
        else:
            self._ended = True

    def wait_for(self, found: Callable[[str], bool], timeout: float) -> bool:
        """Read until `found(text)` holds or `timeout` s passed (or the program ended)."""
        deadline = time.monotonic() + timeout
        while not found(self.text):
            if self._ended or time.monotonic() >= deadline:
                return False
            self._read(min(1.0, max(0.0, deadline - time.monotonic())))
        return True

    def send(self, line: str) -> None:
        """Write `line` and a line break to the program's standard input."""
        assert self.process.stdin is not None
        self.process.stdin.write(line.encode() + b"\n")
        self.process.stdin.flush()

    def finish(self, timeout: float) -> tuple[int, str]:
        """Close its input, read until it closes the terminal; its exit code and text."""
        assert self.process.stdin is not None
        self.process.stdin.close()
        deadline = time.monotonic() + timeout
        try:
            while not self._ended and time.monotonic() < deadline:
                self._read(1.0)
            code = self.process.wait(timeout=max(1.0, deadline - time.monotonic()))
        finally:
            self.close()
        return code, self.text

    def close(self) -> None:
        """Kill the program if it still runs; close the terminal."""
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()
        if self._parent >= 0:
            os.close(self._parent)
            self._parent = -1
