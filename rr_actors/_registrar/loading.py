"""What a `load` callback runs inside: its context, its errors, what must pickle.

A call made while a `load` callback runs records a dependency of the resource being
loaded (rule 5): the callback's thread carries a `LoadContext` in a context variable,
which `call` reads. The context also carries the chain of resources being loaded further
up, for cycle detection (rule 6).
"""

from __future__ import annotations

import contextvars
import dataclasses
import traceback
from typing import Any

import cloudpickle

from rr_actors.errors import (
    ConfigError,
    DependencyCycleError,
    ErrorFrame,
    ResourceLoadError,
    RrError,
)

__all__ = [
    "LOADING",
    "MAX_DEPENDENCY_DEPTH",
    "LoadContext",
    "check_picklable",
    "error_frame",
    "load_error",
]

MAX_DEPENDENCY_DEPTH = 64
"""A load chain deeper than this is reported as a `DependencyCycleError` (runaway recursion)."""


@dataclasses.dataclass(frozen=True)
class LoadContext:
    """What is being loaded on the current thread (read by `call` to record dependencies).

    Attributes:
        registrar: name of the registrar whose server runs the load.
        resource_id: id of the resource being loaded.
        chain: ids of the resources being loaded on the way here, this one last.
    """

    registrar: str
    resource_id: str
    chain: tuple[str, ...]


LOADING: contextvars.ContextVar[LoadContext | None] = contextvars.ContextVar(
    "rr_actors_loading", default=None
)
"""The `LoadContext` of the load callback running on this thread, if any."""


def check_picklable(value: Any, what: str) -> None:
    """Raise `ConfigError` if `value` cannot be stored in a catalog backup.

    Whatever pickling it raises (a user `__reduce__` raising `SystemExit` too) is that.
    """
    try:
        cloudpickle.dumps(value)
    except BaseException as exc:  # (user code: a SystemExit from __reduce__ is contained too)
        raise ConfigError(
            f"{what} cannot be pickled, so the catalog cannot store it: {exc}"
        ) from exc


def error_frame(
    registrar: str,
    server: str,
    exc: BaseException,
    message: str | None = None,
    *,
    with_traceback: bool = True,
) -> ErrorFrame:
    """The frame a failed load adds to a `ResourceLoadError`'s stack (the one builder).

    Args:
        registrar: the registrar whose server failed.
        server: that server's name.
        exc: what failed it.
        message: what to say (default: `str(exc)`).
        with_traceback: whether the frame carries `exc`'s formatted traceback.
    """
    return ErrorFrame(
        registrar=registrar,
        server=server,
        exc_type=type(exc).__qualname__,
        message=str(exc) if message is None else message,
        traceback="".join(traceback.format_exception(exc)) if with_traceback else "",
    )


def load_error(registrar: str, server: str, exc: BaseException) -> RrError:
    """Turn what a `load` callback raised into the error its callers get (rule 4).

    A `DependencyCycleError` raised further down passes through unchanged; anything else
    becomes a `ResourceLoadError` whose stack gains this registrar's frame.
    """
    inner: BaseException | None = exc
    while inner is not None and not isinstance(inner, ResourceLoadError | DependencyCycleError):
        inner = inner.__cause__
    if isinstance(inner, DependencyCycleError):
        return inner
    frame = error_frame(registrar, server, exc)
    stack = inner.stack if isinstance(inner, ResourceLoadError) else ()
    return ResourceLoadError((*stack, frame))
