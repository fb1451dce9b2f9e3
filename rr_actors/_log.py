"""rr_actors' WARNING and ERROR lines on standard error when nobody configured logging.

    record on "rr_actors" (or "rr_actors.*") ──► any other handler on its way up?
                                                   yes: they get it; this one stays quiet
                                                   no:  "WARNING rr_actors: <message>"
                                                        (traceback under it) on stderr,
                                                        on a terminal wrapped at words
                                                        to its width

Python's last-resort handler prints a bare message; this one (installed at `import rr_actors`) says
the level and the logger, and gets out of the way as soon as the application configures logging,
before or after the import. As asyncio's, a library's warnings reach a terminal by default and are
never silently lost. On a terminal a message wraps at words to its width (`COLUMNS`, else the
window's), further lines indented; a traceback, and any line in a pipe or a file, stay whole.
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


class DefaultHandler(logging.Handler):
    """WARNING and above to the current `sys.stderr`, unless logging was configured (decided per
    record, so a later `logging.basicConfig` takes over).
    """

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.setFormatter(logging.Formatter(FORMAT))

    def handle(self, record: logging.LogRecord) -> bool:
        if configured(record.name):
            return False
        return bool(super().handle(record))

    def emit(self, record: logging.LogRecord) -> None:
        """Write the record and a line break to `sys.stderr`, looked up now."""
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
    """The columns of the terminal `stream` writes to (`COLUMNS` first), or `None` if no
    terminal."""
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
    lines = text.split("\n")
    head = [wrap(line, width) for line in lines[:message_lines]]
    return "\n".join([*head, *lines[message_lines:]])


def wrap(line: str, width: int) -> str:
    """`line`, wrapped at words to `width` with further lines indented by `INDENT` if it does not
    fit."""
    if len(line) <= width:
        return line
    wrapped = textwrap.wrap(
        line, width, subsequent_indent=INDENT, break_long_words=False, break_on_hyphens=False
    )
    return "\n".join(wrapped) if wrapped else line


def configured(name: str = LOGGER) -> bool:
    """Whether a handler other than `DefaultHandler` would get a record of logger `name` (as
    propagation finds handlers).
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
