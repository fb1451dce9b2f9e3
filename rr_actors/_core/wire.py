"""What crosses between processes: the contract a message offers carriers, and how a value
is pickled to leave this process.

A carrier (`rr_actors._transport`) moves messages between the processes of a system
without knowing what they mean. Where it must act on a message's behalf, it asks the
message:

- `detached()`: the message as it crosses, without its `reply` (the sender keeps that);
- `compensation()`: what undoes the effect of handling it, when its answer is lost on the
  way back (the registrar's `Load` is undone by an `Abandon` of its consumer id);
- `unreadable_answer()` / `unsendable_answer()`: the error its sender gets when the
  answer cannot be unpickled there, or pickled here.

Every subclass is listed in `WIRE_TYPES`, which the codec pickles by reference on its
fast path.

`plain(value)`: small builtin data and such records, which the C pickler alone encodes
byte for byte as cloudpickle would, without building a cloudpickle `Pickler` (a Python
object, and a Python call per object pickled). The codec frames such a message with it,
and the catalog's backup stores such a request or response with it (nor is one checked
for being picklable: it is).

`dumps(value)` / `Pickler`: everything else, the user's requests and responses included,
is pickled by cloudpickle (so it may hold closures), with the wire's own types by
reference, and code that keeps the file it was written in:

```
 dumps: code object ──► (_named, (code as cloudpickle pickles it, code.co_filename))
 loads: _named(code named "<dynamic-code>", filename) ──► code.replace(co_filename=...)
```

cloudpickle 3.1.3 names every code object it pickles by value `"<dynamic-code>"` (so a
payload does not depend on where its function was defined: cloudpipe/cloudpickle#560,
for notebooks) and has no option to keep the name. A callback run in another process
(a `load`, a manager's `setup`: both are pickled by value when their module cannot be
imported there), or a function inside a request restored from a backup, would then show
no file in a traceback, and no source line: a failed load's cause (rule 4) or a
manager's start error would not say where it failed. The pickling side still knows the
name, so it is pickled beside the code and unpickling puts it back. Nested code (a
closure's, a lambda's) is a code object of its own and is pickled the same way. With
cloudpickle before 3.1.3 the name was already there; nothing else about the code
changes. The frames of `rr_actors._transport.codec`, a manager's `setup` and the
catalog's stored values (`rr_actors._store.codec`) are all pickled here.
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

__all__ = ["WIRE_TYPES", "WIRE_VERSION", "Pickler", "WireMessage", "dumps", "plain"]

WIRE_VERSION = 11
"""The version of what crosses between processes (these messages, pickled): a carrier
that can meet a process of another version (the Zenoh one, across hosts) refuses its
messages unread. Raise it when a `WireMessage` changes incompatibly. (2: the Zenoh
carrier's messages carry a clock stamp after the frame's token. 3: a status reaches
the registrars of a process as one `StatusBatch`. 4: a Zenoh registrar's liveliness
token carries the clock stamp of when it began to serve, which decides which of two
servers of one name is kept: rule 22. 5: an `Unload`'s answer carries the statuses
still on their way to its id, `StatusOnItsWay`s: rule 9. 6: code pickled by value
crosses with its file's name, put back by `_transport.codec._named`, which a process of
version 5 lacks. 7: that function is `_core.wire._named`, which a process of version 6
lacks. 8: a `Load` and a `Reconcile` carry their consumer's run, `life`: a provider of
version 7 would not fence a restarted consumer's earlier loads, and a consumer of version
7 commits a record before its `Load` leaves, which one of 8 no longer does. 9: a `Load`
and an `Unload` carry their caller's W3C trace context, `trace`, and a `Load` its caller's
deadline, `deadline` (a monotonic time of each process, the seconds left on the wire): a
process of version 8 would neither continue the trace nor shed a load too late. 10: an
`OverloadedError` carries when to ask again, `retry_after`, which one of version 9 cannot
unpickle. 11: a `Reconcile` echoes the provider's `ReconcileAsk.round`: a provider of
version 11 would not count the answer of a consumer of version 10 as its ask's.)"""

WIRE_TYPES: set[type] = set()
"""Every `WireMessage` subclass (filled in as they are defined)."""


class WireMessage:
    """Base of the frozen dataclasses that cross between processes.

    A message that wants an answer has a `reply` field (a `Reply`); the others do not.
    """

    __slots__ = ()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        WIRE_TYPES.add(cls)

    def detached(self) -> Any:
        """This message as it crosses to another process: without its `reply`.

        A copy of its fields, not a second construction: the fields were checked when the
        message was built, and a frozen dataclass's `__init__` sets each one through
        `object.__setattr__` (a `Load` is detached on every call across processes).
        """
        if not hasattr(self, "reply"):
            return self
        copy = object.__new__(type(self))
        copy.__dict__.update(self.__dict__, reply=None)
        return copy

    def compensation(self) -> WireMessage | None:
        """A message that undoes handling this one when its answer is lost, if any.

        The carrier delivers it to the registrar that handled this message (the message's
        target), as the one step that keeps a lost answer from leaking what it created.
        """
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


# Small builtin data (exact types: no subclass, nothing defined in `__main__`), the wire
# protocol's records holding only such data, and status codes. `plain` looks at no more
# than `_PLAIN_BUDGET` containers of at most `_PLAIN_WIDTH` items each; anything larger
# or else is not plain (cloudpickle's).
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


# Types pickled by reference with the C pickler's own machinery: cloudpickle's
# `reducer_override` (a Python call per object) is skipped for them, as for every wire
# message (`WIRE_TYPES`). Everything else goes through cloudpickle.
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


# cloudpickle's own reducer of code objects, read once from its `Pickler.dispatch_table`
# (pickle's documented hook; which types cloudpickle puts there is its own business, so
# this is the one place rr_actors relies on it: tests/core/test_wire.py checks it).
# A cloudpickle without it pickles code its own way, as it did before 3.1.3: file names
# may then be lost again, nothing else.
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
    """A code object crosses with the name of its file (see the module docstring)."""
    return _named, (_AsCloudpickleDoes(code), code.co_filename)


def _named(code: types.CodeType, filename: str) -> types.CodeType:
    """`code` with its file's name put back, where cloudpickle changed it."""
    return code if code.co_filename == filename else code.replace(co_filename=filename)


class Pickler(cloudpickle.Pickler):  # type: ignore[misc]
    """cloudpickle, with a fast path for the wire protocol's own types, and code that
    keeps its file's name."""

    def reducer_override(self, obj: Any) -> Any:
        kind = type(obj)
        if _by_reference(kind) or (kind is type and _by_reference(obj)):
            return NotImplemented
        if kind is types.CodeType and _CLOUDPICKLE_CODE is not None:  # (before its table)
            return _reduce_code(obj)
        return super().reducer_override(obj)


def dumps(value: Any) -> bytes:
    """`value` pickled as it leaves this process: `plain` data by the C pickler, the rest
    by cloudpickle, code keeping its file's name (a frame's payload, a manager's `setup`,
    a stored request or response). Pickling errors propagate."""
    if plain(value):
        return pickle.dumps(value, pickle.HIGHEST_PROTOCOL)
    buffer = io.BytesIO()
    Pickler(buffer, protocol=pickle.HIGHEST_PROTOCOL).dump(value)
    return buffer.getvalue()
