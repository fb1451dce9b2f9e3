"""rr_actors' WARNING and ERROR lines on standard error when nobody configured logging.

    record on "rr_actors" (or "rr_actors.*") ──► any other handler on its way up?
                                                   yes: they get it; this one stays quiet
                                                   no:  "WARNING rr_actors: <message>"
                                                        (traceback under it) on stderr

Python's last-resort handler prints a record's bare message, so a user cannot tell a
WARNING from an ERROR, nor either from the program's own output. This handler stands in
for it on the `rr_actors` logger (installed once, at `import rr_actors`) and says the
level and the logger: `WARNING rr_actors: supervisor sup: child erm exited: killed by
SIGKILL`. It gets out of the way as soon as the application configures logging, at any
time, before or after the import: a handler on the root logger (`logging.basicConfig`),
on `rr_actors` or on one of its children takes the records where the application says,
and this one then writes nothing. As asyncio does, a library's warnings reach a
terminal by default; unlike a `NullHandler`, they are never silently lost.
"""

from __future__ import annotations

import logging
import sys

__all__ = ["FORMAT", "DefaultHandler", "configured", "install"]

FORMAT = "%(levelname)s %(name)s: %(message)s"
"""How a line reads: `WARNING rr_actors: ...`, `ERROR rr_actors: ...`."""

LOGGER = "rr_actors"


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
            sys.stderr.write(self.format(record) + "\n")
            sys.stderr.flush()
        except Exception:  # noqa: BLE001 - as logging.StreamHandler: never raise from a log call
            self.handleError(record)


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
