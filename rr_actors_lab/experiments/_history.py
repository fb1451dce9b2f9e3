"""What every rule of `check.py` needs first: findings, and each registrar's lives.

```
 history [(line, event), ...] ──► walk ──► steps: (registrar, line, event, new, life)
                              │        └─► lives: (registrar, life) -> Life
                              └─► gather ──► Facts: what the whole run says, wherever
```

A registrar's *life* (an incarnation) begins at a `CatalogRestored`, at its first event in
another process, or at its first event after a `ChildExited` of its own process or its
`RegistrarStopped`; it ends at that exit or stop, or where the next one begins. A *second
server* of a name (only a cut lets one be, rule 22) is another process whose events of that
registrar begin while the one it would follow still serves: it is checked as a registrar
`<name>@<pid>`, its life recording which one it served `beside`.

Two clocks: within one registrar, the order of its lines (one process publishes in order,
but for events two of its threads built at once: one numbered below the last of a life that
ended comes from that life); across registrars, the hybrid logical clock stamps (`hlc`),
which order a cause before its effects across processes and hosts (the order of lines does
not: each process forwards its events in batches).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Literal

from rr_actors import events
from rr_actors._types import Status

__all__ = [
    "REPORTED",
    "Facts",
    "Finding",
    "Kind",
    "Life",
    "Line",
    "Step",
    "gather",
    "holder_at",
    "registrar_of",
    "walk",
]

Line = tuple[int, events.Event]
"""An event with its line number in `events.jsonl` (1 for the first line)."""

Kind = Literal["violation", "unverifiable"]

Step = tuple[str, int, events.Event, bool, int]
"""`(registrar, line, event, new, life)`: a registrar's event, whether it begins a new
life of it, and which life (0, 1, ...) it belongs to."""

REPORTED = ("provider lost", "unknown at reconcile")
"""`QueryForgotten` reasons whose `FATAL` the consumer delivers itself (no `StatusSent`):
its provider is lost for good (rule 19), or its restart lost the id (rule 20)."""


@dataclasses.dataclass(frozen=True)
class Finding:
    """One thing a run's events show against a rule, or keep from being checked.

    Attributes:
        rule: which rule (one of `check.RULES`).
        kind: `"violation"`, or `"unverifiable"` (events were lost where it happened).
        message: what happened, for people.
        lines: the line numbers of the smallest window of events that shows it.
        registrars: the registrars it is about (a loss in their process downgrades a
            violation to unverifiable).
    """

    rule: str
    kind: Kind
    message: str
    lines: tuple[int, ...]
    registrars: tuple[str, ...] = ()


@dataclasses.dataclass(slots=True)
class Life:
    """One life of a registrar, as its events show it.

    Attributes:
        start: the stamp (`hlc`) of its first event.
        last: the stamp of its last event.
        last_line: the line of its last event.
        end: the stamp it ended at (its `ChildExited`, its `RegistrarStopped`, or the first
            event of its next life), `None` if the run shows no end.
        host: the host of its events (`""`: not known, as in files of schema 2).
        pid: the process of its first event.
        first_line: the line of its first event.
        beside: for a second server of a name (see the module docstring), the
            `(registrar, life)` it served beside; `None` for every other life.
    """

    start: int
    last: int
    last_line: int
    end: int | None = None
    host: str = ""
    pid: int = 0
    first_line: int = 0
    beside: tuple[str, int] | None = None

    def ended_before(self, stamp: int) -> bool:
        """Whether it had ended at `stamp` (by what the run shows)."""
        return self.end is not None and self.end < stamp


def registrar_of(event: events.Event) -> str | None:
    """The registrar an event is of (`None` for a supervisor's or the stream's own)."""
    return getattr(event, "registrar", None)


def walk(history: Sequence[Line]) -> tuple[list[Step], dict[tuple[str, int], Life]]:
    """Each registrar event with its life, and the lives (see the module docstring).

    A `StatusDelivered` or `StatusHandled` belongs to the life its registrar is in and begins
    none (a status desk may publish it from another thread); a `RegistrarStopped` from another
    process begins a life first (a restart without a backup that published nothing else).
    """
    walker = _Walk(history)
    exited, step = walker.exited, walker.step
    for line, event in history:
        if isinstance(event, events.ChildExited):
            exited(event)
        elif getattr(event, "registrar", None) is not None:
            step(line, event)
    return walker.steps, walker.lives


class _Walk:
    """`walk`'s state: each registrar's pid and life now, and the second servers."""

    def __init__(self, history: Sequence[Line]) -> None:
        self.history = history
        self._last: dict[tuple[str, int], tuple[int, int]] | None = None  # (see `last`)
        self.pids: dict[str, int] = {}
        self.current: dict[str, int] = {}  # registrar -> its life now
        self.now: dict[str, Life] = {}  # registrar -> that life's record
        self.over: set[str] = set()  # registrars whose life ended (the next event begins one)
        self.top: dict[str, int] = {}  # registrar -> the greatest `seq` of its life now
        self.second: dict[tuple[str, int], str] = {}  # (name, pid) of a second server -> ...
        self.lives: dict[tuple[str, int], Life] = {}
        self.steps: list[Step] = []

    def exited(self, event: events.ChildExited) -> None:
        child = self.second.get((event.child, event.pid), event.child)
        if self.pids.get(child) == event.pid and child not in self.over:
            self.now[child].end = event.hlc
            self.over.add(child)

    @property
    def last(self) -> dict[tuple[str, int], tuple[int, int]]:
        """`(name, pid)` -> the line and greatest stamp of its last event (statuses' deliveries
        aside)."""
        if self._last is None:
            self._last = {}
            for line, event in self.history:
                name = getattr(event, "registrar", None)
                if name is not None and not isinstance(event, _DESK):
                    seen = self._last.get((name, event.pid), (0, 0))
                    self._last[name, event.pid] = (line, max(seen[1], event.hlc))
        return self._last

    def step(self, line: int, event: events.Event) -> None:
        name: str = getattr(event, "registrar")  # noqa: B009 - `walk` checked it
        if isinstance(event, _ENDING):
            self.ending(line, event, self.second.get((name, event.pid), name))
            return
        seq = getattr(event, "seq", 0)
        if (
            self.pids.get(name) == event.pid
            and (
                name not in self.over
                or 0 < seq < self.top.get(name, 0)
                or self.listed_before_end(event, self.now[name])
            )
            and not (self.second and (name, event.pid) in self.second)
            and not isinstance(event, events.CatalogRestored)
        ):  # (the life it is in goes on: most events; one built before its end, sent
            # after it by another thread; `server` would keep its name)
            going = self.now[name]
            going.last = max(going.last, event.hlc)
            going.last_line = line
            self.top[name] = max(self.top.get(name, 0), seq)
            self.steps.append((name, line, event, False, self.current[name]))
            return
        name, beside = self.server(line, event, name)
        stamp, pid = event.hlc, self.pids.get(name)
        if (
            pid is None
            or pid != event.pid
            or name in self.over
            or isinstance(event, events.CatalogRestored)
        ):
            life = self.current.get(name, -1) + 1
            record = self.now.get(name)
            if record is not None and record.end is None:
                record.end = stamp
            self.current[name] = life
            self.now[name] = self.lives[name, life] = Life(
                stamp, stamp, line, host=event.host, pid=event.pid, first_line=line, beside=beside
            )
            self.over.discard(name)
            self.top[name] = 0
            new = True
        else:
            life = self.current[name]
            record = self.now[name]
            record.last = max(record.last, stamp)
            record.last_line = line
            new = False
        self.pids[name] = event.pid
        self.top[name] = max(self.top.get(name, 0), seq)
        self.steps.append((name, line, event, new, life))

    @staticmethod
    def listed_before_end(event: events.Event, life: Life) -> bool:
        """Whether `event` is a listing begun before `life` ended: its caller's thread
        publishes it when the answer is back, which may be after the registrar's stop (a real
        `simways` run, load 15: db's status thread listed its queries, and the
        `ServerQueriesListed`, begun 1.6 ms before its `RegistrarStopped`, came after it)."""
        started = getattr(event, "started", 0) if isinstance(event, _LISTINGS) else 0
        return life.end is not None and 0 < started <= life.end

    def ending(self, line: int, event: events.Event, name: str) -> None:
        """A `StatusDelivered` or `StatusHandled` (in its life) or a `RegistrarStopped`
        (its life ends; from another process it begins one first: a restart without a
        backup that published nothing before its stop)."""
        stamp = event.hlc
        stopping = isinstance(event, events.RegistrarStopped)
        pid = self.pids.get(name)
        new = stopping and pid is not None and pid != event.pid
        record = self.now.get(name)
        if new or record is None:
            if record is not None and record.end is None:
                record.end = stamp
            self.current[name] = self.current.get(name, -1) + 1
            record = self.now[name] = self.lives[name, self.current[name]] = Life(
                stamp, stamp, line, host=event.host, pid=event.pid, first_line=line
            )
            self.over.discard(name)
            self.top[name] = 0
            if new:
                self.pids[name] = event.pid
        else:
            record.last = max(record.last, stamp)
            record.last_line = line
        if event.pid == self.pids.get(name):
            self.top[name] = max(self.top.get(name, 0), getattr(event, "seq", 0))
        if stopping:
            if record.end is None:
                record.end = stamp
            self.over.add(name)
        self.steps.append((name, line, event, new, self.current[name]))

    def server(
        self, line: int, event: events.Event, name: str
    ) -> tuple[str, tuple[str, int] | None]:
        """The registrar `event` is of (`<name>@<pid>` for a second server), and, at a
        second server's first event, the life it serves beside."""
        known = self.second.get((name, event.pid))
        if known is not None:
            return known, None
        pid = self.pids.get(name)
        if pid is None or pid == event.pid or name in self.over:
            return name, None
        line_then, stamp_then = self.last.get((name, pid), (0, 0))
        if line_then <= line or stamp_then <= event.hlc:
            return name, None  # (the one before serves no more: a restart)
        self.second[name, event.pid] = f"{name}@{event.pid}"
        return self.second[name, event.pid], (name, self.current[name])


