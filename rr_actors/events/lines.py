"""Events as JSON-able dicts and back: one JSON line per event (`events.jsonl`).

```
 event ──► to_dict ──► {"type", its fields, "schema"} ──► json.dumps: a line
 event ──► to_line ──► the same line, without the dict of lists (its fields read in
                        one call): `to_lines` writes a run's `events.jsonl` with it
 a line ──► parse_json ──► from_dict (every field checked) ──► the event
```
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import operator
import os
import reprlib
import sys
import typing
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from rr_actors._core import hlc
from rr_actors._types import Status
from rr_actors.errors import ConfigError
from rr_actors.events.kinds import Event

__all__ = [
    "MAX_LINE_BYTES",
    "SCHEMA",
    "from_dict",
    "json_lines",
    "parse_json",
    "to_dict",
    "to_line",
    "to_lines",
]

SCHEMA = 9
"""Version of the dicts `to_dict` writes (the `"schema"` key); `from_dict` reads 1 to 9.

A field added since a line's schema gets its default: 2 added `seq` (0), digests, labels, reasons
and the catalog events; 3 `host` (`""`) and `hlc` (the stamp of `at`); 4 `ChildExited`'s `restart`
(`""`), `normal`, `stopped`, `max_restarts`, `period`; 5 `QueryForgotten`'s `unload_sent` and
`reconciled` (0); 6 `ChildExited`'s `strategy` and `children`; 7 the calls' `trace`, `caller_span`
(`""`) and `started` (0.0); 8 `ResourceLoaded`'s `trace`; 9 `ShareRefused`'s `since` (0.0),
`waiting` and `firsts` (`()`).
"""

_READS = (1, 2, 3, 4, 5, 6, 7, 8, SCHEMA)


_TYPES: dict[str, type[Event]] = {cls.__name__: cls for cls in typing.get_args(Event)}


def to_dict(event: Event) -> dict[str, Any]:
    """Return `event` as JSON-able data: `"type"` (the class name), its fields, `"schema"`.

    A `Status` becomes its name (`"FATAL"`), a tuple a list. `json.dumps(to_dict(event))` is one
    line of an `events.jsonl` file; [`from_dict`][rr_actors.events.from_dict] reads it back.
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


def to_line(event: Event, extra: dict[str, Any] | None = None) -> str:
    """`json.dumps({**to_dict(event), **extra})`, without building the dict of lists.

    Args:
        event: any event of this module.
        extra: keys written after `"schema"` (an experiment's `run` and `seed`).
    """
    layout = _LAYOUTS.get(type(event))
    if layout is None:  # (not one of the kinds: whatever to_dict makes of it)
        return json.dumps({**to_dict(event), **(extra or {})})
    keys, values = layout
    data = dict(zip(keys, (type(event).__name__, *values(event), SCHEMA), strict=True))
    if extra:
        data.update(extra)
    return _encode(data)


def to_lines(seen: Iterable[Event], extra: dict[str, Any] | None = None) -> str:
    """Each event of `seen` as `to_line` writes it, a line each (an `events.jsonl`).

    Raises:
        TypeError: a value JSON cannot hold, before any line is made.
    """
    return "".join([f"{to_line(event, extra)}\n" for event in seen])


def _status_name(value: object) -> str:
    if isinstance(value, Status):
        return value.name
    raise TypeError(f"Object of type {type(value).__name__} is not JSON serializable")


_encode = json.JSONEncoder(default=_status_name).encode
"""`json.dumps`'s own settings, and a `Status` by its name."""

_LAYOUTS: dict[type[Event], tuple[tuple[str, ...], Callable[[Event], tuple[Any, ...]]]] = {
    cls: (
        ("type", *(f.name for f in dataclasses.fields(cls)), "schema"),
        operator.attrgetter(*(f.name for f in dataclasses.fields(cls))),
    )
    for cls in _TYPES.values()
}
"""Each kind's keys (`to_dict`'s) and the getter of its fields' values (one C call)."""


