"""Events as JSON-able dicts and back: one JSON line per event (`events.jsonl`)."""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

from rr_actors._types import Status
from rr_actors.errors import ConfigError
from rr_actors.events.kinds import Event

__all__ = ["SCHEMA", "from_dict", "to_dict"]

SCHEMA = 1
"""Version of the dicts `to_dict` writes (the `"schema"` key); `from_dict` reads this one."""


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
        data[field.name] = value.name if isinstance(value, Status) else value
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
    if data.get("schema") != SCHEMA:
        raise ConfigError(f"unsupported event schema {data.get('schema')!r} (expected {SCHEMA})")
    name = data.get("type")
    cls = _TYPES.get(name) if isinstance(name, str) else None
    if cls is None:
        raise ConfigError(f"unknown event type {name!r}")
    types = _field_types(cls)
    given = set(data) - {"type", "schema"}
    unknown = sorted(given - set(types))
    missing = [field for field in types if field not in given]
    if unknown or missing:
        problems = [f"unknown fields {unknown}"] * bool(unknown)
        problems += [f"missing fields {missing}"] * bool(missing)
        raise ConfigError(f"{name}: {', '.join(problems)}")
    values = {f: _convert(cls.__name__, f, kind, data[f]) for f, kind in types.items()}
    return cls(**values)


def _field_types(cls: type[Event]) -> dict[str, type]:
    hints = typing.get_type_hints(cls)
    return {field.name: hints[field.name] for field in dataclasses.fields(cls)}


def _convert(event: str, field: str, kind: type, value: object) -> Any:
    """Check one field's value from a dict (and turn a status name into a `Status`)."""
    if kind is Status and isinstance(value, str) and value in Status.__members__:
        return Status[value]
    if kind is float and isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    if kind in (int, str) and isinstance(value, kind) and not isinstance(value, bool):
        return value
    expected = "a Status name" if kind is Status else kind.__name__
    raise ConfigError(f"{event}.{field} must be {expected}, got {value!r}")
