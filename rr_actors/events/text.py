"""One human line per event: the INFO log line and what terminal timelines show."""

from __future__ import annotations

import typing

from rr_actors.events import kinds

__all__ = ["describe"]


def describe(event: kinds.Event) -> str:  # noqa: PLR0911, PLR0912 - one case per event kind
    """Return one human line about `event` (the INFO log line and terminal timelines).

    Ids are shortened to their first 8 characters; durations are in ms below a second.
    The `at` and `pid` every event has are left to the log record's own fields, except
    for child events, where the pid says which incarnation it was.

    Args:
        event: any event of this module.

    Returns:
        One line without a line break, for example `"erm restarted after 23.1 ms (pid 4242)"`.
    """
    match event:
        case kinds.ChildStarted():
            return f"{event.child} started (pid {event.pid})"
        case kinds.ChildExited():
            return f"{event.child} exited: {_text(event.reason)} (pid {event.pid})"
        case kinds.ChildRestarted():
            return f"{event.child} restarted after {_seconds(event.restart_s)} (pid {event.pid})"
        case kinds.SupervisorGaveUp():
            return (
                f"supervisor {event.supervisor} gave up (more than {event.max_restarts} "
                f"restarts within {event.period:g} s): {_text(event.reason)}"
            )
        case kinds.ManagerOverloaded():
            return (
                f"{event.manager} is overloaded, not hung: it answered its heartbeat after "
                f"{_seconds(event.silent_s)} (bound {_seconds(event.bound_s)}), "
                f"{_seconds(event.excused_s)} of it excused (its registrar busy for "
                f"{_seconds(event.busy_s)}, {event.queued} messages queued) (pid {event.pid})"
            )
        case kinds.ResourceLoaded():
            return (
                f"{event.registrar}/{event.server} loaded {_id(event.resource_id)} "
                f"in {_seconds(event.load_s)} (query {_id(event.query_id)})"
            )
        case kinds.LoadFailed():
            return (
                f"{event.registrar}/{event.server} failed to load {_id(event.resource_id)} "
                f"(query {_id(event.query_id)}): {event.error_type}: {_text(event.message)}"
            )
        case kinds.ResourceUnloaded():
            return f"{event.registrar}/{event.server} unloaded {_id(event.resource_id)}"
        case kinds.ConsumerAdded():
            return (
                f"{event.registrar}: {event.consumer} consumes {_id(event.resource_id)} "
                f"(query {_id(event.query_id)})"
            )
        case kinds.ConsumerReleased():
            why = "" if event.reason == "unload" else f", {event.reason}"
            return (
                f"{event.registrar}: {event.consumer} released {_id(event.resource_id)} "
                f"(query {_id(event.query_id)}{why})"
            )
        case kinds.CallAnswered():
            of = "" if event.parent is None else f" for {_id(event.parent)}"
            again = ", a retry" if event.retry else ""
            return (
                f"{event.registrar}: call {_id(event.query_id)} to "
                f"{event.serving_rr}/{event.server} answered{of}{again}"
            )
        case kinds.CallFailed():
            maybe = " (it may have executed: held until reconciled)" * event.may_have_executed
            return (
                f"{event.registrar}: call {_id(event.query_id)} to "
                f"{event.serving_rr}/{event.server} failed{maybe}: {event.error_type}: "
                f"{_text(event.message)}"
            )
        case kinds.CallWithdrawn():
            return (
                f"{event.registrar}: call {_id(event.query_id)} to "
                f"{event.serving_rr}/{event.server} withdrawn ({event.reason})"
            )
        case kinds.QueriesFetched():
            return (
                f"{event.registrar} fetched {len(event.query_ids)} queries it holds at "
                f"{event.serving_rr}/{event.server}"
            )
        case kinds.ServerQueriesListed():
            return (
                f"{event.registrar} listed {len(event.query_ids)} queries of its server "
                f"{event.server}"
            )
        case kinds.QueryForgotten():
            return (
                f"{event.registrar} forgot query {_id(event.query_id)} held at "
                f"{event.serving_rr} ({event.reason})"
            )
        case kinds.StatusSent():
            return (
                f"{event.registrar} sent {event.status.name} for query {_id(event.query_id)}: "
                f"{_text(event.message)}"
            )
        case kinds.StatusDelivered():
            return (
                f"{event.registrar} received {event.status.name} for query "
                f"{_id(event.query_id)} (hop {event.hop}, {_seconds(event.latency_s)} after "
                f"it was sent)"
            )
        case kinds.StatusHandled():
            waited = " (it waited for a registrar)" if event.opened else ""
            return (
                f"{event.registrar}: the callback of {event.status.name} for query "
                f"{_id(event.query_id)} returned{waited}"
            )
        case kinds.StatusAnswered():
            return (
                f"{event.registrar}: the send of {_id(event.status_id)} for query "
                f"{_id(event.query_id)} was answered ({len(event.reached)} reached, "
                f"{len(event.gave_up)} given up on)"
            )
        case kinds.InDoubt():
            cut = event.cut or "load"
            return (
                f"{event.registrar}: query {_id(event.query_id)} is in doubt "
                f"(its {cut} started before a crash and was never committed; found at each "
                f"restart until a setup offered it returns)"
            )
        case kinds.CatalogRestored():
            return f"{event.registrar} restored its catalog: {_counts(event.counts)}"
        case kinds.RegistrarStopped():
            return f"{event.registrar} stopped, its catalog holding {_counts(event.counts)}"
        case kinds.ServerOverloaded():
            return (
                f"{event.registrar}/{event.server} is overloaded: {event.pending} loads queued "
                f"or running (max_pending={event.bound}), {event.refused} calls refused"
            )
        case kinds.ShareRefused():
            return (
                f"{event.registrar}/{event.server} refused {event.consumer} at {event.under_way} "
                f"of {event.pending} loads, its share {event.share} of {event.bound}"
            )
        case kinds.ShareAdmitted():
            return (
                f"{event.registrar}/{event.server} admitted {event.consumer} at {event.under_way} "
                f"of {event.pending} loads, its share {event.share}, {len(event.waiting)} waiting"
            )
        case kinds.UnloadCutShort():
            return (
                f"{event.registrar}/{event.server}: the unload of {_id(event.resource_id)} was "
                f"cut short by a stop (in doubt at the next start)"
            )
        case kinds.EventsDropped(cause="killed"):
            return f"{event.count} events of process {event.pid} lost: it died before it sent them"
        case kinds.EventsDropped(cause="refused"):
            return f"{event.count} events refused: no member's certificate sealed them"
        case kinds.EventsDropped():
            return f"{event.count} events dropped (a subscriber or forwarder fell behind)"
        case kinds.EventsUnpublished():
            return (
                f"{len(event.seqs)} numbers of process {event.pid} never used: it was killed "
                f"before it published those events (none lost)"
            )
    typing.assert_never(event)


def _counts(counts: tuple[int, ...]) -> str:
    resources, consumers, clients = (*counts, 0, 0, 0)[:3]
    return f"{resources} resources, {consumers} consumer ids, {clients} client queries"


def _id(value: str) -> str:
    return value[:8]


def _seconds(value: float) -> str:
    return f"{value * 1e3:.1f} ms" if abs(value) < 1.0 else f"{value:.2f} s"


_LONGEST_TEXT = 200
"""Characters of free text (messages, reasons) `describe` keeps; the rest becomes `...`."""


def _text(value: str) -> str:
    line = value.replace("\r", "\\r").replace("\n", "\\n")
    if len(line) > _LONGEST_TEXT:
        return line[: _LONGEST_TEXT - 3] + "..."
    return line
