"""How stored values are encoded, decoded and cheaply checked.

```
 request / response --dumps--> cloudpickle bytes (NULL for None) --> resources / clients row
 row --check_row / check_keys (no unpickling)--> Resource.encoded --decode, on first use--> value
```

Values are stored as they cross between processes (`wire.dumps`; `NULL` for `None`).
Reading validates cheaply what it does not decode (a whole pickle, a known state, no id
twice), so a damaged row left on disk raises `CatalogCorruptError` when first used.
"""

from __future__ import annotations

import contextlib
import dataclasses
import pickle
import sqlite3
from collections.abc import Callable, Iterator
from typing import Any

from rr_actors._catalog import ResourceState
from rr_actors._core import wire
from rr_actors.errors import CatalogCorruptError

STATE_CODES = {ResourceState.LOADING: 0, ResourceState.LOADED: 1, ResourceState.UNLOADING: 2}
STATES_BY_CODE = tuple(STATE_CODES)


def dumps(value: Any) -> bytes | None:
    """Encode a request or response for a row (`None` is stored as `NULL`)."""
    return None if value is None else wire.dumps(value)


def loads(blob: bytes | None) -> Any:
    return None if blob is None else pickle.loads(blob)


def decode(path: str, rid: str, field: str, blob: bytes | None) -> Any:
    """Decode a restored resource's stored value on first use (`CatalogCorruptError`)."""
    try:
        return loads(blob)
    except Exception as exc:
        raise CatalogCorruptError(
            path,
            f"the stored {field} of resource {rid} cannot be read: {type(exc).__name__}: {exc}",
        ) from exc


def _not_a_pickle(blob: bytes | None) -> bool:
    """Whether a stored value cannot be a whole binary pickle (protocol header ... STOP)."""
    return blob is not None and (
        type(blob) is not bytes or blob[:1] != b"\x80" or blob[-1:] != b"."
    )


def check_values(row: Any) -> None:
    """Raise `ValueError` if a resource row's request or response cannot be a pickle (a cheap
    check of what a restore leaves encoded)."""
    if _not_a_pickle(row[5]) or _not_a_pickle(row[6]):
        raise ValueError(f"the stored request or response of resource {row[1]} is not a pickle")


def _check_state(row: Any) -> None:
    state = row[3]
    if type(state) is not int or not 0 <= state < len(STATES_BY_CODE):
        raise ValueError(f"resource {row[1]} has an unknown state {state!r}")


def check_row(row: Any) -> None:
    """Raise `ValueError` if a resource row has an unknown state or a value is no pickle."""
    _check_state(row)
    check_values(row)


def check_keys(rows: list[Any], consumer_rows: list[Any], client_rows: list[Any]) -> None:
    """Raise `ValueError` for a duplicate id (it would replace the first silently) or an
    unknown state code."""
    for row in rows:
        _check_state(row)
    for what, ids in (
        ("resource id", [row[1] for row in rows]),
        ("consumer query id", [row[1] for row in consumer_rows]),
        ("client query id", [row[1] for row in client_rows]),
    ):
        if len(set(ids)) != len(ids):
            raise ValueError(f"{what} {first_duplicate(ids)} is stored twice")


def first_duplicate(values: list[Any]) -> Any:
    seen: set[Any] = set()
    for value in values:
        if value in seen:
            return value
        seen.add(value)
    return None


@dataclasses.dataclass(frozen=True)
class Unreadable:
    """Stands for a stored request or response that cannot be unpickled here (inspection).

    Attributes:
        error: why, e.g. `"ModuleNotFoundError: No module named 'drivers'"`.
        size: length of the pickle, in bytes.
    """

    error: str
    size: int

    def __repr__(self) -> str:
        return f"<unreadable, {self.size} bytes: {self.error}>"


@dataclasses.dataclass(frozen=True)
class NotUnpickled:
    """Stands for a stored request or response that was not unpickled (`size`: of the
    pickle, in bytes)."""

    size: int

    def __repr__(self) -> str:
        return f"<not unpickled, {self.size} bytes>"


def not_unpickled(_rid: str, _field: str, blob: bytes | None) -> Any:
    return None if blob is None else NotUnpickled(len(blob) if type(blob) is bytes else 0)


def lenient_decode(_rid: str, _field: str, blob: bytes | None) -> Any:
    """Decode a stored value, or stand for it with an `Unreadable` (inspection)."""
    try:
        return loads(blob)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is shown, not raised
        return Unreadable(f"{type(exc).__name__}: {exc}", len(blob or b""))


_DAMAGE_CODES = frozenset({"SQLITE_CORRUPT", "SQLITE_NOTADB"})  # pages not as written


def damaged_file(exc: BaseException) -> bool:
    """Whether SQLite raised `exc` because the file's pages are damaged (not a row)."""
    if not isinstance(exc, sqlite3.DatabaseError):
        return False
    code = getattr(exc, "sqlite_errorname", None)
    if code is not None:
        return any(code == c or code.startswith(f"{c}_") for c in _DAMAGE_CODES)
    return "malformed" in str(exc) or "not a database" in str(exc)


@contextlib.contextmanager
def as_corrupt(path: str, on_damage: Callable[[str], None] | None = None) -> Iterator[None]:
    """Raise `CatalogCorruptError`, naming `path`, for what SQLite, unpickling or a row
    check raises (`on_damage` told first when the pages are damaged)."""
    try:
        yield
    except sqlite3.DatabaseError as exc:
        why = f"{type(exc).__name__}: {exc}"
        if on_damage is not None and damaged_file(exc):
            on_damage(why)
        raise CatalogCorruptError(path, why) from exc
    except (
        pickle.UnpicklingError,
        EOFError,
        AttributeError,
        ImportError,
        ValueError,
        TypeError,
        KeyError,
        IndexError,
    ) as exc:
        raise CatalogCorruptError(
            path, f"a stored row cannot be read: {type(exc).__name__}: {exc}"
        ) from exc
