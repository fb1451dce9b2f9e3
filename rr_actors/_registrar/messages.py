"""Messages registrars exchange (the wire protocol between registrars).

Each is a frozen dataclass. A `reply` field holds where the answer goes: a local object
in-process; a transport replaces it by a token when the message crosses processes.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from rr_actors._core.directory import Reply
from rr_actors._types import Status

__all__ = [
    "Abandon",
    "ConsumerDown",
    "Fetch",
    "Load",
    "ResponseUpdated",
    "Revoke",
    "StatusNotice",
    "Unload",
]


@dataclasses.dataclass(frozen=True)
class Load:
    """Consumer -> provider: load `request` on `server` for consumer id `query_id`.

    `chain` holds the ids of the resources being loaded further up the call chain
    (for cycle detection). Answer: the response, or an error.
    """

    query_id: str
    server: str
    request: Any
    origin_rr: str
    chain: tuple[str, ...]
    reply: Reply


@dataclasses.dataclass(frozen=True)
class Unload:
    """Consumer -> provider: release consumer id `query_id`. Answer: `None` or an error."""

    query_id: str
    origin_rr: str
    reply: Reply


@dataclasses.dataclass(frozen=True)
class Abandon:
    """Consumer -> provider: the caller gave up on `query_id`; release it when possible."""

    query_id: str
    origin_rr: str


@dataclasses.dataclass(frozen=True)
class Fetch:
    """Consumer -> provider: list the queries `origin_rr` holds at `server`."""

    server: str
    origin_rr: str
    reply: Reply


@dataclasses.dataclass(frozen=True)
class StatusNotice:
    """Provider -> consumer: a status about the resources behind `query_ids`.

    `event` identifies one `send_status` so that a callback reached twice (diamond
    dependencies) runs once. Answer: `None` once delivered along the whole path.
    """

    query_ids: tuple[str, ...]
    status: Status
    message: str
    source: str
    event: str
    reply: Reply


@dataclasses.dataclass(frozen=True)
class Revoke:
    """Provider -> consumer: these consumer ids were released by the provider."""

    query_ids: tuple[str, ...]


@dataclasses.dataclass(frozen=True)
class ResponseUpdated:
    """Provider -> consumer: the stored response of these consumer ids changed.

    Answer: `None` once the consumer's client records hold the new response.
    """

    query_ids: tuple[str, ...]
    response: Any
    reply: Reply


@dataclasses.dataclass(frozen=True)
class ConsumerDown:
    """Death watch -> provider: registrar `origin_rr` died and will not come back."""

    origin_rr: str
