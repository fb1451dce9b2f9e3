"""What crosses between hosts for the observer: JSON messages, and the checks of what arrives.

```
 Share (host B) ── delta: dumps({"v", "member", "instance", "seq", "sections", "events",
                  │        "missed"})  ─────────────────► decode ─► valid_section,
                  └─ state: dumps({"v", "member", "instance",     valid_event ─► SystemView
                           "seq", "sections", "events"}) ─────►  (host A): what fails a
                                                                 check is dropped
```

Keys (`rr_actors._transport.zenoh.wire.Keys`, under `rr/<system>/obs/<member>/`, members
only): `delta`, `state`, `fault`, `here`. JSON only, and each section and event is checked
on its own (`valid_*`, `finite`: a non-finite number would make a browser refuse the whole
message); one out of sequence has the state asked again. A delta's sections are
`[key, "v"|"p", value or patch]` (`_delta.diff`); the state's are `{key: value}`,
consistent with the delta numbered `seq`. Shared sections (`shared`): `host`, `tree`,
`catalog/<registrar>`, `links` (`link_row`), `ended`.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable, Mapping
from typing import Any

from rr_actors.config import NAME

__all__ = [
    "MAX_MESSAGE",
    "VERSION",
    "decode",
    "dumps",
    "finite",
    "link_row",
    "shared",
    "text",
    "valid_catalog",
    "valid_event",
    "valid_section",
    "valid_tree",
]

logger = logging.getLogger("rr_actors")

VERSION = 1
"""The version of what crosses (a message of another version is dropped)."""


MAX_MESSAGE = 32 * 1024 * 1024
"""Bytes a delta or a state may have (a catalog of 10,000 resources is a few MiB)."""


def dumps(value: Any) -> bytes:
    """`value` as compact JSON bytes."""
    return json.dumps(value, separators=(",", ":")).encode()


def shared(key: str) -> bool:
    """Whether a section of a host's own hub crosses to other hosts."""
    if key in ("host", "tree", "links", "ended"):
        return True
    return key.startswith("catalog/") and NAME.fullmatch(key[8:]) is not None


def link_row(m: Any) -> dict[str, Any]:
    """A row of the `links` section: this host's link to member `m.member`
    (`Services.links()`: up, or down since when, where, why)."""
    return {"member": m.member, "up": m.up, "since": m.since, "where": m.where, "why": m.why}


# -- what a host receives is checked ----------------------------------------------------------


def decode(member: str, data: bytes) -> dict[str, Any] | None:
    """A delta or a state `member` sent, if it is JSON of this version from `member`."""
    if len(data) > MAX_MESSAGE:
        logger.warning("observer: %s sent %d bytes, more than allowed", member, len(data))
        return None
    try:
        message = json.loads(data)
    except (ValueError, RecursionError):  # (nested past the parser's stack: not a message)
        return None
    if (
        not isinstance(message, dict)
        or message.get("v") != VERSION
        or message.get("member") != member
        or not text(message.get("instance"))
        or not isinstance(message.get("seq"), int)
    ):
        return None
    return message


def text(value: Any, *, none: bool = False) -> bool:
    """Whether `value` is a string (or, with `none`, `None`)."""
    return isinstance(value, str) or (none and value is None)


def _number(value: Any, *, none: bool = False) -> bool:
    if value is None:
        return none
    if isinstance(value, float):
        return math.isfinite(value)
    return isinstance(value, int) and not isinstance(value, bool)


def finite(value: Any) -> bool:
    """Whether every number in `value` (parsed JSON, at any depth) is finite: no `NaN`,
    `Infinity` or `-Infinity`, which a browser's `JSON.parse` refuses."""
    stack = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, float):
            if not math.isfinite(item):
                return False
        elif isinstance(item, dict):
            stack.extend(item.values())
        elif isinstance(item, list):
            stack.extend(item)
    return True


def valid_tree(node: Any, depth: int = 0) -> bool:
    """Whether `node` is a tree section as a `LiveSource` makes it (names, states, numbers)."""
    if not isinstance(node, dict) or depth > 16:
        return False
    if not (text(node.get("name")) and text(node.get("kind")) and text(node.get("state"))):
        return False
    for key in ("pid", "restarts", "restart_due", "server_time", "max_restarts", "period"):
        if key in node and not _number(node[key], none=True):
            return False
    for key in ("last_exit", "gave_up", "isolation", "restart", "strategy"):
        if key in node and not text(node[key], none=True):
            return False
    children = node.get("children", [])
    if not isinstance(children, list):
        return False
    return all(valid_tree(child, depth + 1) for child in children)


def _rows(value: Any, fields: Mapping[str, Callable[[Any], bool]]) -> bool:
    return isinstance(value, list) and all(
        isinstance(row, dict) and all(check(row.get(f)) for f, check in fields.items())
        for row in value
    )


_CONSUMER = {"query_id": text, "origin": text}
_RESOURCE: dict[str, Callable[[Any], bool]] = {
    "id": text,
    "server": text,
    "state": text,
    "in_doubt": lambda v: isinstance(v, bool),
    "request": text,
    "response": text,
    "label": lambda v: text(v, none=True),
    "consumers": lambda v: _rows(v, _CONSUMER),
}
_CLIENT: dict[str, Callable[[Any], bool]] = {
    "query_id": text,
    "serving_rr": text,
    "server": text,
    "request": text,
    "parent": lambda v: text(v, none=True),
    "loaded": lambda v: isinstance(v, bool),
}


def valid_catalog(section: Any) -> bool:
    """Whether `section` is a catalog section as a `LiveSource` makes it."""
    if not isinstance(section, dict):
        return False
    if not (
        text(section.get("registrar"))
        and text(section.get("kind"))
        and text(section.get("state"))
        and isinstance(section.get("available"), bool)
        and text(section.get("error"), none=True)
    ):
        return False
    catalog = section.get("catalog")
    if catalog is None:
        return True
    return (
        isinstance(catalog, dict)
        and catalog.get("registrar") == section["registrar"]
        and isinstance(catalog.get("servers"), list)
        and all(text(s) for s in catalog["servers"])
        and _rows(catalog.get("resources"), _RESOURCE)
        and _rows(catalog.get("clients"), _CLIENT)
        and _rows(catalog.get("in_doubt", []), {"id": text, "request": text})
    )


_LINK = {
    "member": text,
    "up": lambda v: isinstance(v, bool),
    "since": _number,
    "where": text,
    "why": text,
}


def valid_section(key: str, value: Any) -> bool:
    """Whether `value` is a shared section `key` as a host makes it (`None`: removed),
    every number in it finite."""
    return value is None or (finite(value) and _shaped(key, value))


def _shaped(key: str, value: Any) -> bool:
    if key == "tree":
        return valid_tree(value)
    if key == "links":
        return _rows(value, _LINK)
    if key == "ended":
        return isinstance(value, dict) and _number(value.get("at"))
    if key == "host":
        return (
            isinstance(value, dict)
            and text(value.get("member"))
            and text(value.get("title"))
            and isinstance(value.get("allow_faults"), bool)
            and _number(value.get("pid"), none=True)
        )
    return valid_catalog(value)


def valid_event(event: Any) -> bool:
    """Whether `event` is an event as a host shares it (a type, a time, its `seq`), every
    number in it finite."""
    return (
        isinstance(event, dict)
        and text(event.get("type"))
        and _number(event.get("at"))
        and text(event.get("text"), none=True)
        and isinstance(event.get("seq"), int)
        and finite(event)
    )
