"""What crosses between processes: the contract a message offers carriers, and how a value
is pickled to leave this process.

A carrier moves messages without knowing what they mean, and asks a `WireMessage` where it
must act for it: `detached()`, `compensation()` (a `Load`'s `Abandon`),
`unreadable_answer()`, `unsendable_answer()`. `plain` data is pickled by the C pickler
alone (as cloudpickle would), the rest by cloudpickle (`Pickler`), the wire's own types by
reference, and code keeping its file's name:

```
 dumps: code object ──► (_named, (code as cloudpickle pickles it, code.co_filename))
 loads: _named(code named "<dynamic-code>", filename) ──► code.replace(co_filename=...)
```

Why: docs/explanation/inside.md, "Code that keeps its file's name".
"""

from __future__ import annotations

import io
import pickle
import types
from collections.abc import Callable
from typing import Any

import cloudpickle

from rr_actors._types import Query, Status, StatusUpdate
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    DeadlineExceededError,
    DependencyCycleError,
    ErrorFrame,
    MessageTooLargeError,
    OverloadedError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    ResourceLoadError,
    RrError,
    TransferError,
    UnknownQueryError,
    UnknownServerError,
)

WIRE_VERSION = 13
"""The version of what crosses between processes: a carrier that can meet another version
(the Zenoh one) refuses its messages unread. Raise it when a `WireMessage` changes
incompatibly (10: an `OverloadedError` carries `retry_after`; 11: a `Reconcile` echoes the
`ReconcileAsk.round` it answers, which a consumer of version 10 does not; 12: and that
ask's `life`, without which a round of an earlier run of the provider passes for its own;
13: its answer names the provider's run, `Reconciled`).
"""

WIRE_TYPES: set[type] = set()
"""Every `WireMessage` subclass (filled in as they are defined)."""


class WireMessage:
    """Base of the frozen dataclasses that cross between processes.
    A message that wants an answer has a `reply` field (a `Reply`); the others do not."""

    __slots__ = ()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        WIRE_TYPES.add(cls)

    def detached(self) -> Any:
        """This message as it crosses to another process: without its `reply`.
        A copy of its fields, not a second construction (a `Load` is detached on every call)."""
        if not hasattr(self, "reply"):
            return self
        copy = object.__new__(type(self))
        copy.__dict__.update(self.__dict__, reply=None)
        return copy

    def compensation(self) -> WireMessage | None:
        """What undoes handling this when its answer is lost, if any (to the registrar that did)."""
        return None

    def unreadable_answer(self, target: str, exc: BaseException) -> RrError:
        """The error for an answer from `target` that cannot be unpickled in this process."""
        return TransferError(
            f"the answer of registrar {target!r} to a {type(self).__name__} message "
            f"cannot be unpickled here: {exc}"
        )

    def unsendable_answer(self, target: str, value: Any, exc: BaseException) -> RrError:
        """The error sent back instead of an answer of `target` that cannot be pickled."""
        return TransferError(
            f"the answer of registrar {target!r} to a {type(self).__name__} message "
            f"is not picklable: {exc}"
        )


# Exact types only; `plain` walks at most `_PLAIN_BUDGET` containers of `_PLAIN_WIDTH` items.
_PLAIN_ATOMS: frozenset[type] = frozenset({str, int, float, bool, type(None), bytes, Status})
_PLAIN_SEQUENCES: frozenset[type] = frozenset({tuple, list, set, frozenset})
_PLAIN_VALUE_RECORDS: frozenset[type] = frozenset({Query, StatusUpdate})  # (+ WIRE_TYPES)
_PLAIN_BUDGET = 64
_PLAIN_WIDTH = 256


def plain(obj: Any) -> bool:
    """Whether `obj` is small builtin data that plain `pickle` encodes as cloudpickle would."""
    return type(obj) in _PLAIN_ATOMS or _plain_walk(obj, _PLAIN_BUDGET) >= 0


def _plain_walk(item: Any, budget: int) -> int:
    """The budget left after walking the container `item`, or -1 if it is not plain."""
    kind = type(item)
    budget -= 1
    if budget < 0:
        return -1
    items: Any
    if kind in _PLAIN_SEQUENCES or kind is dict:
        if len(item) > _PLAIN_WIDTH:
            return -1
        items = item if kind is not dict else (*item.keys(), *item.values())
    elif kind in WIRE_TYPES or kind in _PLAIN_VALUE_RECORDS:  # a few fields each
        items = item.__dict__.values()
    else:
        return -1
    for value in items:
        if type(value) not in _PLAIN_ATOMS:
            budget = _plain_walk(value, budget)
            if budget < 0:
                return -1
    return budget


# Pickled by reference by the C pickler (as `WIRE_TYPES`): no `reducer_override` call each.
_VALUES_BY_REFERENCE: frozenset[type] = frozenset(
    {
        Query,
        Status,
        StatusUpdate,
        ErrorFrame,
        MessageTooLargeError,
        OverloadedError,
        ResourceLoadError,
        DependencyCycleError,
        UnknownServerError,
        UnknownQueryError,
        RegistrarUnavailableError,
        RegistrarStoppedError,
        CallTimeoutError,
        DeadlineExceededError,
        ConfigError,
        RrError,
    }
)


def _by_reference(kind: type) -> bool:
    return kind in _VALUES_BY_REFERENCE or kind in WIRE_TYPES


# cloudpickle's own reducer of code objects (tests/core/test_wire.py checks it is there).
_CLOUDPICKLE_CODE: Callable[[types.CodeType], Any] | None = cloudpickle.Pickler.dispatch_table.get(
    types.CodeType
)


class _AsCloudpickleDoes:
    """A code object to pickle as cloudpickle does (the first half of `_reduce_code`)."""

    __slots__ = ("code",)

    def __init__(self, code: types.CodeType) -> None:
        self.code = code

    def __reduce__(self) -> Any:
        assert _CLOUDPICKLE_CODE is not None  # (only made when it is there)
        return _CLOUDPICKLE_CODE(self.code)


def _reduce_code(code: types.CodeType) -> tuple[Any, ...]:
    return _named, (_AsCloudpickleDoes(code), code.co_filename)


def _named(code: types.CodeType, filename: str) -> types.CodeType:
    return code if code.co_filename == filename else code.replace(co_filename=filename)


class Pickler(cloudpickle.Pickler):  # type: ignore[misc]
    """cloudpickle: the wire's own types by reference, code keeping its file's name."""

    def reducer_override(self, obj: Any) -> Any:
        kind = type(obj)
        if _by_reference(kind) or (kind is type and _by_reference(obj)):
            return NotImplemented
        if kind is types.CodeType and _CLOUDPICKLE_CODE is not None:  # (before its table)
            return _reduce_code(obj)
        return super().reducer_override(obj)


def dumps(value: Any) -> bytes:
    """`value` pickled as it leaves this process: `plain` data by the C pickler, the rest by
    `Pickler`. Pickling errors propagate."""
    if plain(value):
        return pickle.dumps(value, pickle.HIGHEST_PROTOCOL)
    buffer = io.BytesIO()
    Pickler(buffer, protocol=pickle.HIGHEST_PROTOCOL).dump(value)
    return buffer.getvalue()