def from_dict(data: dict[str, Any]) -> Event:
    """Rebuild an event from [`to_dict`][rr_actors.events.to_dict] output.

    Every field must be present (`at` and `pid` too) and of its type; an `int` is accepted for a
    `float`, and a `float` must be finite.

    Raises:
        ConfigError: `data` is not a dict, has another `"schema"`, an unknown `"type"`, unknown
            or missing fields, or a value of the wrong type or not finite; the message names
            what was wrong.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"an event must be a dict, got {type(data).__name__}")
    schema = data.get("schema")
    if schema not in _READS:
        raise ConfigError(f"unsupported event schema {schema!r} (expected {SCHEMA})")
    name = data.get("type")
    reader = _READERS.get(name) if isinstance(name, str) else None
    if reader is None:
        close = difflib.get_close_matches(name, _READERS, n=1) if isinstance(name, str) else []
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise ConfigError(f"unknown event type {_shown(name)}{hint}")
    return reader.read(data, schema)


class _Reader:
    """How one event kind is read: its fields, each with the function that checks it."""

    def __init__(self, cls: type[Event]) -> None:
        hints = typing.get_type_hints(cls)
        self.cls = cls
        self.fields = tuple(
            (f.name, _converter(cls.__name__, f.name, hints[f.name]))
            for f in dataclasses.fields(cls)
        )
        self.keys = frozenset(name for name, _ in self.fields) | {"type", "schema"}
        self.optional = _optional(cls)

    def read(self, data: dict[str, Any], schema: int) -> Event:
        if data.keys() != self.keys:  # (what is wrong, unless an older schema's default)
            given = set(data) - {"type", "schema"}
            unknown = sorted(given - self.keys)
            optional = self.optional if schema < SCHEMA else set()
            missing = [f for f, _ in self.fields if f not in given and f not in optional]
            if unknown or missing:
                problems = [f"unknown fields {_shown(unknown)}"] * bool(unknown)
                problems += [f"missing fields {missing}"] * bool(missing)
                raise ConfigError(f"{self.cls.__name__}: {', '.join(problems)}")
        values = {name: check(data[name]) for name, check in self.fields if name in data}
        if schema < 3:  # (not this process's host, nor a stamp of reading time)
            values.setdefault("host", "")
            values.setdefault("hlc", hlc.from_seconds(values["at"]))
        return self.cls(**values)


def _optional(cls: type[Event]) -> set[str]:
    """Fields a line of an older schema may lack (those added since, with defaults)."""
    return {
        f.name
        for f in dataclasses.fields(cls)
        if f.name not in ("at", "pid")
        and (f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING)
    }


def _shown(value: object) -> str:
    """`repr(value)`, abbreviated (a field of a hostile file may be huge)."""
    return reprlib.repr(value)


def _converter(event: str, field: str, kind: Any) -> Callable[[Any], Any]:
    args = typing.get_args(kind)

    def wrong(value: object) -> ConfigError:
        expected = "a Status name" if kind is Status else getattr(kind, "__name__", str(kind))
        return ConfigError(f"{event}.{field} must be {expected}, got {_shown(value)}")

    if type(None) in args:  # `X | None`
        (inner,) = [a for a in args if a is not type(None)]
        check = _converter(event, field, inner)
        return lambda value: None if value is None else check(value)
    if typing.get_origin(kind) is tuple:
        item = _converter(event, field, args[0])

        def items(value: Any) -> tuple[Any, ...]:
            if not isinstance(value, list | tuple):
                raise ConfigError(f"{event}.{field} must be a list, got {_shown(value)}")
            return tuple(item(v) for v in value)

        return items
    if kind is str or kind is bool:

        def exact(value: Any) -> Any:
            if type(value) is not kind:
                raise wrong(value)
            return value

        return exact
    if kind is float:

        def real(value: Any) -> float:
            if type(value) is float:
                number = value
            elif type(value) is int:
                try:
                    number = float(value)
                except OverflowError:  # (beyond a float's range)
                    number = math.inf
            else:
                raise wrong(value)
            if not math.isfinite(number):
                raise ConfigError(f"{event}.{field} must be a finite number, got {_shown(value)}")
            return number

        return real
    if kind is int:
        low, high = (0, 2**64) if field == "hlc" else (None, None)

        def whole(value: Any) -> int:
            if type(value) is not int:
                raise wrong(value)
            if low is not None and not low <= value < high:  # type: ignore[operator]
                raise ConfigError(
                    f"{event}.hlc must be a stamp (0 to 2**64 - 1), got {_shown(value)}"
                )
            return value

        return whole
    if kind is Status:

        def status(value: Any) -> Status:
            if not isinstance(value, str) or value not in Status.__members__:
                raise wrong(value)
            return Status[value]

        return status
    raise TypeError(f"{event}.{field}: no reader for {kind!r}")  # (a new kind's field type)


_READERS: dict[str, _Reader] = {name: _Reader(cls) for name, cls in _TYPES.items()}


def parse_json(text: str | bytes, where: str) -> Any:
    """One line of a JSON lines file, parsed.

    Raises:
        ConfigError: not UTF-8, not JSON, nested too deeply, or a number of more than
            `sys.get_int_max_str_digits()` digits; the message begins with `where`.
    """
    try:
        return json.loads(text.decode("utf-8") if isinstance(text, bytes) else text)
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{where}: not UTF-8 text ({exc.reason})") from None
    except json.JSONDecodeError as exc:  # (its line and column are the file's line's)
        raise ConfigError(f"{where}: not JSON (column {exc.colno}: {exc.msg})") from None
    except RecursionError:
        raise ConfigError(f"{where}: not JSON that can be read (nested too deeply)") from None
    except ValueError:  # (an integer of more digits than Python converts: CVE-2020-10735)
        raise ConfigError(
            f"{where}: not JSON that can be read (a number of more than "
            f"{sys.get_int_max_str_digits()} digits)"
        ) from None


MAX_LINE_BYTES = 64 * 1024 * 1024
"""The longest line `json_lines` reads (64 MiB): a longer one is an error, not an out-of-memory."""


def json_lines(path: str | os.PathLike[str]) -> Iterator[tuple[int, Any]]:
    """`(line number, parsed JSON)` of each non-blank line of a JSON lines file (lines from 1).

    For files of unknown origin: what is wrong is a `ConfigError` naming the file and the line.

    Raises:
        ConfigError: the file cannot be read, or a line is not UTF-8, longer than
            `MAX_LINE_BYTES`, or not JSON.
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
            value = parse_json(raw, f"{os.fspath(path)} line {number}")
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
