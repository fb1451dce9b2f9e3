"""Run a program on a pseudo-terminal of a given width, as in a user's shell.

The program's standard output and error are the terminal (`pty.openpty`), whose window
size is set with `TIOCSWINSZ` and `COLUMNS` both (`rich` and `argparse` read one or the
other); what it wrote comes back without its control codes, split where the terminal
would start a line again (`\\n` and `\\r`).
"""

from __future__ import annotations

import fcntl
import os
import pty
import re
import select
import struct
import subprocess
import termios
import time
from pathlib import Path

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


def drawn(text: str) -> list[str]:
    """Each piece of `text` a terminal draws from column 0 (split at `\\n` and `\\r`)."""
    return [piece for line in text.split("\n") for piece in line.split("\r")]
