"""What a supervision tree and its registrars do, as frozen dataclasses (one per event kind).

Subscribe with `Supervisor.subscribe(callback)` (every child and every registrar of the
tree, manager processes included) or `ResourceRegistrar.subscribe(callback)` (one
registrar); both return an [`rr_actors.Subscription`][rr_actors.Subscription], and the
callback runs on a subscriber thread of its own, never in a registrar's mailbox.

Every event has its own fields first, then two keyword-only ones:

- `at`: when it happened, wall clock (`time.time()` seconds), so that events of several
  processes can be put on one timeline;
- `pid`: the process it happened in (for child events, the child's process).

Events pickle (they cross from manager processes to the supervisor's), and
[`to_dict`][rr_actors.events.to_dict] / [`from_dict`][rr_actors.events.from_dict] turn them
into JSON-able dicts and back (one JSON line per event is how experiments write
`events.jsonl`). [`describe`][rr_actors.events.describe] gives the one human line that is
also logged at INFO.

The kinds are in `kinds.py`, the JSON form in `lines.py`, the human line in `text.py`.
Durations are in seconds. Query and resource ids are UUID4 strings; `describe` shows their
first 8 characters.
"""

from __future__ import annotations

import logging

from rr_actors._core.bus import Publisher
from rr_actors.events.kinds import (
    CallAnswered,
    CallFailed,
    CallWithdrawn,
    CatalogRestored,
    ChildExited,
    ChildRestarted,
    ChildStarted,
    ConsumerAdded,
    ConsumerReleased,
    Event,
    EventsDropped,
    InDoubt,
    LoadFailed,
    QueryForgotten,
    RegistrarStopped,
    ResourceLoaded,
    ResourceUnloaded,
    StatusDelivered,
    StatusSent,
    SupervisorGaveUp,
    UnloadCutShort,
)
from rr_actors.events.lines import from_dict, to_dict
from rr_actors.events.text import describe

__all__ = [
    "CallAnswered",
    "CallFailed",
    "CallWithdrawn",
    "CatalogRestored",
    "ChildExited",
    "ChildRestarted",
    "ChildStarted",
    "ConsumerAdded",
    "ConsumerReleased",
    "Event",
    "EventsDropped",
    "InDoubt",
    "LoadFailed",
    "QueryForgotten",
    "RegistrarStopped",
    "ResourceLoaded",
    "ResourceUnloaded",
    "StatusDelivered",
    "StatusSent",
    "SupervisorGaveUp",
    "UnloadCutShort",
    "describe",
    "from_dict",
    "to_dict",
]


def publisher(logger: logging.Logger | None = None) -> Publisher[Event]:
    """A `Publisher` of these events: INFO lines through `describe`, `EventsDropped` notices.

    What registrars and supervisors publish on; not needed by programs that subscribe.

    Args:
        logger: where each event is also logged at INFO (when that logger is enabled
            for INFO), or `None` for no log lines.
    """
    return Publisher(logger=logger, describe=describe, notice=EventsDropped)
