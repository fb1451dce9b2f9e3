"""A verdict per run: check the semantic rules a run's events can show (events in, findings out).

```
 events.jsonl ──► read_runs ──► {run: [(line, event), ...]}
 a run's events, as published ──► numbered ──► the same, without the JSON (a simulated run)
                                      │
 check(history) ──────────────────────┴─► _history: each registrar's lives, the run's facts
     ├─► _provider_rules: one pass over each provider's catalog
     ├─► _status_rules: each status's deliveries, against who should have got it
     ├─► _consumer_rules: each consumer's calls, lost ids, rows left, fetches, outcomes
     ├─► _supervision_rules: give-ups, strategies, escalations, how lives end
     └─► events lost ──► findings (violation / unverifiable, each with the line
                         numbers of the events that show it) ──► Verdict
```

The rules (`RULES`), their windows and what cannot be checked: the table of
`docs/how-to/check-a-run.md`. Lines are compared within one registrar, clock stamps
(`hlc`) across registrars; every step is a dict lookup.
"""

from __future__ import annotations

import bisect
import dataclasses
import itertools
import reprlib
import tomllib
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from rr_actors import events
from rr_actors.errors import ConfigError
from rr_actors.events.lines import json_lines, parse_json
from rr_actors_lab.experiments import _consumer_rules, _status_rules, _supervision_rules
from rr_actors_lab.experiments._history import (
    Finding,
    Life,
    Line,
    gather,
    registrar_of,
    walk,
)
from rr_actors_lab.experiments._provider_rules import (
    Providers,
    dependency_held,
    doubt_reported,
    overload_paced,
    share_kept,
    share_needed,
    shed_needed,
    undigested,
    unload_order,
)

__all__ = [
    "RULES",
    "Finding",
    "Line",
    "Verdict",
    "check",
    "check_file",
    "format_verdict",
    "numbered",
    "read_runs",
]

RULES = (
    "kept",
    "unload-once",
    "no-leak",
    "one-resource",
    "release-match",
    "in-doubt",
    "dedup",
    "restore-first",
    "status-once",
    "status-reached",
    "status-path",
    "status-order",
    "status-answered",
    "status-patient",
    "answered",
    "answer-released",
    "record-kept",
    "reported-lost",
    "end",
    "withdrawn",
    "retry-ended",
    "retry-kept",
    "kept-unclaimed",
    "timed-out",
    "left",
    "unload-order",
    "dependency-held",
    "doubt-reported",
    "shed-needed",
    "overload-paced",
    "share-needed",
    "share-kept",
    "intensity",
    "strategy",
    "escalation",
    "one-name",
    "gone-told",
    "client-stopped",
    "fetch",
    "outcome",
    "life-end",
    "damaged-backup",
    "backup-readable",
    "events",
)
"""The rules `check` checks, by name (`docs/how-to/check-a-run.md` says what each means)."""


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


def _loss_rule(history: Sequence[Line]) -> tuple[list[Finding], set[int]]:
    """`events`: every lost event (a notice, a gap in a process's numbers no
    `EventsUnpublished` fills); the pids."""
    findings: list[Finding] = []
    lossy: set[int] = set()
    numbers: dict[int, list[tuple[int, int]]] = defaultdict(list)
    dropped: list[int] = []  # lines of the notices, in order
    unused: dict[int, set[int]] = defaultdict(set)  # numbers no event took, by pid
    for line, event in history:
        if isinstance(event, events.EventsUnpublished):
            unused[event.pid].update(event.seqs)
        if isinstance(event, events.EventsDropped):
            dropped.append(line)
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
    for pid, seen in numbers.items():
        seen.sort()
        for (a, la), (b, lb) in itertools.pairwise(seen):
            if b - a <= 1 or unused[pid].issuperset(range(a + 1, b)):
                continue  # (a number a killed process took for an event it never published)
            low, high = min(la, lb), max(la, lb)
            first = bisect.bisect_left(dropped, low)
            if first < len(dropped) and dropped[first] <= high:
                continue  # (a notice between them counted it)
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


KEEPS = {
    "first_served": "the one served later yields",
    "majority": "the one begun on a minority side yields (both on a majority side: the earlier)",
}
"""What each named rule 22 policy (`[hosts]`' `resolve`) keeps, as `one-name` words it."""


SERVICE = "rr_actors_lab.experiments.services:service"
"""The setup whose loads send on only requests a plan names (`uses_request`) or their own."""
PLAIN_FACTORIES = frozenset({"rr_actors_lab.experiments.services:long_request"})
"""The lab's factories whose requests are plain values (`plain_plan`)."""


