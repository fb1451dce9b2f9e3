"""From a run's events, faults and calls to its numbers: pure functions, no I/O.

    events (ChildExited / ChildStarted / ChildRestarted) ──down_intervals──► per manager, down
    faults (kill, hang) ──────────────────────────────────┘ (a kill or hang starts the interval)
    down + events + calls + client recoveries ──recovery_time(fault)──► seconds, or None
    events ──restarts──► restarts of managers, restarts of nested supervisors

Times are seconds from the start of the run's workload; events carry wall-clock `at`,
so the run's wall-clock start `t0` converts them.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import NamedTuple

from rr_actors import events
from rr_actors_lab.experiments.results import FaultRecord

__all__ = [
    "ClientRecovery",
    "Down",
    "down_intervals",
    "percentile",
    "recovery_time",
    "restarts",
    "unavailable",
]

Down = dict[str, list[tuple[float, float | None]]]
"""Per manager, the intervals it did not serve: `(start, end)`, `end` `None` if never back."""

_MANAGER_FAULTS = ("kill_manager", "hang_manager")

_EPS = 1e-9
"""Seconds of slack when comparing a fault's injection with an interval's start."""


class ClientRecovery(NamedTuple):
    """A client got a resource back after its provider said it failed (`workload.Client`).

    Attributes:
        manager: the provider the client called (it may hold the failed resource through
            a nested load of another manager's).
        heard_s: when the client heard the `FATAL` or `UPDATE` (seconds from the run's start).
        back_s: when it had the resource back (seconds from the run's start).
    """

    manager: str
    heard_s: float
    back_s: float


def down_intervals(
    seen: Iterable[events.Event],
    managers: Sequence[str],
    t0: float,
    faults: Sequence[FaultRecord] = (),
    resumed: Sequence[tuple[str, float]] = (),
    until: float | None = None,
) -> Down:
    """When each manager did not serve, from the child events of a run.

    An interval opens at a `ChildExited` (or at a kill or hang injected into a serving
    manager) and closes at its next `ChildStarted` or `ChildRestarted` (or its `SIGCONT`).

    Args:
        seen: the run's events, in any order.
        managers: the managers' names.
        t0: the wall-clock start of the run (`time.time()` seconds).
        faults: the run's faults.
        resumed: `(manager, time)` of each hung manager resumed while still alive.
        until: ignore what happened after this time (the run's own shutdown of the tree).

    Returns:
        Per manager, its intervals in time order.
    """
    changes: list[tuple[float, int, str, bool]] = []  # (time, order, manager, up)
    for event in seen:
        if isinstance(event, events.ChildExited) and event.child in managers:
            changes.append((event.at - t0, 1, event.child, False))
        elif isinstance(event, events.ChildStarted | events.ChildRestarted) and (
            event.child in managers
        ):
            changes.append((event.at - t0, 2, event.child, True))
    changes.extend(
        (fault.injected_s, 0, fault.target, False)
        for fault in faults
        if fault.kind in _MANAGER_FAULTS and fault.injected_s is not None and fault.target
    )
    changes.extend((at, 3, name, True) for name, at in resumed if name in managers)
    if until is not None:
        changes = [change for change in changes if change[0] <= until]
    changes.sort()
    down: Down = {name: [] for name in managers}
    opened: dict[str, float] = {}
    for at, _, name, up in changes:
        if up:
            if name in opened:
                down[name].append((opened.pop(name), at))
        elif name not in opened:
            opened[name] = at
    for name, at in opened.items():
        down[name].append((at, None))
    for intervals in down.values():
        intervals.sort(key=lambda i: i[0])
    return down


def unavailable(down: Down, end: float) -> dict[str, float]:
    """Seconds each manager did not serve between the run's start (0) and `end`."""
    total: dict[str, float] = {}
    for name, intervals in down.items():
        seconds = 0.0
        for start, stop in intervals:
            lo, hi = max(0.0, start), min(end, end if stop is None else stop)
            seconds += max(0.0, hi - lo)
        total[name] = seconds
    return total


def recovery_time(
    fault: FaultRecord,
    down: Down,
    seen: Sequence[events.Event],
    t0: float,
    client_recoveries: Sequence[ClientRecovery],
    *,
    load_error_until: float | None = None,
) -> float | None:
    """Seconds from `fault`'s injection until the system served again, or `None`.

    "Served again" per kind (`docs/reference/plan.md`, "Recovery"): `kill_manager`,
    `hang_manager`: the manager and every other that went down meanwhile serve again;
    `kill_resource`: a client that heard of the failure got its resource back;
    `load_error`: a load completed after the fault ended; `cut_connections`: the manager
    answered a call again.

    Args:
        fault: an injected fault.
        down: `down_intervals` of the run.
        seen: the run's events.
        t0: the wall-clock start of the run (`time.time()` seconds).
        client_recoveries: every time a client got a resource back.
        load_error_until: for `load_error`, when the fault ended (seconds from the run's
            start), or `None` if it never ended.

    Returns:
        Seconds from the injection to the recovery; `None` if the fault was not injected,
        has no target, or the system did not recover within the events given.
    """
    if fault.injected_s is None or fault.target is None:
        return None
    t = fault.injected_s
    if fault.kind in _MANAGER_FAULTS:
        back = _all_up_after(down, fault.target, t)
        return None if back is None else back - t
    if fault.kind == "kill_resource":
        holders = _holders_of(fault.target, seen)
        later = [
            r.back_s
            for r in client_recoveries
            if r.manager in holders and r.heard_s >= t - _EPS and r.back_s >= t
        ]
        return min(later) - t if later else None
    if fault.kind == "load_error":
        if load_error_until is None:
            return None
        loads = [
            e.at - t0
            for e in seen
            if isinstance(e, events.ResourceLoaded)
            and e.registrar == fault.target
            and e.at - t0 >= load_error_until
        ]
        return min(loads) - t if loads else None
    answered = [
        e.at - t0
        for e in seen
        if isinstance(e, events.ConsumerAdded) and e.registrar == fault.target and e.at - t0 >= t
    ]
    return min(answered) - t if answered else None


def restarts(seen: Iterable[events.Event], managers: Sequence[str]) -> tuple[int, int]:
    """How many times the tree restarted a manager, and a nested supervisor:
    `(restarts of managers, restarts of nested supervisors)`.

    A nested supervisor's restart counts once among the supervisors' and once per manager
    it restarted among the managers'; `managers` are the managers' names.
    """
    of_managers = of_supervisors = 0
    for event in seen:
        if isinstance(event, events.ChildRestarted):
            if event.child in managers:
                of_managers += 1
            else:
                of_supervisors += 1
    return of_managers, of_supervisors


def _holders_of(manager: str, seen: Iterable[events.Event]) -> set[str]:
    """`manager` and every registrar that holds its resources, directly or through others."""
    consumers: dict[str, set[str]] = {}
    for event in seen:
        if isinstance(event, events.ConsumerAdded):
            consumers.setdefault(event.registrar, set()).add(event.consumer)
    holders = {manager}
    todo = [manager]
    while todo:
        for consumer in consumers.get(todo.pop(), ()):
            if consumer not in holders:
                holders.add(consumer)
                todo.append(consumer)
    return holders


def _all_up_after(down: Down, target: str, t: float) -> float | None:
    """The first time after `t` when `target` is back from the interval `t` is in, and no
    manager that went down at or after `t` is still down (a sibling taken down meanwhile
    counts; an outage that began before the fault belongs to another fault)."""
    back: float | None = None
    for start, end in down.get(target, []):
        if start <= t + _EPS and (end is None or end >= t):
            back = end
            if back is None:
                return None
            break
    if back is None:
        return None  # it never went down: nothing to recover from
    moved = True
    while moved:
        moved = False
        for intervals in down.values():
            for start, end in intervals:
                if t - _EPS <= start <= back and (end is None or end > back):
                    if end is None:
                        return None
                    back = end
                    moved = True
    return back


def percentile(values: Sequence[float], q: float) -> float | None:
    """The `q`-th percentile (0-100) of `values`, linearly interpolated; `None` if empty."""
    if not values:
        return None
    ordered = sorted(values)
    rank = (len(ordered) - 1) * q / 100.0
    low = math.floor(rank)
    high = math.ceil(rank)
    return ordered[low] + (ordered[high] - ordered[low]) * (rank - low)


def affected_hosts(
    kind: str, target: str | None, hosts: Sequence[str], side: Sequence[str] = ()
) -> set[str]:
    """The hosts whose managers a fault between hosts takes from the clients (who run on
    the first host): the far end of a cut link, the side of a partition without the
    clients' host, a frozen or killed router's host."""
    home = hosts[0]
    if kind == "cut" and target is not None:
        ends = set(target.split("-", 1)) if "-" in target else {target}
        return ends - {home} if home in ends else ends
    if kind == "partition":
        return set(hosts) - set(side) if home in side else set(side)
    return {target} if target is not None else set()


def host_fault_times(
    fault: FaultRecord,
    providers: set[str],
    for_s: float,
    seen: Sequence[events.Event],
    t0: float,
) -> tuple[float | None, float | None, float | None]:
    """`(time to fail, time to heal, recovery)` of a fault between hosts, in seconds (`None`: not
    in the run): to the first failed call to `providers`; from the fault's end (`kill_router`:
    that failure) to the first call answered after it; from the injection to that answer."""
    if fault.injected_s is None or fault.skipped:
        return None, None, None
    start = fault.injected_s
    failed = [
        e.at - t0
        for e in seen
        if isinstance(e, events.CallFailed)
        and e.serving_rr in providers
        and e.registrar.startswith("client-")
        and e.at - t0 >= start
    ]
    first_failure = min(failed) if failed else None
    end = start + for_s
    if fault.kind == "kill_router":
        end = first_failure if first_failure is not None else start
    answered = [
        e.at - t0
        for e in seen
        if isinstance(e, events.CallAnswered)
        and e.serving_rr in providers
        and e.registrar.startswith("client-")
        and e.at - t0 >= end
    ]
    healed = min(answered) if answered else None
    return (
        None if first_failure is None else first_failure - start,
        None if healed is None else healed - end,
        None if healed is None else healed - start,
    )