_DESK = (events.StatusDelivered, events.StatusHandled)
"""Events a process's status desk publishes for a registrar, from any thread."""

_LISTINGS = (events.ServerQueriesListed, events.QueriesFetched)
"""Events a registrar's caller publishes when the answer is back (each `started` before it)."""

_ENDING = (events.StatusDelivered, events.StatusHandled, events.RegistrarStopped)
"""The events `_Walk.ending` takes: two that are in a life, and one that ends it."""


@dataclasses.dataclass
class Facts:
    """What the whole run says, wherever in it (query and status ids are UUIDs).

    Attributes:
        with_backup: registrars that published a `CatalogRestored`.
        forgets: (provider, query id) -> the stamps of its consumer's `QueryForgotten`s, in
            order (an id called again once forgotten is held anew).
        released: (provider, query id) -> `(unload_sent, reconciled)` of the first `QueryForgotten`
            if forgotten on the answer to its release.
        fatal: query id -> the line of the first `FATAL` its holder was told.
        fatal_at: query id -> the stamps of every `FATAL` its holder was told, in order (an id
            called again once forgotten may be lost again).
        added: query ids some provider added (`ConsumerAdded`, or a catalog's rows).
        held_at: query id -> (provider, resource id, line of its `ConsumerAdded` or row).
        held_on: query id -> `(stamp, provider, resource id, line)` of each of those, in order
            (a retry after a restart without a backup adds it to a new resource).
        parent: (consumer, query id) -> the consumer's resource it is a dependency of.
        sent: status id -> the query id it was sent about (its `StatusSent`).
        reported: (consumer, query id) told `FATAL` by its consumer itself (`REPORTED`).
        delivered: (status id, query id) of every `StatusDelivered`.
        last_delivery: status id -> the greatest stamp of its deliveries.
        lost: (provider, query id) its consumer reported lost itself (`REPORTED`).
        told_self: (line, consumer, query id) of each `QueryForgotten` of `REPORTED`.
        outcomes: query id -> `(stamp, held)` of each `CallAnswered` / `CallFailed`: whether
            its caller holds the id after it (answered, or a failed retry of the id it held
            since its last answer: it still holds it, `retry_failed`).
        fetched: (provider, query id) whose holdings `fetch` needs (listed by a fetch or a
            `ServerQueriesListed`, or answered at a provider fetched from).
        releasing: (consumer, query id) -> the stamp of the consumer's first restore that
            listed it as a dependency of a resource it was unloading (its release was
            committed before the kill, and may have reached its provider).
    """

    with_backup: set[str] = dataclasses.field(default_factory=set)
    forgets: dict[tuple[str, str], list[int]] = dataclasses.field(default_factory=dict)
    released: dict[tuple[str, str], tuple[int, int]] = dataclasses.field(default_factory=dict)
    fatal: dict[str, int] = dataclasses.field(default_factory=dict)
    fatal_at: dict[str, list[int]] = dataclasses.field(default_factory=dict)
    added: set[str] = dataclasses.field(default_factory=set)
    held_at: dict[str, tuple[str, str, int]] = dataclasses.field(default_factory=dict)
    held_on: dict[str, list[tuple[int, str, str, int]]] = dataclasses.field(default_factory=dict)
    parent: dict[tuple[str, str], str] = dataclasses.field(default_factory=dict)
    sent: dict[str, str] = dataclasses.field(default_factory=dict)
    reported: set[tuple[str, str]] = dataclasses.field(default_factory=set)
    delivered: set[tuple[str, str]] = dataclasses.field(default_factory=set)
    last_delivery: dict[str, int] = dataclasses.field(default_factory=dict)
    lost: set[tuple[str, str]] = dataclasses.field(default_factory=set)
    told_self: list[tuple[int, str, str]] = dataclasses.field(default_factory=list)
    outcomes: dict[str, list[tuple[int, bool]]] = dataclasses.field(default_factory=dict)
    fetched: set[tuple[str, str]] = dataclasses.field(default_factory=set)
    releasing: dict[tuple[str, str], int] = dataclasses.field(default_factory=dict)


