"""A verdict per run: check the semantic rules a run's events can show (events in, findings out).

```
 events.jsonl ──► read_runs ──► {run: [(line, event), ...]}
                                      │
              check(history) ─────────┴─► one function per rule ─► findings ─► Verdict
                                          (violation / unverifiable, each with the
                                           line numbers of the events that show it)
```

The rules checked (`docs/how-to/check-a-run.md` says what each means and what cannot be
checked):

- `held`: an acknowledged load (a `ConsumerAdded`) is held until it is released (a
  `ConsumerReleased`) or its consumer is told `FATAL`; a restart that loses it otherwise
  (a `CatalogRestored` without it, or a restart without a backup) is a violation, unless
  its consumer had forgotten it before (`QueryForgotten`): a release committed just
  before a kill has no `ConsumerReleased`, and the restore shows it.
- `unload-once`: a resource is unloaded at most once, and only once its last consumer
  id was released; no consumer is added to a resource after its unload.
- `dedup`: no two resources of equal requests (the same request digest) are live at once
  at a provider's server (requests of plain values only: others carry no digest); one
  its provider reported `FATAL` is not live for this (a new equal one loads beside it).
- `restore-first`: a registrar with a backup publishes `CatalogRestored` before any
  other event of each of its incarnations.
- `status-once`: a status send (its `status_id`) reaches each holder once per path.
- `status-path`: each delivery of a status is on a dependency path from its send: a
  direct consumer of the resource it was sent about (hop 1), or a consumer of a resource
  one of whose dependencies got it one hop before (the dependency's `CallAnswered.parent`).
- `answered`: from the consumer's side, an answered call (`CallAnswered`) is held until
  it is forgotten (`QueryForgotten`, with why) or listed when its registrar stops; it is
  not answered twice but as a retry; its provider added it (`ConsumerAdded`); nothing
  is forgotten that was not held.
- `end`: nothing is held at the end by a consumer that stopped (`RegistrarStopped`).
- `events`: no event was lost (an `EventsDropped`, a gap in a process's `seq`); a loss
  makes the findings about the registrars of that process unverifiable.

The checker re-synchronises a registrar's state at each `CatalogRestored`.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, Literal

from rr_actors import events
from rr_actors._types import Status
from rr_actors.errors import ConfigError
from rr_actors.events.lines import json_lines

__all__ = [
    "RULES",
    "Finding",
    "Verdict",
    "check",
    "check_file",
    "format_verdict",
    "read_runs",
]

Line = tuple[int, events.Event]
"""An event with its line number in `events.jsonl` (1 for the first line)."""

Kind = Literal["violation", "unverifiable"]

RULES = (
    "held",
    "unload-once",
    "dedup",
    "restore-first",
    "status-once",
    "status-path",
    "answered",
    "end",
    "events",
)
"""The rules `check` checks, by name (see the module docstring)."""


@dataclasses.dataclass(frozen=True)
class Finding:
    """One thing a run's events show against a rule, or keep from being checked.

    Attributes:
        rule: which rule (one of `RULES`).
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


@dataclasses.dataclass(frozen=True)
class Verdict:
    """A run's verdict: `"held"`, `"violated"` or `"unverifiable"`, with its findings.

    Attributes:
        verdict: `"violated"` if any finding is a violation, else `"unverifiable"` if any
            is unverifiable, else `"held"`.
        events: how many events were checked.
        findings: every finding, in the order of their first line.
    """

    verdict: str
    events: int
    findings: tuple[Finding, ...]

    @property
    def violations(self) -> int:
        """How many findings are violations."""
        return sum(f.kind == "violation" for f in self.findings)

    @property
    def unverifiable(self) -> int:
        """How many findings are unverifiable."""
        return sum(f.kind == "unverifiable" for f in self.findings)


# -- a registrar's state, as its events tell it ----------------------------------------------


@dataclasses.dataclass
class _Held:
    resource_id: str
    consumer: str
    line: int


@dataclasses.dataclass
class _Live:
    server: str
    digest: int | None
    line: int


@dataclasses.dataclass
class _Provider:
    """What the events say one provider registrar holds now."""

    pid: int | None = None
    held: dict[str, _Held] = dataclasses.field(default_factory=dict)
    live: dict[str, _Live] = dataclasses.field(default_factory=dict)
    unloaded: dict[str, int] = dataclasses.field(default_factory=dict)  # rid -> line
    restored: bool = False  # a CatalogRestored began the current incarnation


