"""What a supervision tree and its registrars do, as frozen dataclasses (one per event kind).

Subscribe with `Supervisor.subscribe(callback)` (every child and every registrar of the
tree, manager processes included) or `ResourceRegistrar.subscribe(callback)` (one
registrar); both return an [`rr_actors.Subscription`][rr_actors.Subscription], and the
callback runs on a subscriber thread of its own, never in a registrar's mailbox.

Every event has its own fields first, then keyword-only ones:

- `at`: when it happened, wall clock (`time.time()` seconds), so that events of several
  processes can be put on one timeline;
- `pid`: the process it happened in (for child events, the child's process);
- `seq`: its number among its process's events (1, 2, 3, ... in a manager process, where a
  gap shows a lost event; 0 where events are not numbered; child events have none);
- `host`: the member name of the host it happened on (the certificate's common name on a
  `ZenohNetwork` with TLS; else the machine's host name);
- `hlc`: a hybrid logical clock stamp (Kulkarni et al., 2014), carried on every message
  between hosts: sorting a stream of several hosts by `hlc` ([`order`][rr_actors.events.order])
  puts every cause before its effects, whatever the machines' clocks say.

A kind's own docstring says when its `at` was taken and whose process `pid` is, where that
is more precise.

Every event of every host of a system served on a `ZenohNetwork`:
`net.subscribe_events(callback)` (`rr-actors events --network ...` on the command line).

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

import functools
import logging
from collections.abc import Iterable

from rr_actors._core import runtime
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
    ManagerOverloaded,
    QueriesFetched,
    QueryForgotten,
    RegistrarStopped,
    ResourceLoaded,
    ResourceUnloaded,
    ServerOverloaded,
    ServerQueriesListed,
    StatusDelivered,
    StatusHandled,
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
    "ManagerOverloaded",
    "QueriesFetched",
    "QueryForgotten",
    "RegistrarStopped",
    "ResourceLoaded",
    "ResourceUnloaded",
    "ServerOverloaded",
    "ServerQueriesListed",
    "StatusDelivered",
    "StatusHandled",
    "StatusSent",
    "SupervisorGaveUp",
    "UnloadCutShort",
    "describe",
    "from_dict",
    "order",
    "to_dict",
]


def order(stream: Iterable[Event]) -> list[Event]:
    """The events of `stream` (of one or several hosts) sorted by their `hlc` stamp.

    Every cause then comes before its effects (an answered `Load`'s `ConsumerAdded` on
    the provider's host before the consumer's `CallAnswered`), which sorting by `at`
    does not give when the hosts' clocks differ. Events with equal stamps (of different
    processes) keep their order in `stream`.
    """
    return sorted(stream, key=_stamp)


def _stamp(event: Event) -> int:
    return event.hlc


_EVERYTHING: Publisher[Event] = runtime.process_state(
    Publisher(notice=EventsDropped), functools.partial(Publisher, notice=EventsDropped)
)


def everything() -> Publisher[Event]:
    """Every event published in this process, once, where it happened (not the events
    forwarded to it from manager processes, which they publish themselves).

    What a system-wide event stream sends from each process (`ZenohNetwork`); every
    `publisher()` taps into it, so its registrars build events while it has a sink.
    """
    return _EVERYTHING


def publisher(logger: logging.Logger | None = None) -> Publisher[Event]:
    """A `Publisher` of these events: INFO lines through `describe`, `EventsDropped` notices.

    What registrars and supervisors publish on; not needed by programs that subscribe.

    Args:
        logger: where each event is also logged at INFO (when that logger is enabled
            for INFO), or `None` for no log lines.
    """
    return Publisher(logger=logger, describe=describe, notice=EventsDropped, tap=_EVERYTHING)