def holder_at(facts: Facts, qid: str, stamp: int) -> tuple[str, str, int] | None:
    """Where `qid` was held at `stamp`: `(provider, resource id, line)` of its last
    `ConsumerAdded` (or row) before it, or of its first if none is before; `None` if no
    provider shows it."""
    held = facts.held_on.get(qid)
    if not held:
        return None
    before = [h for h in held if h[0] < stamp]
    _, provider, rid, line = before[-1] if before else held[0]
    return provider, rid, line


def gather(history: Sequence[Line]) -> Facts:  # noqa: PLR0912, PLR0915 - a branch per event kind
    """The `Facts` of a run, in one pass."""
    facts = Facts()
    answers: dict[tuple[str, str], list[str]] = {}  # (consumer, provider) -> ids answered
    fetchers: set[tuple[str, str]] = set()  # (consumer, provider) of each fetch
    listers: set[str] = set()  # providers that listed their own server's queries
    for line, event in history:
        if isinstance(event, events.ConsumerAdded):
            facts.added.add(event.query_id)
            facts.held_at.setdefault(event.query_id, (event.registrar, event.resource_id, line))
            facts.held_on.setdefault(event.query_id, []).append(
                (event.hlc, event.registrar, event.resource_id, line)
            )
        elif isinstance(event, events.StatusDelivered):
            if event.status is Status.FATAL:
                facts.fatal.setdefault(event.query_id, line)
                facts.fatal_at.setdefault(event.query_id, []).append(event.hlc)
            if event.status_id:
                facts.delivered.add((event.status_id, event.query_id))
                last = facts.last_delivery.get(event.status_id, event.hlc)
                facts.last_delivery[event.status_id] = max(last, event.hlc)
        elif isinstance(event, events.CallAnswered):
            if event.parent is not None:
                facts.parent[event.registrar, event.query_id] = event.parent
            facts.outcomes.setdefault(event.query_id, []).append((event.hlc, True))
            answers.setdefault((event.registrar, event.serving_rr), []).append(event.query_id)
        elif isinstance(event, events.QueriesFetched):
            fetchers.add((event.registrar, event.serving_rr))
            facts.fetched.update((event.serving_rr, qid) for qid in event.query_ids)
        elif isinstance(event, events.ServerQueriesListed):
            listers.add(event.registrar)
            facts.fetched.update((event.registrar, qid) for qid in event.query_ids)
        elif isinstance(event, events.CallFailed):
            calls = facts.outcomes.setdefault(event.query_id, [])
            calls.append((event.hlc, event.retry and bool(calls) and calls[-1][1]))
        elif isinstance(event, events.QueryForgotten):
            held = (event.serving_rr, event.query_id)
            stamps = facts.forgets.setdefault(held, [])
            stamps.append(event.hlc)
            if len(stamps) == 1 and event.unload_sent:
                facts.released[held] = (event.unload_sent, event.reconciled)
            if event.reason in REPORTED:
                facts.reported.add((event.registrar, event.query_id))
                facts.lost.add((event.serving_rr, event.query_id))
                facts.told_self.append((line, event.registrar, event.query_id))
        elif isinstance(event, events.StatusSent):
            if event.status_id:
                facts.sent[event.status_id] = event.query_id
        elif isinstance(event, events.CatalogRestored | events.RegistrarStopped):
            if isinstance(event, events.CatalogRestored):
                facts.with_backup.add(event.registrar)
                unloading = {row[0] for row in event.resources if row[2] == "unloading"}
                for qid, _serving, _server, parent, *_ in event.clients:
                    if parent in unloading:
                        facts.releasing.setdefault((event.registrar, qid), event.hlc)
            for qid, rid, *_ in event.consumers:
                facts.added.add(qid)
                facts.held_at.setdefault(qid, (event.registrar, rid, line))
                facts.held_on.setdefault(qid, []).append((event.hlc, event.registrar, rid, line))
            for qid, _serving, _server, parent, *_ in event.clients:
                if parent:
                    facts.parent[event.registrar, qid] = parent
    for consumer, provider in fetchers:
        facts.fetched.update((provider, qid) for qid in answers.get((consumer, provider), ()))
    if listers:
        facts.fetched.update(
            (provider, qid) for qid, (provider, *_) in facts.held_at.items() if provider in listers
        )
    return facts