def _registrar_of(event: events.Event) -> str | None:
    return getattr(event, "registrar", None)


def _incarnations(history: Sequence[Line]) -> Iterator[tuple[str, int, events.Event, bool]]:
    """Each registrar event, with whether it begins a new incarnation of its registrar.

    A new incarnation begins at a `CatalogRestored`, at the first event of another
    process (a restarted manager process), or at the first event after a `ChildExited`
    of the registrar's own process (a restarted thread manager).
    """
    pids: dict[str, int] = {}
    exited: set[tuple[str, int]] = set()
    for line, event in history:
        if isinstance(event, events.ChildExited):
            exited.add((event.child, event.pid))
            continue
        name = _registrar_of(event)
        if name is None or isinstance(event, events.StatusDelivered | events.RegistrarStopped):
            if isinstance(event, events.RegistrarStopped):
                yield name or "", line, event, False
            continue
        pid = pids.get(name)
        new = (
            pid is None
            or pid != event.pid
            or (name, pid) in exited
            or isinstance(event, events.CatalogRestored)
        )
        if new:
            exited.discard((name, event.pid))
        pids[name] = event.pid
        yield name, line, event, new


def _forgotten(history: Sequence[Line]) -> dict[tuple[str, str], int]:
    """(provider, query id) -> line of the first `QueryForgotten` of it by its consumer."""
    forgot: dict[tuple[str, str], int] = {}
    for line, event in history:
        if isinstance(event, events.QueryForgotten):
            forgot.setdefault((event.serving_rr, event.query_id), line)
    return forgot


def _fatal_deliveries(history: Sequence[Line]) -> dict[str, int]:
    """Query id -> line of the first `FATAL` its holder was told (`StatusDelivered`)."""
    told: dict[str, int] = {}
    for line, event in history:
        if isinstance(event, events.StatusDelivered) and event.status is Status.FATAL:
            told.setdefault(event.query_id, line)
    return told


# -- the rules ---------------------------------------------------------------------------------


