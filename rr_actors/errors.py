"""Errors raised by rr_actors.

Every error derives from [`RrError`][rr_actors.errors.RrError]. "You stopped it"
([`RegistrarStoppedError`][rr_actors.errors.RegistrarStoppedError]) is kept apart from "it
died" ([`RegistrarUnavailableError`][rr_actors.errors.RegistrarUnavailableError]); a timeout
is also a built-in `TimeoutError`. All errors pickle with their attributes. Beside
`CatalogCorruptError` is its recovery, `quarantine_backup`: the store's, which imports this
module, so this module's `__getattr__` imports it at its first use (PEP 562).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Callable
    from os import PathLike
    from pathlib import Path

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
    "quarantine_backup",  # (the store's, imported at its first use: `__getattr__`)
]


quarantine_backup: Callable[[str | PathLike[str]], Path]  # (`__getattr__`, below)


def __getattr__(name: str) -> object:
    """`rr_actors.errors.quarantine_backup`, beside the error it recovers from, imported at
    its first use: the store imports this module, so this one imports the store's function
    only when asked (PEP 562).

    Raises:
        AttributeError: `name` is not one of this module's.
    """
    if name != "quarantine_backup":
        raise AttributeError(f"module 'rr_actors.errors' has no attribute {name!r}")
    import importlib  # noqa: PLC0415 - (by name: the store is above this module)

    return importlib.import_module("rr_actors._store.files").quarantine_backup


class RrError(Exception):
    """Base class of every error rr_actors raises."""


def _known_names(name: object, known: Iterable[str], *, shown: int = 12) -> str:
    """`"; did you mean 'camera'? (known: 'camera', 'filter')"` or `" (none known)"` for `name`."""
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
    """A call reused a query id that names another call (another request or server) at its provider.

    A retry must repeat the same request to the same server; the provider changed nothing.
    """


class MessageTooLargeError(ConfigError):
    """A message is larger than the receiving registrar's `max_message_bytes`.

    Raised at the sender before anything is sent, or instead of an answer too large (the call's
    consumer id released). Sending it again fails the same way: send less, or raise
    `RegistrarConfig.max_message_bytes`.

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

    One short line with the command that installs it (`rr.ZenohNetwork needs an extra: pip
    install -e ".[zenoh]"`); the failed import is its `__cause__`. Also an `ImportError`.

    Attributes:
        what: what needs the extra (`""`: the whole command).
        extra: the extra's name in `pyproject.toml`.
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

    An `UnknownServerError`: a server is unreachable when its registrar is.
    """


class UnknownQueryError(RrError, LookupError):
    """The query id is unknown here, or was already released. Nothing was changed."""


class DependencyCycleError(RrError):
    """A load would wait for a resource being loaded further up the same chain.

    Raised instead of deadlocking, or of recursing deeper than
    `rr_actors.config.MAX_DEPENDENCY_DEPTH`.
    """


class CallTimeoutError(RrError, TimeoutError):
    """A blocking call did not finish within its `timeout` (seconds).

    It leaves nothing behind: if its load completes later, the provider releases the query id.
    """


class DeadlineExceededError(CallTimeoutError):
    """A load was shed before it started: its caller's `timeout` left (or, as it arrived, would
    leave once the server's loads queued ahead of it had started) less than 1.5 times what the
    server's loads take lately. Nothing was loaded; retry later or with a longer timeout."""


class OverloadedError(RrError):
    """A server had its `max_pending` loads under way (or the caller its share) for as long as
    the call could wait (or at once, with `if_overloaded="raise"`). The provider holds nothing.

    Attributes:
        registrar: the provider registrar's name.
        server: the server's name there.
        bound: its registrar's `max_pending` (per server).
        retry_after: seconds after which the provider expects a slot for this caller (as
            HTTP's `Retry-After`); `None` without an estimate.
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

    A call in flight may or may not have executed at the provider; retrying with the same
    query id is safe (loads are idempotent per id).
    """


class RegistrarStoppedError(RrError):
    """The registrar was stopped by its owner (`stop()`), so it takes no more work.

    Attributes:
        registrar: the registrar its owner stopped, where that one's end says so; `None`:
            this side's (its process left the system, or the network closed).
    """

    def __init__(self, message: str = "", registrar: str | None = None) -> None:
        super().__init__(message)
        self.registrar = registrar


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

    The registrar keeps the change and writes it with the next write that succeeds; the file
    stays as it was (every write is one transaction).

    Attributes:
        path: the backup file.
        cause: what went wrong.
        errno: the OS error number, if known.
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
    """A message, its answer, or an error did not pickle in the sender or unpickle in the
    receiver (the message says which and why)."""


class InternalError(RrError):
    """What should not happen did: a bug in rr_actors (the message says what was seen; please
    report it)."""


@dataclasses.dataclass(frozen=True)
class ErrorFrame:
    """One failed load's part of a [`ResourceLoadError`][rr_actors.errors.ResourceLoadError] stack:
    the `registrar` and `server` that failed, the exception's qualified name (`exc_type`), its
    `str()` (`message`) and its formatted `traceback`."""

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
    [`ErrorFrame`][rr_actors.errors.ErrorFrame] per load it failed through, the origin first,
    whose traceback is its `__cause__` (as `concurrent.futures` does). Sub-resources loaded
    inside the failed load were unloaded first.
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
