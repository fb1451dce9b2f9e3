"""Request digests: when two requests are `==`, without comparing every pair.

Dedup is by `==` on the request value, also for unhashable values: requests are bucketed
by `request_digest`, a deterministic (storable) digest of a canonical form that covers
only built-in values whose `==` it mirrors, and compared with `==` within a bucket. Any
other request has no digest: it is bucketed by its in-process `hash()` when its class
defines one with its `__eq__`, else with the unhashable ones. A comparison that raises
means "different".
"""

from __future__ import annotations

import decimal
import enum
import fractions
import hashlib
import reprlib
import sys
from collections import OrderedDict
from typing import Any

UNHASHABLE = ("<unhashable>",)

NO_DIGEST = -1
"""`Resource.digest` of a request that has no digest (`hash()` never returns -1 either)."""

_TAG_NONE, _TAG_SEQ, _TAG_MAP, _TAG_SET, _TAG_NAN, _TAG_ENUM = range(0x5F3A_0000, 0x5F3A_0006)
_NUMBERS = (int, float, complex, decimal.Decimal, fractions.Fraction)
_STRINGS: dict[str, int] = {}  # str -> digest; strings repeat (keys, command names)
_STRINGS_MAX = 4096

DIGEST_SCHEME = (
    f"rr4-py{sys.version_info[0]}.{sys.version_info[1]}-w{sys.hash_info.width}"
    f"-{sys.hash_info.modulus}"
)
"""Names the digest function (`hash()` of tuples of integers may change with Python's
version or word size: a backup of another scheme has its digests recomputed)."""


def _blake(data: bytes) -> int:
    digest = int.from_bytes(hashlib.blake2b(data, digest_size=8).digest(), "little", signed=True)
    return -2 if digest == NO_DIGEST else digest


def _number(value: Any) -> int:
    # NaN != NaN, and its hash() is its address: every NaN gets one constant instead.
    return _TAG_NAN if value != value else hash(value)  # noqa: PLR0124


class _Opaque(Exception):  # noqa: N818 - control flow inside _digest, never escapes
    pass


def _digest(value: Any) -> int:  # noqa: PLR0911 - one return per kind of value
    cls = type(value)
    if cls is str:
        digest = _STRINGS.get(value)
        if digest is None:
            if len(_STRINGS) >= _STRINGS_MAX:
                _STRINGS.clear()
            digest = _STRINGS[value] = _blake(value.encode("utf-8", "surrogatepass"))
        return digest
    if cls is int or cls is bool:
        return hash(value)
    if cls is float or cls is complex:
        return _number(value)
    if value is None:
        return _TAG_NONE
    # Containers are read through their base class's own methods (`dict.items`, ...), so
    # digesting one runs no code of a subclass: a value with a digest is a plain value,
    # which the registrar's actor compares with `==` itself (see `plain_value`).
    if cls is dict or (issubclass(cls, dict) and _keeps_eq(cls, _MAPPING_EQ)):
        items = dict.items(value)
        return hash((_TAG_MAP, frozenset([(_digest(k), _digest(v)) for k, v in items])))
    if cls is list or cls is tuple:
        return hash((_TAG_SEQ, *[_digest(item) for item in value]))
    if issubclass(cls, list | tuple) and _keeps_eq(cls, _SEQ_EQ):
        base: Any = list if issubclass(cls, list) else tuple
        return hash((_TAG_SEQ, *[_digest(item) for item in base.__iter__(value)]))
    if issubclass(cls, set | frozenset) and _keeps_eq(cls, _SET_EQ):
        base = set if issubclass(cls, set) else frozenset
        return hash((_TAG_SET, frozenset([_digest(item) for item in base.__iter__(value)])))
    if cls is bytes or cls is bytearray:  # bytearray(b"a") == b"a"
        return hash((_TAG_SEQ, _blake(value)))  # not the digest of the equal str
    if issubclass(cls, enum.Enum) and identity_equality(value):
        return _enum_member(value, cls)
    return _digest_subclass(value, cls)


def _enum_member(value: enum.Enum, cls: type) -> int:
    """A plain enum member equals only itself: its class's path and its name name it."""
    name = value._name_
    if type(name) is not str:  # a composite Flag without a name: leave it to `==`
        raise _Opaque
    where = _blake(f"{cls.__module__}:{cls.__qualname__}".encode("utf-8", "surrogatepass"))
    return hash((_TAG_ENUM, where, _blake(name.encode("utf-8", "surrogatepass"))))


