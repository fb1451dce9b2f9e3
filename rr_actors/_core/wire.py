"""What a message must offer to cross between processes: the contract carriers rely on.

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
"""

from __future__ import annotations

from typing import Any

from rr_actors._types import Query, Status, StatusUpdate
from rr_actors.errors import RrError, TransferError

__all__ = ["WIRE_TYPES", "WIRE_VERSION", "WireMessage", "plain"]

WIRE_VERSION = 6
"""The version of what crosses between processes (these messages, pickled): a carrier
that can meet a process of another version (the Zenoh one, across hosts) refuses its
messages unread. Raise it when a `WireMessage` changes incompatibly. (2: the Zenoh
carrier's messages carry a clock stamp after the frame's token. 3: a status reaches
the registrars of a process as one `StatusBatch`. 4: a Zenoh registrar's liveliness
token carries the clock stamp of when it began to serve, which decides which of two
servers of one name is kept: rule 22. 5: an `Unload`'s answer carries the statuses
still on their way to its id, `StatusOnItsWay`s: rule 9. 6: code pickled by value
crosses with its file's name, put back by `_transport.codec._named`, which a process of
version 5 lacks.)"""

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