def _provider_rules(history: Sequence[Line]) -> list[Finding]:  # noqa: PLR0912, PLR0915
    """`held`, `unload-once`, `dedup` and `restore-first`: one pass over each provider."""
    findings: list[Finding] = []
    fatal = _fatal_deliveries(history)
    forgot = _forgotten(history)
    with_backup = {e.registrar for _, e in history if isinstance(e, events.CatalogRestored)}
    providers: dict[str, _Provider] = defaultdict(_Provider)

    def lose(name: str, state: _Provider, kept: set[str], line: int, why: str) -> None:
        for qid, held in state.held.items():
            if qid in kept:
                continue
            # its consumer had let it go: the release was committed, and the kill came
            # before its `ConsumerReleased` was published (the restore shows the commit)
            if forgot.get((name, qid), line) < line:
                continue
            told = fatal.get(qid)
            if told is None or told < held.line:
                findings.append(
                    Finding(
                        "held",
                        "violation",
                        f"{name}: query {qid[:8]} of {held.consumer} (resource "
                        f"{held.resource_id[:8]}) was lost {why}, neither released nor "
                        f"reported FATAL",
                        (held.line, line),
                        (name, held.consumer),
                    )
                )

    for name, line, event, new in _incarnations(history):
        state = providers[name]
        if isinstance(event, events.RegistrarStopped):
            continue
        if new:
            if name in with_backup and not isinstance(event, events.CatalogRestored):
                findings.append(
                    Finding(
                        "restore-first",
                        "violation",
                        f"{name} (pid {event.pid}) published {type(event).__name__} before "
                        f"its CatalogRestored",
                        (line,),
                        (name,),
                    )
                )
            if not isinstance(event, events.CatalogRestored) and state.pid is not None:
                lose(name, state, set(), line, "in a restart without a backup")
                state.held.clear()
                state.live.clear()
            state.pid = event.pid
        match event:
            case events.CatalogRestored():
                if not event.complete:
                    findings.append(
                        Finding(
                            "held",
                            "unverifiable",
                            f"{name} restored more rows than are listed ({event.counts})",
                            (line,),
                            (name,),
                        )
                    )
                    continue
                kept = {row[0] for row in event.consumers}
                lose(name, state, kept, line, "in a restore")
                state.held = {
                    qid: _Held(rid, consumer, state.held[qid].line if qid in state.held else line)
                    for qid, rid, consumer, *_ in event.consumers
                }
                state.live = {
                    row[0]: _Live(row[1], int(row[3]) if len(row) > 3 and row[3] else None, line)
                    for row in event.resources
                    if not (len(row) > 4 and row[4])  # reported FATAL: matched no more
                }
            case events.ResourceLoaded():
                if event.digest is not None:
                    for rid, live in state.live.items():
                        if live.server == event.server and live.digest == event.digest:
                            findings.append(
                                Finding(
                                    "dedup",
                                    "violation",
                                    f"{name}/{event.server}: equal requests loaded twice "
                                    f"({rid[:8]} still live when {event.resource_id[:8]} "
                                    f"loaded)",
                                    (live.line, line),
                                    (name,),
                                )
                            )
                            break
                state.live[event.resource_id] = _Live(event.server, event.digest, line)
            case events.LoadFailed():
                state.live.pop(event.resource_id, None)
            case events.StatusSent() if event.status is Status.FATAL:
                # dead: an equal request loads a new resource beside it (rule 1)
                dead = state.held.get(event.query_id)
                if dead is not None:
                    state.live.pop(dead.resource_id, None)
            case events.InDoubt():
                state.live.pop(event.query_id, None)
                for qid in [q for q, h in state.held.items() if h.resource_id == event.query_id]:
                    del state.held[qid]
            case events.ConsumerAdded():
                if event.resource_id in state.unloaded:
                    findings.append(
                        Finding(
                            "unload-once",
                            "violation",
                            f"{name}: {event.consumer} consumes {event.resource_id[:8]} "
                            f"(query {event.query_id[:8]}) after its unload",
                            (state.unloaded[event.resource_id], line),
                            (name, event.consumer),
                        )
                    )
                state.held[event.query_id] = _Held(event.resource_id, event.consumer, line)
            case events.ConsumerReleased():
                if state.held.pop(event.query_id, None) is None:
                    findings.append(
                        Finding(
                            "unload-once",
                            "violation",
                            f"{name}: query {event.query_id[:8]} of {event.consumer} released "
                            f"({event.reason}) but not held",
                            (line,),
                            (name, event.consumer),
                        )
                    )
            case events.ResourceUnloaded():
                rid = event.resource_id
                if rid in state.unloaded:
                    findings.append(
                        Finding(
                            "unload-once",
                            "violation",
                            f"{name}/{event.server}: {rid[:8]} unloaded twice",
                            (state.unloaded[rid], line),
                            (name,),
                        )
                    )
                holders = [(q, h) for q, h in state.held.items() if h.resource_id == rid]
                if holders:
                    qid, held = holders[0]
                    findings.append(
                        Finding(
                            "unload-once",
                            "violation",
                            f"{name}/{event.server}: {rid[:8]} unloaded while {held.consumer} "
                            f"still held it (query {qid[:8]})",
                            (held.line, line),
                            (name, held.consumer),
                        )
                    )
                state.unloaded[rid] = line
                state.live.pop(rid, None)
            case _:
                pass
    return findings


def _status_rule(history: Sequence[Line]) -> list[Finding]:
    """`status-once`: each status send reaches each holder once per path."""
    findings: list[Finding] = []
    seen: dict[tuple[str, str, str], int] = {}
    for line, event in history:
        if not isinstance(event, events.StatusDelivered) or not event.status_id:
            continue
        key = (event.status_id, event.registrar, event.query_id)
        first = seen.get(key)
        if first is not None:
            findings.append(
                Finding(
                    "status-once",
                    "violation",
                    f"{event.registrar}: status {event.status_id[:8]} ({event.status.name}) "
                    f"reached query {event.query_id[:8]} twice on one path",
                    (first, line),
                    (event.registrar,),
                )
            )
        else:
            seen[key] = line
    return findings


@dataclasses.dataclass
class _Paths:
    """Who holds what, from the whole run (ids are UUIDs: unique across registrars)."""

    held_at: dict[str, tuple[str, str, int]] = dataclasses.field(default_factory=dict)
    # query id -> (provider, resource id, line of the ConsumerAdded or restored row)
    parent: dict[tuple[str, str], str] = dataclasses.field(default_factory=dict)
    # (consumer, query id) -> the consumer's resource it is a dependency of
    sent: dict[str, str] = dataclasses.field(default_factory=dict)  # status id -> query id
    reported: set[tuple[str, str]] = dataclasses.field(default_factory=set)
    # (consumer, query id) told FATAL by its consumer itself (its provider lost it)


