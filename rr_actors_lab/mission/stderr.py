"""The terminal's standard error while `rich` draws the demo's live progress line.

```
 this process, and every process it starts from now on (the forkserver, the managers:
 they inherit its fd 2)
     write to fd 2 ──► a pipe ──► reader thread ──► open: show(line), one line at a time
                                                     (RichOutput: above the progress
                                                     line, wrapped at words)
                                                 └► closed: the bytes to the terminal,
                                                     as they come
```

`rich` redraws its live line in place, so a line another process writes to the terminal
meanwhile runs on from the cursor; `rich` only redirects its own process's `sys.stderr`.
So while the output is open, fd 2 is a pipe whose lines the output shows. Only when fd 2
is the terminal the output draws on (`open` returns `None` otherwise). After `close`, fd 2
is the terminal again, and the reader passes on what earlier children still write.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import threading
from collections.abc import Callable
from typing import IO

__all__ = ["StderrLines"]

STDERR = 2

CLOSE_WAIT = 2.0
"""Seconds `close` waits at most for the reader to show what was written before it."""

_BREAK = re.compile(rb"\r\n|\r|\n")
_MARK = b"\x00rr-actors demo: stderr closed\x00"
"""Written by `close` through the pipe: what came before it is shown, what comes after is
passed on to the terminal (a line of its own, no process writes it)."""


class StderrLines:
    """Standard error (fd 2) through a pipe into `show`, one line at a time, until `close`.

    Args:
        show: called with each line (without its line break), on the reader thread.
    """

    def __init__(self, show: Callable[[str], None]) -> None:
        self._show = show
        self._pending = b""  # the start of a line whose break has not come yet
        self._passing = False  # the mark came: bytes go to the terminal as they come
        self._shown = threading.Event()  # the mark came
        self._terminal = os.dup(STDERR)  # (the reader's to close, at the end)
        self._read_end, write_end = os.pipe()
        with contextlib.suppress(ValueError, OSError):  # (a closed sys.stderr)
            sys.stderr.flush()
        os.dup2(write_end, STDERR)
        os.close(write_end)  # fd 2 is this process's only write end now
        threading.Thread(target=self._read, name="rr-actors-demo-stderr", daemon=True).start()

    @classmethod
    def open(cls, terminal: IO[str], show: Callable[[str], None]) -> StderrLines | None:
        """Take fd 2 over if it is the terminal `terminal` writes to, else `None`."""
        try:
            drawn_on = os.fstat(terminal.fileno())
            stderr = os.fstat(STDERR)
        except (AttributeError, ValueError, OSError):  # no file under it (a test's stream)
            return None
        if not (os.isatty(STDERR) and os.path.samestat(drawn_on, stderr)):
            return None
        return cls(show)

    def close(self) -> None:
        """Show what was written so far (`CLOSE_WAIT` s at most); fd 2 is the terminal again."""
        with contextlib.suppress(ValueError, OSError):
            sys.stderr.flush()
        try:
            os.write(STDERR, _MARK + b"\n")
            self._shown.wait(CLOSE_WAIT)
        finally:  # (a Ctrl-C meanwhile: the terminal is fd 2 again all the same)
            os.dup2(self._terminal, STDERR)

    def _read(self) -> None:
        """The reader thread: lines to `show` until the mark, then bytes to the terminal;
        ends when every process holding the pipe has closed it."""
        try:
            while chunk := os.read(self._read_end, 65536):
                if self._passing:
                    self._pass(chunk)
                    continue
                *lines, self._pending = _BREAK.split(self._pending + chunk)
                for i, line in enumerate(lines):
                    if line.endswith(_MARK):
                        if line != _MARK:  # (another writer's line without its break)
                            self._line(line.removesuffix(_MARK))
                        self._passing = True
                        self._pass(b"".join(rest + b"\n" for rest in lines[i + 1 :]))
                        self._pass(self._pending)
                        self._shown.set()
                        break
                    self._line(line)
        finally:
            os.close(self._read_end)
            os.close(self._terminal)

    def _line(self, line: bytes) -> None:
        try:
            self._show(line.decode(errors="replace"))
        except Exception:  # noqa: BLE001 - the line reaches the terminal all the same
            self._pass(line + b"\n")

    def _pass(self, data: bytes) -> None:
        if data:
            with contextlib.suppress(OSError):  # (the terminal is gone: nobody to tell)
                os.write(self._terminal, data)