# The `==` of containers the digest mirrors: a subclass that overrides `__eq__` (Counter,
# a case-insensitive dict, a tuple with a tolerance) may call values equal whose digests
# differ, so it has no digest. OrderedDict's `==` is dict's when either side is a plain
# dict and stricter (order too) between two OrderedDicts, so equal ones have equal items.
# Other mappings and sets (the `Mapping` and `Set` ABCs) compare through their own
# methods, which may hang: they have no digest.
_MAPPING_EQ: tuple[object, ...] = (dict.__eq__, OrderedDict.__eq__)
_SEQ_EQ: tuple[object, ...] = (list.__eq__, tuple.__eq__)
_SET_EQ: tuple[object, ...] = (set.__eq__, frozenset.__eq__)


def _keeps_eq(cls: type, eqs: tuple[object, ...]) -> bool:
    eq: object = cls.__eq__
    return eq in eqs


def _digest_subclass(value: Any, cls: type) -> int:
    """Subclasses that keep their base's `==` and `hash()` (IntEnum, StrEnum, ...)."""
    bases: tuple[type, ...] = (str, bytes, *_NUMBERS)
    for base in bases:
        same: object = (cls.__eq__, cls.__hash__) == (base.__eq__, base.__hash__)
        if issubclass(cls, base) and same:
            if base is str:
                return _blake(str.encode(value, "utf-8", "surrogatepass"))
            if base is bytes:
                return hash((_TAG_SEQ, _blake(bytes(value))))
            return _number(value)
    raise _Opaque


def request_digest(request: Any) -> int | None:
    """A deterministic 64-bit digest of a request, such that `a == b` implies equal digests.

    Only *plain values* get one: built-in strings (BLAKE2b), bytes, numbers (their
    `hash()`), `None`, enum members with identity equality, and dicts, lists, tuples, sets
    of them (subclasses too that keep their base's `__eq__` and `__hash__`), digested
    without running code of their classes. `None` for any other value, or one that raises
    while digested (`Decimal("sNaN")`, a nesting too deep). Never `NO_DIGEST`.
    """
    try:
        return _digest(request)
    except Exception:  # noqa: BLE001 - _Opaque, RecursionError, InvalidOperation (sNaN)
        return None


def runtime_key(request: Any) -> Any:
    """The in-process bucket of a request that has no digest (never stored); a class that
    overrides `__eq__` but keeps a built-in `__hash__` goes with the unhashable ones."""
    cls = type(request)
    hasher: object = cls.__hash__
    owner = getattr(hasher, "__objclass__", None)
    if isinstance(owner, type) and owner is not cls:
        base_eq: object = owner.__eq__
        own_eq: object = cls.__eq__
        if base_eq is not own_eq:
            return UNHASHABLE
    try:
        return ("h", hash(request))
    except Exception:  # noqa: BLE001 - unhashable, or a __hash__ that raises: compare by ==
        return UNHASHABLE


def request_bucket(request: Any) -> Any:
    """A hashable key such that `a == b` implies equal keys: the digest, else `runtime_key`."""
    digest = request_digest(request)
    return digest if digest is not None else runtime_key(request)


def requests_equal(a: Any, b: Any) -> bool:
    """`a == b`, made total: a comparison that raises or is ambiguous means "different"."""
    try:
        return bool(a == b)
    except Exception:  # noqa: BLE001 - user __eq__ may raise anything; then they differ
        return False


def identity_equality(value: Any) -> bool:
    """Whether `value` can only equal itself (its class keeps `object.__eq__`)."""
    eq: object = type(value).__eq__
    return eq is object.__eq__


def candidates_without_digest(others: dict[Any, list[str]], key: Any) -> list[str]:
    """The resource ids among requests without a digest (`others`: `runtime_key` -> ids)
    that may `==` a request whose `runtime_key` is `key`."""
    if key == UNHASHABLE:
        return [rid for bucket in others.values() for rid in bucket]
    # Equal hashable values have equal hashes; unhashable stored ones are compared anyway.
    return [*others.get(key, ()), *others.get(UNHASHABLE, ())]


def describe(value: Any, limit: int = 200) -> str:
    """A `repr` of a plain value (cut at `limit` characters), else its type's name (user
    code may raise or hang on an actor's thread)."""
    if request_digest(value) is None:
        return f"<{type(value).__module__}.{type(value).__qualname__} object>"
    text = reprlib.repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."