_REPORTED = ("provider lost", "unknown at reconcile")
"""`QueryForgotten` reasons whose `FATAL` the consumer delivers itself (no `StatusSent`)."""


def _paths(history: Sequence[Line]) -> _Paths:
    paths = _Paths()
    for line, event in history:
        match event:
            case events.ConsumerAdded():
                paths.held_at.setdefault(event.query_id, (event.registrar, event.resource_id, line))
            case events.CatalogRestored() | events.RegistrarStopped():
                for qid, rid, *_ in event.consumers:
                    paths.held_at.setdefault(qid, (event.registrar, rid, line))
                for qid, _serving, _server, parent, *_ in event.clients:
                    if parent:
                        paths.parent[event.registrar, qid] = parent
            case events.CallAnswered() if event.parent is not None:
                paths.parent[event.registrar, event.query_id] = event.parent
            case events.StatusSent() if event.status_id:
                paths.sent[event.status_id] = event.query_id
            case events.QueryForgotten() if event.reason in _REPORTED:
                paths.reported.add((event.registrar, event.query_id))
            case _:
                pass
    return paths


def _status_path_rule(history: Sequence[Line]) -> list[Finding]:
    """`status-path`: each delivery of a status is on a dependency path from its send."""
    paths = _paths(history)
    # (status id, registrar, hop) -> the resources of that registrar it climbed to
    climbed: dict[tuple[str, str, int], set[str]] = defaultdict(set)
    for _, event in history:
        if isinstance(event, events.StatusDelivered) and event.status_id:
            parent = paths.parent.get((event.registrar, event.query_id))
            if parent is not None:
                climbed[event.status_id, event.registrar, event.hop].add(parent)
    findings: list[Finding] = []
    for line, event in history:
        if not isinstance(event, events.StatusDelivered) or not event.status_id:
            continue
        holder = paths.held_at.get(event.query_id)
        if holder is None:
            continue  # (whose it is, the run does not say)
        provider, rid, added = holder
        message = _off_path(event, provider, rid, paths, climbed)
        if message is None:
            continue
        findings.append(
            Finding(
                "status-path",
                "violation",
                f"{event.registrar}: status {event.status_id[:8]} ({event.status.name}) "
                f"reached query "
                f"{event.query_id[:8]} at hop {event.hop} off any path: {message}",
                (added, line),
                (event.registrar, provider),
            )
        )
    return findings


def _off_path(
    event: events.StatusDelivered,
    provider: str,
    rid: str,
    paths: _Paths,
    climbed: dict[tuple[str, str, int], set[str]],
) -> str | None:
    """Why delivery `event` (of an id held at `provider`'s `rid`) is on no path, or `None`."""
    if event.hop > 1:
        if rid in climbed.get((event.status_id, provider, event.hop - 1), ()):
            return None
        return f"no dependency of {rid[:8]} got it at {provider} one hop before"
    if (event.registrar, event.query_id) in paths.reported:
        return None  # its consumer told it FATAL itself (rules 19, 20)
    about = paths.sent.get(event.status_id)
    if about is None:
        return f"no StatusSent at {provider}"
    if about in paths.held_at and paths.held_at[about][:2] != (provider, rid):
        return f"it was sent about {paths.held_at[about][1][:8]}, not {rid[:8]}"
    return None


