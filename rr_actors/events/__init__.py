"""What a supervision tree and its registrars do, as frozen dataclasses (one per event kind).

Subscribe with `Supervisor.subscribe(callback)` (every child and registrar of the tree, manager
processes included), `ResourceRegistrar.subscribe(callback)` (one registrar) or
`net.subscribe_events(callback)` (every host of a `ZenohNetwork`); the first two return an
[`rr_actors.Subscription`][rr_actors.Subscription], whose callback runs on a thread of its own,
never in a registrar's mailbox.

Every event has its own fields first, then keyword-only stamps: `at` (wall clock, `time.time()`
seconds), `pid` (its process; a child event's is the child's), `seq` (its number among its process's
events, where a gap shows a lost event; 0 where not numbered), `host` (the member name of its host)
and `hlc`, a hybrid logical clock stamp (Kulkarni et al., 2014): sorting several hosts' events by it
([`order`][rr_actors.events.order]) puts every cause before its effects, whatever the clocks say.
Fields named alike mean alike: `registrar` is the registrar that published it (the provider for a
server's event, the consumer for a call's), `server` a resource server of it (of `serving_rr`, the
provider, in a call's event), `resource_id` and `query_id` the ids (UUID4), `supervisor` and `child`
names, `status` the status code; a call's `started`, `trace` and `caller_span` are as
[`CallAnswered`][rr_actors.events.CallAnswered] says. Durations are in seconds.

Events pickle; [`to_dict`][rr_actors.events.to_dict] / [`from_dict`][rr_actors.events.from_dict]
turn them into JSON-able dicts and back (one line each in `events.jsonl`);
[`describe`][rr_actors.events.describe] gives the human line also logged at INFO.
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
    EventsUnpublished,
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
    ShareAdmitted,
    ShareRefused,
    StatusAnswered,
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
    "EventsUnpublished",
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
    "ShareAdmitted",
    "ShareRefused",
    "StatusAnswered",
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

    Every cause then comes before its effects, which sorting by `at` does not give when the
    hosts' clocks differ; equal stamps keep their order in `stream`.
    """
    return sorted(stream, key=_stamp)


def _stamp(event: Event) -> int:
    return event.hlc


_EVERYTHING: Publisher[Event] = runtime.process_state(
    Publisher(notice=EventsDropped), functools.partial(Publisher, notice=EventsDropped)
)


def everything() -> Publisher[Event]:
    """Every event published in this process where it happened (not those forwarded to it).

    What a system-wide event stream sends from each process; registrars build events while it
    has a sink.
    """
    return _EVERYTHING


def publisher(logger: logging.Logger | None = None) -> Publisher[Event]:
    """A `Publisher` of these events: INFO lines through `describe`, `EventsDropped` notices.

    Args:
        logger: where each event is also logged at INFO, or `None` for no log lines.
    """
    return Publisher(logger=logger, describe=describe, notice=EventsDropped, tap=_EVERYTHING)
