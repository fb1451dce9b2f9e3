"""Errors raised by rr_actors.

Every error derives from [`RrError`][rr_actors.errors.RrError]. "You stopped it"
([`RegistrarStoppedError`][rr_actors.errors.RegistrarStoppedError]) is kept apart from
"it died" ([`RegistrarUnavailableError`][rr_actors.errors.RegistrarUnavailableError]), and
a timeout is also a built-in `TimeoutError`.

All errors pickle (they cross process boundaries) and keep their attributes when they do.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import Any

__all__ = [
    "CallTimeoutError",
    "CatalogCorruptError",
    "CatalogWriteError",
    "ConfigError",
    "DeadlineExceededError",
    "DependencyCycleError",
    "DuplicateNameError",
    "DuplicateQueryIdError",
    "ErrorFrame",
    "InternalError",
    "MessageTooLargeError",
    "MissingExtraError",
    "OverloadedError",
    "RegistrarStoppedError",
    "RegistrarUnavailableError",
    "ResourceLoadError",
    "RrError",
    "SupervisorGaveUpError",
    "TransferError",
    "UnknownQueryError",
    "UnknownRegistrarError",
    "UnknownServerError",
]


class RrError(Exception):
    """Base class of every error rr_actors raises."""


def _known_names(name: object, known: Iterable[str], *, shown: int = 12) -> str:
    """What to add to an error about an unknown `name`: the closest known name, the known.

    For example `"; did you mean 'camera'? (known: 'camera', 'filter')"`, or
    `" (none known)"`; at most `shown` names are listed.
    """
    import difflib  # noqa: PLC0415 - an error's path only: `import rr_actors` leaves it out

    names = sorted(set(known))
    if not names:
        return " (none known)"
    close = difflib.get_close_matches(name, names, n=1) if isinstance(name, str) else []
    hint = f"; did you mean {close[0]!r}?" if close else ""
    listed = ", ".join(repr(n) for n in names[:shown])
    more = f", ... ({len(names) - shown} more)" if len(names) > shown else ""
    return f"{hint} (known: {listed}{more})"


class ConfigError(RrError, ValueError):
    """A configuration value is invalid; the message names the field and the value."""


class DuplicateNameError(ConfigError):
    """A registrar or resource server name is already in use where names must be unique."""


class DuplicateQueryIdError(ConfigError):
    """A call reused a query id that already names another call (another request, or
    another server) at its provider.

    A query id is for one call and its retries: a retry must repeat the same request
    to the same server. The message names the id; the provider changed nothing.
    """


class MessageTooLargeError(ConfigError):
    """A message is larger than the receiving registrar's `max_message_bytes`.

    Raised at the sender before anything of the message is sent (a request, a status
    message, ...), or instead of an answer that is too large (the consumer id of the
    call is released again). A `ConfigError`, like a message that does not pickle: what
    was asked for cannot be sent as it is, and sending it again fails the same way;
    send less, or raise the receiver's `RegistrarConfig.max_message_bytes`.

    Attributes:
        size: the message's size in bytes, pickled.
        limit: the `max_message_bytes` it exceeds.
    """

    def __init__(self, message: str, size: int, limit: int) -> None:
        super().__init__(message)
        self.size = size
        self.limit = limit

    def __reduce__(self) -> tuple[Any, ...]:
        return (type(self), (str(self), self.size, self.limit))


class MissingExtraError(ConfigError, ImportError):
    """What was asked for needs an optional extra of rr-actors that is not installed.

    The message is one line that gives the command that installs the extra into this
    installation, naming it in pip's notation: `rr.ZenohNetwork needs an extra: pip
    install -e ".[zenoh]"` (`-e` and the checkout for an editable install, as the
    README's; `pip install "rr-actors[zenoh]"` for a wheel). Short, so that a command's
    line fits 80 columns (`rr-actors experiment needs an extra: pip install -e
    ".[experiments]"`: `what` is empty when a whole command needs it). The import that
    failed is its `__cause__`. A `ConfigError` (the installation lacks
    something, as a value can) and an `ImportError` (what code that tries an optional
    import catches). The command line prints the line and exits with 2.

    Attributes:
        what: what needs the extra (`"rr.ZenohNetwork"`, `"the observer"`, `"--hosts 2"`;
            `""`: the whole command that caught it).
        extra: the extra's name in `pyproject.toml` (`"zenoh"`, `"observe"`, ...).
        command: the command that installs it.
    """

    def __init__(self, what: str, extra: str, command: str) -> None:
        super().__init__(f"{what} needs an extra: {command}".lstrip())
        self.what = what
        self.extra = extra
        self.command = command

    def __reduce__(self) -> tuple[Any, ...]:
        return (type(self), (self.what, self.extra, self.command))


class UnknownServerError(RrError, LookupError):
    """No resource server (or no registrar at all) answers to the given name."""


class UnknownRegistrarError(UnknownServerError):
    """No registrar (or supervised manager) of that name was ever seen on this system.

    A subclass of `UnknownServerError`: a server is unreachable when its registrar is.
    """


class UnknownQueryError(RrError, LookupError):
    """The query id is unknown here, or was already released. Nothing was changed."""


class DependencyCycleError(RrError):
    """A load would wait for a resource that is being loaded further up the same chain.

    Raised instead of deadlocking (equal request further up) or recursing forever
    (the chain grew deeper than `rr_actors.config.MAX_DEPENDENCY_DEPTH`).
    """


class CallTimeoutError(RrError, TimeoutError):
    """A blocking call did not finish within its `timeout` (seconds).

    A call that timed out leaves nothing behind: if its load completes later, the
    provider releases that query id.
    """


class DeadlineExceededError(CallTimeoutError):
    """A load was shed before it started: what was left of its caller's `timeout` (carried
    with the call, seconds) was less than 1.5 times what the server's loads take lately.

    Raised instead of running the load at once, not after the timeout: nothing was loaded
    and the provider holds nothing for the call (its query id is given back). A subclass
    of `CallTimeoutError`, so code that catches a timeout catches it. *What to do:* retry
    later, or with a longer timeout; the server is overloaded or its loads slowed down.
    """


class OverloadedError(RrError):
    """A server had as much work under way as its registrar's `max_pending` allows (or
    the calling registrar its share of it, while other consumers want loads there), for
    as long as the call could wait.

    A call refused so waits and asks again (a blocking call on its thread, an awaited
    one with no thread held) while its `timeout` lasts; this is raised when the time
    left is too short for another try, or at once for a caller that cannot wait
    (`call(..., if_overloaded="raise")`). Nothing was loaded and the provider holds
    nothing of the call: it is never dropped silently.

    Attributes:
        registrar: the provider registrar's name.
        server: the server's name there.
        bound: its registrar's `max_pending` (loads queued or running, per server).
        retry_after: seconds after which the provider expects a slot for this caller
            (as HTTP's `Retry-After`): the pause a waiting call takes before it asks
            again; `None` when the provider has no estimate yet (no load has run).
    """

    def __init__(
        self,
        message: str,
        registrar: str,
        server: str,
        bound: int,
        retry_after: float | None = None,
    ) -> None:
        super().__init__(message)
        self.registrar = registrar
        self.server = server
        self.bound = bound
        self.retry_after = retry_after

    def __reduce__(self) -> tuple[Any, ...]:
        args = (str(self), self.registrar, self.server, self.bound, self.retry_after)
        return (type(self), args)


class RegistrarUnavailableError(RrError):
    """The registrar died (crashed, was killed, or its process exited).

    A call that was in flight when this is raised may or may not have executed at
    the provider; retrying with the same query id is safe (loads are idempotent per id).
    """


class RegistrarStoppedError(RrError):
    """The registrar was stopped by its owner (`stop()`), so it takes no more work."""


class CatalogCorruptError(RrError):
    """A catalog backup file cannot be read; it was left untouched.

    Attributes:
        path: the file that could not be read.
    """

    def __init__(self, path: str, cause: str) -> None:
        super().__init__(f"catalog backup {path!r} cannot be used: {cause}")
        self.path = path
        self.cause = cause

    def __reduce__(self) -> tuple[Any, ...]:
        return (type(self), (self.path, self.cause))


class CatalogWriteError(RrError):
    """A change could not be written to the catalog backup (a full disk, an I/O error).

    The change is not lost: the registrar still holds it and writes it with the next
    write that succeeds. What the file held before stays as it was (every write is one
    transaction).

    Attributes:
        path: the backup file.
        cause: what went wrong, e.g. `"ENOSPC (No space left on device): database or
            disk is full (SQLITE_FULL)"`.
        errno: the OS error number (`errno.ENOSPC`, ...) when it is known, else `None`.
    """

    def __init__(self, path: str, cause: str, errno: int | None = None) -> None:
        super().__init__(f"catalog backup {path!r} could not be written: {cause}")
        self.path = path
        self.cause = cause
        self.errno = errno

    def __reduce__(self) -> tuple[Any, ...]:
        return (type(self), (self.path, self.cause, self.errno))


class SupervisorGaveUpError(RrError):
    """A supervisor exceeded its restart intensity (`max_restarts` within `period` s)."""


class TransferError(RrError):
    """A message, its answer, or an error could not cross between processes.

    It does not pickle in the process that sends it, or does not unpickle in the one it
    reached (a class or module that process lacks, a `__reduce__` that raises); the
    message says which and why. Where rr_actors can tell before sending (a request, a
    stored response), it raises `ConfigError` instead; a lost `Load` answer is a
    `ResourceLoadError`, and its consumer id is released.
    """


class InternalError(RrError):
    """What should not happen did: a bug in rr_actors, not in the code that called it.

    For example an answer in no form a carrier sends, or an answer to a message that
    wants none. The message says what was seen; please report it.
    """


@dataclasses.dataclass(frozen=True)
class ErrorFrame:
    """One failed load's part of a [`ResourceLoadError`][rr_actors.errors.ResourceLoadError] stack.

    Attributes:
        registrar: name of the registrar whose server failed to load.
        server: name of that resource server.
        exc_type: qualified name of the exception raised there.
        message: `str()` of that exception.
        traceback: formatted traceback text, as produced where it was raised.
    """

    registrar: str
    server: str
    exc_type: str
    message: str
    traceback: str


class _RemoteTraceback(Exception):  # noqa: N818 - named as concurrent.futures names it
    """The traceback text of a load that failed elsewhere (a `ResourceLoadError`'s cause)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class ResourceLoadError(RrError):
    """A `load` callback raised, here or further down the dependency chain.

    Like TeMoto's `TemotoErrorStack` (thesis 4.3.4): `stack` holds one
    [`ErrorFrame`][rr_actors.errors.ErrorFrame] per load the error failed on its way up,
    the origin first: one per registrar it crossed, and one per server when a server's
    load calls another server of the same registrar. Sub-resources loaded inside the
    failed load were unloaded before this error was raised.

    The origin's traceback (the failing `load`'s file and line) is its `__cause__`, a
    `_RemoteTraceback` whose text it is, so an uncaught one prints it, as
    `concurrent.futures` does for an exception raised in a worker process. It is set
    again from `stack` when the error is unpickled in another process.
    """

    def __init__(self, stack: tuple[ErrorFrame, ...]) -> None:
        origin = stack[0]
        path = " <- ".join(f"{f.registrar}/{f.server}" for f in stack)
        super().__init__(f"{origin.exc_type}: {origin.message} (at {path})")
        self.stack = stack
        if origin.traceback:
            self.__cause__ = _RemoteTraceback(
                f"the load of '{origin.registrar}/{origin.server}' raised:\n"
                f'"""\n{origin.traceback.rstrip()}\n"""'
            )

    def __reduce__(self) -> tuple[Any, ...]:
        return (type(self), (self.stack,))