def _answered_rule(history: Sequence[Line]) -> list[Finding]:
    """`answered`: the consumer's side of each call, against what it and its provider say."""
    findings: list[Finding] = []
    added = {
        qid
        for _, e in history
        if isinstance(e, events.CatalogRestored | events.RegistrarStopped)
        for qid, *_ in e.consumers
    }
    added |= {e.query_id for _, e in history if isinstance(e, events.ConsumerAdded)}
    held: dict[str, dict[str, int]] = defaultdict(dict)  # consumer -> answered id -> line
    restored: dict[str, set[str]] = defaultdict(set)  # consumer -> ids its restore listed

    def found(message: str, lines: tuple[int, ...], *registrars: str) -> None:
        findings.append(Finding("answered", "violation", message, lines, registrars))

    for name, line, event, new in _incarnations(history):
        if new:
            held[name].clear()
            restored[name].clear()
        match event:
            case events.CatalogRestored():
                restored[name] = {row[0] for row in event.clients}
            case events.CallAnswered():
                qid = event.query_id
                if qid in held[name] and not event.retry:
                    found(
                        f"{name}: call {qid[:8]} answered twice, not as a retry",
                        (held[name][qid], line),
                        name,
                    )
                if qid not in added:
                    found(
                        f"{name}: call {qid[:8]} answered, but {event.serving_rr} never "
                        f"added it (no ConsumerAdded)",
                        (line,),
                        name,
                        event.serving_rr,
                    )
                held[name].setdefault(qid, line)
            case events.QueryForgotten():
                qid = event.query_id
                if held[name].pop(qid, None) is None and qid not in restored[name]:
                    found(
                        f"{name}: query {qid[:8]} forgotten ({event.reason}) but not held",
                        (line,),
                        name,
                    )
                restored[name].discard(qid)
            case events.RegistrarStopped() if event.complete:
                listed = {row[0] for row in event.clients}
                for qid, at in held[name].items():
                    if qid not in listed:
                        found(
                            f"{name}: call {qid[:8]} answered, but at its stop neither "
                            f"forgotten nor listed",
                            (at, line),
                            name,
                        )
                held[name].clear()
            case _:
                pass
    return findings


def _end_rule(history: Sequence[Line]) -> list[Finding]:  # noqa: PLR0912 - one branch per event kind
    """`end`: at the end, no provider holds an id of a consumer that stopped."""
    stopped: dict[str, int] = {}  # consumer -> line of its (last) RegistrarStopped
    last_pid: dict[str, int] = {}
    exited: dict[tuple[str, int], int] = {}  # (child, pid) -> line of its ChildExited
    held: dict[str, dict[str, tuple[str, int]]] = defaultdict(dict)  # provider -> qid -> ...
    for line, event in history:
        if isinstance(event, events.ChildExited):
            exited.setdefault((event.child, event.pid), line)
        name = _registrar_of(event)
        if name is None:
            continue
        if isinstance(event, events.RegistrarStopped):
            stopped[name] = line
            for qid, _rid, consumer, *_ in event.consumers:
                held[name].setdefault(qid, (consumer, line))
            continue
        if last_pid.get(name) not in (None, event.pid):
            stopped.pop(name, None)  # it came back
        last_pid[name] = event.pid
        if isinstance(event, events.CatalogRestored):
            stopped.pop(name, None)
            held[name] = {qid: (c, line) for qid, _rid, c, *_ in event.consumers}
        elif isinstance(event, events.ConsumerAdded):
            held[name][event.query_id] = (event.consumer, line)
        elif isinstance(event, events.ConsumerReleased):
            held[name].pop(event.query_id, None)
        elif isinstance(event, events.InDoubt):
            pass
    findings = []
    for provider, ids in held.items():
        down = stopped.get(provider, exited.get((provider, last_pid.get(provider, -1))))
        for qid, (consumer, line) in ids.items():
            # a provider down when its consumer stopped is told at its next start (rule 12)
            up = consumer in stopped and (down is None or down > stopped[consumer])
            if up and consumer != provider:
                findings.append(
                    Finding(
                        "end",
                        "violation",
                        f"{provider} still holds query {qid[:8]} of {consumer}, which stopped",
                        (line, stopped[consumer]),
                        (provider, consumer),
                    )
                )
    return findings


def _loss_rule(history: Sequence[Line]) -> tuple[list[Finding], set[int]]:
    """`events`: every lost event (a notice, a gap in a process's numbers); the pids."""
    findings: list[Finding] = []
    lossy: set[int] = set()
    numbers: dict[int, list[tuple[int, int]]] = defaultdict(list)
    for line, event in history:
        if isinstance(event, events.EventsDropped):
            lossy.add(event.pid)
            why = " (it was killed before it sent them)" if event.cause == "killed" else ""
            findings.append(
                Finding(
                    "events",
                    "unverifiable",
                    f"{event.count} events lost in process {event.pid}{why}",
                    (line,),
                )
            )
        seq = getattr(event, "seq", 0)
        if seq:
            numbers[event.pid].append((seq, line))
    dropped = {line for line, e in history if isinstance(e, events.EventsDropped)}
    for pid, seen in numbers.items():
        seen.sort()
        for (a, la), (b, lb) in itertools.pairwise(seen):
            if b - a > 1 and not dropped.intersection(range(min(la, lb), max(la, lb) + 1)):
                lossy.add(pid)
                findings.append(
                    Finding(
                        "events",
                        "unverifiable",
                        f"{b - a - 1} events of process {pid} missing (seq {a + 1}..{b - 1})",
                        (la, lb),
                    )
                )
    return findings, lossy