def plain_plan(
    calls: Iterable[tuple[object, object]], managers: Iterable[tuple[object, Any]]
) -> bool:
    """Whether every request of a plan is a plain value (`check`'s `plain_requests`): its
    calls' `(request, factory)` TOML values without a factory (or one of `PLAIN_FACTORIES`),
    its managers' `(setup, options)` all `SERVICE`'s (another's requests are unknown), with
    TOML options (a `uses_request`); a date or time in any of them has no digest."""

    def plain(value: object) -> bool:
        if isinstance(value, list):
            return all(map(plain, value))
        if isinstance(value, dict):
            return all(map(plain, value.values()))
        return value is None or type(value) in (str, int, float, bool)

    calls_plain = (
        factory in PLAIN_FACTORIES or (factory is None and plain(request))
        for request, factory in calls
    )
    return all(calls_plain) and all(
        setup == SERVICE and plain(options) for setup, options in managers
    )


def _one_name_rule(
    history: Sequence[Line], lives: dict[tuple[str, int], Life], resolve: str
) -> list[Finding]:
    """`one-name` (rule 22): a second server of a name and the one it served beside do
    not both serve to the end of the run, whichever one `resolve` (the plan's policy)
    keeps. A life whose serving failed (its restart's `DuplicateNameError`, as a
    `permanent` registrar that yielded is restarted into the one kept) does not serve."""
    exits = {(e.child, e.pid): e.reason for _, e in history if isinstance(e, events.ChildExited)}
    refused = [  # (a restart into a name another serves: line, child, host)
        (line, e.child, e.host)
        for line, e in history
        if isinstance(e, events.ChildExited)
        and e.reason.startswith("failed to start")
        and "DuplicateNameError" in e.reason
    ]
    latest: dict[str, int] = {}
    for name, life in lives:
        latest[name] = max(latest.get(name, 0), life)

    def to_the_end(name: str) -> Life | None:
        """The last life of `name` if it served to the end of the run."""
        record = lives[name, latest[name]]
        child = name.partition("@")[0]
        reason = exits.get((child, record.pid))
        if any(
            line > record.first_line and c == child and h == record.host for line, c, h in refused
        ):
            return None  # (it began, and its serve failed: the name was another's)
        return record if reason in (None, "shutdown") else None

    keeps = KEEPS.get(resolve, f"resolve = {resolve!r} keeps one and the other yields")
    findings = []
    for (name, life), record in lives.items():
        if record.beside is None or latest[name] != life or to_the_end(name) is None:
            continue
        base = record.beside[0]
        other = to_the_end(base)  # (the one it served beside, or its restart)
        if other is None:
            continue
        findings.append(
            Finding(
                "one-name",
                "violation",
                f"two registrars {base} served to the end of the run: pid {other.pid}'s and "
                f"pid {record.pid}'s, begun while the other served (behind a cut); once it "
                f"healed, {keeps} (rule 22)",
                (other.first_line, record.first_line, record.last_line),
                (base, name),
            )
        )
    return findings


