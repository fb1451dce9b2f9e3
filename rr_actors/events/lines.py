"""Events as JSON-able dicts and back: one JSON line per event (`events.jsonl`)."""

from __future__ import annotations

import dataclasses
import json
import os
import typing
from collections.abc import Iterator
from typing import Any

from rr_actors._core import hlc
from rr_actors._types import Status
from rr_actors.errors import ConfigError
from rr_actors.events.kinds import Event

__all__ = ["MAX_LINE_BYTES", "SCHEMA", "from_dict", "json_lines", "to_dict"]

SCHEMA = 3
"""Version of the dicts `to_dict` writes (the `"schema"` key); `from_dict` reads it, 2 and 1.

Schema 2 added `seq`, request digests and labels, release reasons, in-doubt details and
the catalog events; a schema 1 line may lack the fields that have defaults (`seq`: 0).
Schema 3 added `host` (the member name of the host) and `hlc` (the hybrid logical clock
stamp) to every event; a line of an older schema gets `host` `""` (not known) and the
stamp of its `at` (`hlc.from_seconds`), so that old lines still sort by wall time.
"""

_READS = (1, 2, SCHEMA)


_TYPES: dict[str, type[Event]] = {cls.__name__: cls for cls in typing.get_args(Event)}


def to_dict(event: Event) -> dict[str, Any]:
    """Return `event` as JSON-able data: `"type"` (the class name), its fields, `"schema"`.

    A `Status` becomes its name (`"FATAL"`). `json.dumps(to_dict(event))` is one line of
    an `events.jsonl` file; [`from_dict`][rr_actors.events.from_dict] reads it back.

    Args:
        event: any event of this module.

    Returns:
        A new dict of strings, numbers and `"type"`/`"schema"` keys.
    """
    data: dict[str, Any] = {"type": type(event).__name__}
    for field in dataclasses.fields(event):
        value = getattr(event, field.name)
        if isinstance(value, Status):
            value = value.name
        elif isinstance(value, tuple):
            value = [list(row) if isinstance(row, tuple) else row for row in value]
        data[field.name] = value
    data["schema"] = SCHEMA
    return data


def from_dict(data: dict[str, Any]) -> Event:
    """Rebuild an event from [`to_dict`][rr_actors.events.to_dict] output.

    Every field must be present (`at` and `pid` too: they say when and where it
    happened, not when it was read) and of its type; an `int` is accepted for a `float`.

    Args:
        data: a dict as `to_dict` returns it (for example, one parsed JSON line).

    Returns:
        An event equal to the one `to_dict` was given.

    Raises:
        ConfigError: `data` is not a dict, has another `"schema"`, an unknown `"type"`,
            unknown or missing fields, or a value of the wrong type; the message names
            what was wrong.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"an event must be a dict, got {type(data).__name__}")
    if data.get("schema") not in _READS:
        raise ConfigError(f"unsupported event schema {data.get('schema')!r} (expected {SCHEMA})")
    name = data.get("type")
    cls = _TYPES.get(name) if isinstance(name, str) else None
    if cls is None:
        raise ConfigError(f"unknown event type {name!r}")
    types = _field_types(cls)
    given = set(data) - {"type", "schema"}
    unknown = sorted(given - set(types))
    optional = _optional(cls) if data["schema"] < SCHEMA else set()
    missing = [field for field in types if field not in given and field not in optional]
    if unknown or missing:
        problems = [f"unknown fields {unknown}"] * bool(unknown)
        problems += [f"missing fields {missing}"] * bool(missing)
        raise ConfigError(f"{name}: {', '.join(problems)}")
    values = {f: _convert(cls.__name__, f, kind, data[f]) for f, kind in types.items() if f in data}
    if data["schema"] < 3:  # (not this process's host, nor a stamp of reading time)
        values.setdefault("host", "")
        values.setdefault("hlc", hlc.from_seconds(values["at"]))
    return cls(**values)


def _optional(cls: type[Event]) -> set[str]:
    """Fields a line of an older schema may lack (those added since, with defaults)."""
    return {
        f.name
        for f in dataclasses.fields(cls)
        if f.name not in ("at", "pid")
        and (f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING)
    }


_FIELD_TYPES: dict[type, dict[str, type]] = {}  # (`get_type_hints` costs 1 ms, a line 20 us)


def _field_types(cls: type[Event]) -> dict[str, type]:
    types = _FIELD_TYPES.get(cls)
    if types is None:
        hints = typing.get_type_hints(cls)
        types = {field.name: hints[field.name] for field in dataclasses.fields(cls)}
        _FIELD_TYPES[cls] = types
    return types


def _convert(event: str, field: str, kind: Any, value: object) -> Any:
    """Check one field's value from a dict (and turn a status name into a `Status`)."""
    args = typing.get_args(kind)
    if type(None) in args:  # `X | None`
        if value is None:
            return None
        (kind,) = [a for a in args if a is not type(None)]
    if typing.get_origin(kind) is tuple:
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{event}.{field} must be a list, got {value!r}")
        item = args_of(kind)
        return tuple(_convert(event, field, item, v) for v in value)
    if kind is bool and isinstance(value, bool):
        return value
    if kind is Status and isinstance(value, str) and value in Status.__members__:
        return Status[value]
    if kind is float and isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    if kind in (int, str) and isinstance(value, kind) and not isinstance(value, bool):
        if field == "hlc" and not 0 <= value < 2**64:
            raise ConfigError(f"{event}.hlc must be a stamp (0 to 2**64 - 1), got {value!r}")
        return value
    expected = "a Status name" if kind is Status else getattr(kind, "__name__", str(kind))
    raise ConfigError(f"{event}.{field} must be {expected}, got {value!r}")