def check(history: Sequence[Line]) -> Verdict:
    """Check one run's events against every rule of `RULES`.

    Args:
        history: the run's events in the order they were written, each with its line
            number (`read_runs` gives them).

    Returns:
        The verdict and every finding. A violation about a registrar whose process lost
        events counts as unverifiable (the lost events may explain it).
    """
    losses, lossy = _loss_rule(history)
    lossy_registrars = {
        _registrar_of(e) for _, e in history if e.pid in lossy and _registrar_of(e) is not None
    }
    found = [
        *_provider_rules(history),
        *_status_rule(history),
        *_status_path_rule(history),
        *_answered_rule(history),
        *_end_rule(history),
    ]
    findings = [
        dataclasses.replace(f, kind="unverifiable", message=f"{f.message} (events were lost)")
        if f.kind == "violation" and lossy_registrars.intersection(f.registrars)
        else f
        for f in found
    ]
    findings = sorted([*losses, *findings], key=lambda f: (min(f.lines, default=0), f.rule))
    if any(f.kind == "violation" for f in findings):
        verdict = "violated"
    elif findings:
        verdict = "unverifiable"
    else:
        verdict = "held"
    return Verdict(verdict, len(history), tuple(findings))


# -- reading and printing ----------------------------------------------------------------------


def read_runs(lines: Iterable[str]) -> dict[int, list[Line]]:
    """The events of each run of an `events.jsonl` (other lines, such as faults, skipped).

    Args:
        lines: the file's lines.

    Returns:
        Run number (the line's `"run"`, 0 without one) -> its events with line numbers.

    Raises:
        ConfigError: a line is not JSON, or an event line that cannot be read; the
            message names the line.
    """
    return _runs(_parsed(lines), "line")


def _parsed(lines: Iterable[str]) -> Iterator[tuple[int, Any]]:
    for number, text in enumerate(lines, start=1):
        if not text.strip():
            continue
        try:
            yield number, json.loads(text)
        except (json.JSONDecodeError, RecursionError) as exc:
            why = exc if isinstance(exc, json.JSONDecodeError) else "nested too deeply"
            raise ConfigError(f"line {number}: not JSON ({why})") from None


def _runs(numbered: Iterable[tuple[int, Any]], where: str) -> dict[int, list[Line]]:
    """The events of each run of `(line number, JSON value)` pairs; `where` names a line
    in errors (`"line"`, or `"<file> line"`)."""
    runs: dict[int, list[Line]] = defaultdict(list)
    for number, data in numbered:
        if not isinstance(data, dict) or "schema" not in data:
            continue  # a fault line
        run = data.pop("run", 0)
        data.pop("seed", None)
        if isinstance(run, bool) or not isinstance(run, int) or run < 0:
            raise ConfigError(f"{where} {number}: run must be an int >= 0, got {run!r}")
        try:
            event = events.from_dict(data)
        except ConfigError as exc:
            raise ConfigError(f"{where} {number}: {exc}") from None
        runs[run].append((number, event))
    return dict(runs)


def check_file(path: Path) -> dict[int, Verdict]:
    """Check every run of an `events.jsonl` file (or of a directory holding one).

    Raises:
        ConfigError: no such file, or it cannot be read, or a line that cannot be read
            (named with the file).
    """
    file = path / "events.jsonl" if path.is_dir() else path
    if not file.is_file():
        raise ConfigError(f"no events.jsonl at {path}")
    runs = _runs(json_lines(file), f"{file} line")
    return {run: check(history) for run, history in sorted(runs.items())}


def format_verdict(
    run: int, verdict: Verdict, show: Callable[[int], str] | None = None
) -> list[str]:
    """The lines `rr-actors check` prints for one run: each finding with its window.

    Args:
        run: the run's number.
        verdict: its verdict.
        show: `show(line_number)` gives the text of a line (`None`: numbers only).
    """
    out = [
        f"run {run}: {verdict.verdict} ({verdict.events} events, {verdict.violations} "
        f"violations, {verdict.unverifiable} unverifiable)"
    ]
    for finding in verdict.findings:
        out.append(f"  {finding.kind} [{finding.rule}] {finding.message}")
        for number in finding.lines:
            text = show(number) if show is not None else ""
            out.append(f"    line {number}: {text}".rstrip())
    return out
