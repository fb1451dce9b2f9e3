"""rr_actors' WARNING and ERROR lines on standard error when nobody configured logging.

    record on "rr_actors" (or "rr_actors.*") ──► any other handler on its way up?
                                                   yes: they get it; this one stays quiet
                                                   no:  "WARNING rr_actors: <message>"
                                                        (traceback under it) on stderr,
                                                        on a terminal wrapped at words
                                                        to its width

Python's last-resort handler prints a record's bare message, so a user cannot tell a
WARNING from an ERROR, nor either from the program's own output. This handler stands in
for it on the `rr_actors` logger (installed once, at `import rr_actors`) and says the
level and the logger: `WARNING rr_actors: supervisor sup: child erm exited: killed by
SIGKILL`. It gets out of the way as soon as the application configures logging, at any
time, before or after the import: a handler on the root logger (`logging.basicConfig`),
on `rr_actors` or on one of its children takes the records where the application says,
and this one then writes nothing. As asyncio does, a library's warnings reach a
terminal by default; unlike a `NullHandler`, they are never silently lost.

On a terminal a line is as wide as the terminal at most (the terminal's `COLUMNS`, else
its window size): the message wraps at words, each further line indented four columns
(`manager erm has not answered its heartbeat for 0.812 s, but it could run for only ...`
is 250 columns on one line). A word longer than a line (a path) stays whole, and so does
a traceback, as Python prints it. In a pipe or a file a record stays one line, for grep.
"""

from __future__ import annotations

import logging
import os
import sys
import textwrap
from typing import TextIO

__all__ = ["FORMAT", "INDENT", "DefaultHandler", "configured", "install", "terminal_width", "wrap"]

FORMAT = "%(levelname)s %(name)s: %(message)s"
"""How a line reads: `WARNING rr_actors: ...`, `ERROR rr_actors: ...`."""

LOGGER = "rr_actors"

INDENT = "    "
"""How the further lines of a record's message wrapped on a terminal start."""


class DefaultHandler(logging.Handler):
    """WARNING and above to the current `sys.stderr`, unless logging was configured.

    "Configured" is decided per record (`configured`), so an application that calls
    `logging.basicConfig` after `import rr_actors` still gets every record where it said,
    and none twice on stderr.
    """

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.setFormatter(logging.Formatter(FORMAT))

    def handle(self, record: logging.LogRecord) -> bool:
        """Emit `record` only when no other handler is on its way up."""
        if configured(record.name):
            return False
        return bool(super().handle(record))

    def emit(self, record: logging.LogRecord) -> None:
        """Write the formatted record and a line break to `sys.stderr` (looked up now:
        a test or a program may have replaced it)."""
        try:
            stream = sys.stderr
            text = self.format(record)
            width = terminal_width(stream)
            if width is not None:
                text = _wrapped(text, record.getMessage().count("\n") + 1, width)
            stream.write(text + "\n")
            stream.flush()
        except Exception:  # noqa: BLE001 - as logging.StreamHandler: never raise from a log call
            self.handleError(record)


def terminal_width(stream: TextIO) -> int | None:
    """The columns of the terminal `stream` writes to, or `None` if it is no terminal.

    `COLUMNS` first, as `shutil.get_terminal_size` reads it (a user's `COLUMNS=80`, a
    test's pseudo-terminal), then the terminal's window size.
    """
    try:
        if not stream.isatty():
            return None
        fd = stream.fileno()
    except (AttributeError, ValueError, OSError):  # closed, or a stand-in without a file
        return None
    columns = os.environ.get("COLUMNS", "")
    if columns.isdigit() and int(columns) > 0:
        return int(columns)
    try:
        return os.get_terminal_size(fd).columns or None
    except OSError:
        return None


def _wrapped(text: str, message_lines: int, width: int) -> str:
    """`text` (a formatted record) with its first `message_lines` lines wrapped at words to
    `width` columns; what follows (a traceback) as it is."""
    lines = text.split("\n")
    head = [wrap(line, width) for line in lines[:message_lines]]
    return "\n".join([*head, *lines[message_lines:]])


def wrap(line: str, width: int) -> str:
    """`line` as it is if it fits `width` columns, else wrapped at words, each further
    line indented by `INDENT` (a word longer than a line stays whole)."""
    if len(line) <= width:
        return line
    wrapped = textwrap.wrap(
        line, width, subsequent_indent=INDENT, break_long_words=False, break_on_hyphens=False
    )
    return "\n".join(wrapped) if wrapped else line


def configured(name: str = LOGGER) -> bool:
    """Whether a handler other than `DefaultHandler` would get a record of logger `name`.

    Walks from `name` up the logger tree as propagation does (stopping at a logger with
    `propagate = False`), as `logging.Logger.callHandlers` finds handlers.
    """
    logger: logging.Logger | None = logging.getLogger(name)
    while logger is not None:
        if any(not isinstance(h, DefaultHandler) for h in logger.handlers):
            return True
        if not logger.propagate:
            return False
        logger = logger.parent
    return False


def install() -> None:
    """Put one `DefaultHandler` on the `rr_actors` logger (again: nothing more)."""
    logger = logging.getLogger(LOGGER)
    if not any(isinstance(h, DefaultHandler) for h in logger.handlers):
        logger.addHandler(DefaultHandler())