def args_of(kind: Any) -> Any:
    """The item type of `tuple[X, ...]`."""
    return typing.get_args(kind)[0]


MAX_LINE_BYTES = 64 * 1024 * 1024
"""The longest line `json_lines` reads (64 MiB): an event listing `LISTED_ROWS` rows of
each kind is far shorter; a longer line is an error, not a reason to run out of memory."""


def json_lines(path: str | os.PathLike[str]) -> Iterator[tuple[int, Any]]:
    """`(line number, parsed JSON)` of each non-blank line of a JSON lines file.

    For files of unknown origin (`rr-actors check`, `rr-actors events --merge`): what is
    wrong with one is a `ConfigError` naming the file and the line, never a traceback.

    Args:
        path: an `events.jsonl` file (or any JSON lines file).

    Yields:
        `(number, value)`: the line number (1 for the first line) and its JSON value.

    Raises:
        ConfigError: the file cannot be read (missing, a directory, no permission), or a
            line is not UTF-8, longer than `MAX_LINE_BYTES`, or not JSON (nested too
            deeply included).
    """
    try:
        file = open(path, "rb")  # noqa: SIM115 - closed below; opened first to name the error
    except OSError as exc:
        raise ConfigError(f"{os.fspath(path)}: cannot be read ({exc.strerror})") from None
    with file:
        number = 0
        while raw := _read_line(file, path, number + 1):
            number += 1
            if not raw.strip():
                continue
            where = f"{os.fspath(path)} line {number}"
            try:
                value = json.loads(raw.decode("utf-8"))
            except UnicodeDecodeError as exc:
                raise ConfigError(f"{where}: not UTF-8 text ({exc.reason})") from None
            except json.JSONDecodeError as exc:
                raise ConfigError(f"{where}: not JSON ({exc})") from None
            except RecursionError:
                raise ConfigError(
                    f"{where}: not JSON that can be read (nested too deeply)"
                ) from None
            yield number, value


def _read_line(file: Any, path: str | os.PathLike[str], number: int) -> bytes:
    try:
        raw: bytes = file.readline(MAX_LINE_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"{os.fspath(path)}: cannot be read ({exc.strerror})") from None
    if len(raw) > MAX_LINE_BYTES:
        raise ConfigError(
            f"{os.fspath(path)} line {number}: longer than {MAX_LINE_BYTES} bytes "
            f"(MAX_LINE_BYTES): not a line of events"
        )
    return raw