def check(
    history: Sequence[Line],
    resolve: str = "first_served",
    backoff_s: float = 0.0,
    timeouts: Mapping[str, float] | None = None,
    damaged: Mapping[int, str] | None = None,
    *,
    unreadable: Mapping[str, str] | None = None,
    heard_from_start: bool = True,
    plain_requests: bool = False,
) -> Verdict:
    """Check one run's events against every rule of `RULES`.

    Args:
        history: the run's events in the order they were written, each with its line
            number (`read_runs` gives them).
        resolve: the run's rule 22 policy (its plan's `[hosts]` `resolve`), as
            `one-name` says which registrar of a name yields at a heal.
        backoff_s: the longest delay before a restart the run's plan allows (its
            supervisors' `backoff` `max`, 0 without a backoff), in seconds: `strategy`
            waits that much longer for a restart due.
        timeouts: the `call_timeout` of consumers by name (its plan's clients' and managers'), in
            seconds: how long a restored id kept for a retry of theirs waits for it
            (`kept-unclaimed` judges those consumers only, `timed-out` those of them that
            are no child of a supervisor; no event carries it).
        damaged: the backups the run's faults damaged between two lives (`corrupt_backup`):
            the pid of the manager process killed first -> how (`damaged-backup` judges
            its restarts; no event carries it).
        unreadable: the backups the run left that `read_backup` refuses: manager -> why
            (`backup-readable` judges them; no event carries it: simulated runs).
        heard_from_start: whether the history begins before the tree's start (`False`: its
            plan's `listen = "after_start"`, each registrar's first life heard from after its
            start, so `restore-first` does not judge that life's first event).
        plain_requests: whether every request of the run is a plain value (`plain_plan`:
            its plan's TOML requests, no factory): `dedup` then wants each load's digest.

    Returns:
        The verdict and every finding. A violation about a registrar whose process lost
        events counts as unverifiable (the lost events may explain it).
    """
    losses, lossy = _loss_rule(history)
    lossy_registrars = {
        name for _, e in history if e.pid in lossy and (name := registrar_of(e)) is not None
    }
    steps, lives = walk(history)
    managers = {e.child for _, e in history if isinstance(e, events.ChildStarted)}
    facts = gather(history)
    damage, refusals, lost_backups = _supervision_rules.damaged_backup(history, damaged or {})
    providers = Providers(facts, lives, lost_backups, heard_from_start=heard_from_start)
    providers.run(steps)
    wanted = {(want.holder, want.query_id) for want in providers.expected}
    answered, spans = _consumer_rules.answered(steps, facts, wanted)
    due_s = _supervision_rules.DUE_S + backoff_s
    strategy, escalation = _supervision_rules.strategy(history, due_s)
    found = [
        *providers.findings,
        *_status_rules.status_once(history),
        *_status_rules.status_reached(providers.expected, facts, spans, lives, history, steps),
        *_status_rules.status_path(history, facts),
        *_status_rules.status_order(history),
        *_status_rules.status_answered(history),
        *_status_rules.status_patient(history),
        *answered,
        *_consumer_rules.answer_released(history),
        *_consumer_rules.record_kept(steps, history),
        *_consumer_rules.reported_lost(history, providers.holdings, lives),
        *_consumer_rules.end(steps, history),
        *_consumer_rules.withdrawn(steps),
        *_consumer_rules.retry_ended(steps),
        *_consumer_rules.retry_kept(steps),
        *_consumer_rules.kept_unclaimed(steps, lives, timeouts or {}),
        *_consumer_rules.timed_out(steps, timeouts or {}, managers),
        *_consumer_rules.left(steps, history, lives),
        *_consumer_rules.fetch(steps, providers.holdings, lives),
        *_consumer_rules.outcome(steps, lives, history),
        *unload_order(steps),
        *dependency_held(steps),
        *doubt_reported(steps),
        *shed_needed(history),
        *overload_paced(steps),
        *share_needed(steps),
        *share_kept(steps),
        *_supervision_rules.intensity(history),
        *strategy,
        *escalation,
        *_supervision_rules.life_end(history, refusals),
        *damage,
        *_supervision_rules.backup_readable(history, unreadable or {}, damaged=bool(damaged)),
        *_one_name_rule(history, lives, resolve),
        *(undigested(history) if plain_requests else ()),
        *_consumer_rules.gone_told(history, steps),
        *_consumer_rules.client_stopped(steps, timeouts or {}, managers),
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


def numbered(seen: Iterable[events.Event]) -> list[Line]:
    """One run's events as published, numbered as the lines of its `events.jsonl` would be (1
    first), their rows checked as `read_runs` checks them: the same verdict, no JSON.

    Raises:
        ConfigError: a catalog event's row too short, or a digest not a number; names the line.
    """
    history = list(enumerate(seen, start=1))
    for number, event in history:
        if isinstance(event, _CATALOG):  # (the others have no rows: no call for them)
            try:
                _check_rows(event)
            except ConfigError as exc:
                raise ConfigError(f"line {number}: {exc}") from None
    return history


def _parsed(lines: Iterable[str]) -> Iterator[tuple[int, Any]]:
    for number, text in enumerate(lines, start=1):
        if text.strip():
            yield number, parse_json(text, f"line {number}")


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
            raise ConfigError(f"{where} {number}: run must be an int >= 0, got {reprlib.repr(run)}")
        try:
            event = events.from_dict(data)
            _check_rows(event)
        except ConfigError as exc:
            raise ConfigError(f"{where} {number}: {exc}") from None
        runs[run].append((number, event))
    return dict(runs)


_CATALOG = (events.CatalogRestored, events.RegistrarStopped)
"""The kinds with rows (`_check_rows`)."""

_ROW_FIELDS = {"resources": 3, "consumers": 3, "clients": 4}
"""The fields a row of a catalog event has at least (its kind's docstring names them)."""


def _check_rows(event: events.Event) -> None:
    """A catalog event's rows are as wide as the rules read them, and its digests numbers.

    Raises:
        ConfigError: a short row, or a digest not a whole number of at most 40 digits.
    """
    if not isinstance(event, _CATALOG):
        return
    kind = type(event).__name__
    for field, least in _ROW_FIELDS.items():
        for row in getattr(event, field):
            if len(row) < least:
                raise ConfigError(
                    f"{kind}.{field}: a row of fewer than {least} fields: {reprlib.repr(row)}"
                )
    for row in event.resources:
        digest = row[3] if len(row) > 3 else ""
        if digest and not (len(digest) <= 40 and digest.lstrip("-").isdecimal()):
            raise ConfigError(
                f"{kind}.resources: a digest that is not a whole number: {reprlib.repr(row)}"
            )


def check_file(path: Path, *, heard_from_start: bool | None = None) -> dict[int, Verdict]:
    """Check every run of an `events.jsonl` file (or of a directory holding one).

    `heard_from_start`: `check`'s (`None`: from the `listen` of the plan copied beside it).

    Raises:
        ConfigError: no such file, or it cannot be read, or a line that cannot be read
            (named with the file).
    """
    file = path / "events.jsonl" if path.is_dir() else path
    if not file.is_file():
        if (path / "seeds.jsonl").is_file():
            raise ConfigError(
                f"no events.jsonl at {path}: it is a simulation's output; its seeds.jsonl "
                f"says each seed's verdict, and `rr-actors replay {path} --seed S` re-runs one"
            )
        raise ConfigError(f"no events.jsonl at {path}")
    runs = _runs(json_lines(file), f"{file} line")
    plan = _plan_beside(file)
    resolve, backoff_s = _resolve_of(plan), _backoff_of(plan.get("tree"))
    heard = plan.get("listen") != "after_start" if heard_from_start is None else heard_from_start
    workload = plan.get("workload", {})
    plain = bool(plan) and plain_plan(
        ((c.get("request", "{key}"), c.get("factory")) for c in workload.get("calls", [])),
        ((m.get("setup"), m.get("options", {})) for m in _managers_of(plan.get("tree", {}))),
    )
    return {
        run: check(history, resolve, backoff_s, heard_from_start=heard, plain_requests=plain)
        for run, history in sorted(runs.items())
    }


def _managers_of(tree: dict[str, Any]) -> Iterator[dict[str, Any]]:
    """The managers of a plan's TOML `[tree]` (a child with a `setup`), depth first."""
    for child in tree.get("children", []):
        if "setup" in child:
            yield child
        else:
            yield from _managers_of(child)


def _plan_beside(file: Path) -> dict[str, Any]:
    """The plan copied beside `file` (its `plan.toml`), as TOML data; `{}` without one: its
    `listen` then `"before_start"`, and the defaults below."""
    try:
        return tomllib.loads((file.parent / "plan.toml").read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return {}


def _resolve_of(plan: dict[str, Any]) -> str:
    """The rule 22 policy of a plan's TOML data (its `[hosts]` `resolve`); `"first_served"`,
    the default, without one that says it."""
    hosts = plan.get("hosts", {})
    resolve = hosts.get("resolve") if isinstance(hosts, dict) else None
    return resolve if isinstance(resolve, str) and resolve else "first_served"


def _backoff_of(tree: object) -> float:
    """The longest restart backoff (`max`, seconds) of a plan's `tree` table and every
    supervisor nested in it, as TOML data; 0.0 where none waits (`initial` 0, the default)."""
    if not isinstance(tree, dict):
        return 0.0
    backoff = tree.get("backoff")
    longest = 0.0
    if isinstance(backoff, dict) and _number(backoff.get("initial", 0.0)) > 0:
        longest = _number(backoff.get("max", 30.0))
    children = tree.get("children", [])
    nested = (_backoff_of(c) for c in children) if isinstance(children, list) else ()
    return max(longest, *nested, 0.0)


def _number(value: object) -> float:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else 0.0


def format_verdict(
    run: int, verdict: Verdict, show: Callable[[int], str] | None = None
) -> list[str]:
    """The lines `rr-actors check` prints for one run: each finding with its window.

    Args:
        run: the run's number.
        verdict: its verdict.
        show: `show(line_number)` gives the text of a line (`None`: numbers only, each
            `line N` with nothing after it).
    """
    out = [
        f"run {run}: {verdict.verdict} ({verdict.events} events, {verdict.violations} "
        f"violations, {verdict.unverifiable} unverifiable)"
    ]
    for finding in verdict.findings:
        out.append(f"  {finding.kind} [{finding.rule}] {finding.message}")
        for number in finding.lines:
            text = show(number) if show is not None else ""
            out.append(f"    line {number}: {text}".rstrip() if text else f"    line {number}")
    return out
