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

`rich` redraws its live line in place and leaves the cursor at the line's end. A line
that another writer puts on the same terminal meanwhile (a manager process's WARNING
before its `setup` sent its log to the run's file, Python's own warnings, a thread's
traceback) runs on from there: on an 80-column terminal, one line of 80 columns plus its
own (a loaded CI run of `rr-actors demo --step` showed one of 121). `rich` takes care of
this for its own process's `sys.stderr` only (`redirect_stderr`); the other processes of
the demo write to the file descriptor. So while the demo's output is open, fd 2 is a
pipe, and every line written to it is shown by the output, which knows where the live
line is.

Only when fd 2 is the very terminal the output draws on (`open` returns `None`
otherwise: a redirected stderr stays where the user sent it). After `close`, fd 2 is the
terminal again; the processes started meanwhile still hold the pipe, so the reader goes
on passing what they write to the terminal until the last of them has closed it.
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
