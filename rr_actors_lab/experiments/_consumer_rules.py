"""The consumer's side of a run (rules `answered`, `answer-released`, `record-kept`,
`reported-lost`, `end`, `withdrawn`, `retry-ended`, `retry-kept`, `kept-unclaimed`,
`timed-out`, `left`, `fetch`, `outcome`, `gone-told`, `client-stopped`).

```
 steps ──► answered: each consumer's answered calls against what its providers added
 history ──► answer_released: answers recorded after their provider's reconcile released them
 steps ──► record_kept: what a consumer recorded against what its next restore lists
 QueryForgotten + the provider pass's holdings ──► reported_lost
 steps (+ the history's exits) ──► end: what providers still hold for stopped consumers
 steps ──► withdrawn: what providers still hold of withdrawn calls
 steps ──► retry-ended: what providers still hold of failed calls whose load ended
 steps ──► retry-kept: a failed call's id released while its consumer could retry it
 steps + lives ──► kept-unclaimed: a failed call's id kept past its consumer's call_timeout
 steps ──► timed-out: a client's call withdrawn at its timeout, against its first start
 steps (+ the give-ups) ──► left: a last stop's rows no running consumer holds
 steps + holdings ──► fetch: QueriesFetched, ServerQueriesListed against what was held
 steps + lives (+ the exits) ──► outcome: each call a provider added against its caller's end
 history's losses for good + steps ──► gone_told: a life begun after them forgets, not releases
 steps ──► client_stopped: each client of the plan's last life ends in its RegistrarStopped
```

Each rule's windows and what it excuses: docs/how-to/check-a-run.md.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Collection, Mapping, Sequence

from rr_actors import events
from rr_actors._core import hlc
from rr_actors_lab.experiments._history import (
    REPORTED,
    Facts,
    Finding,
    Life,
    Line,
    Step,
    registrar_of,
)
from rr_actors_lab.experiments._provider_rules import Holding
from rr_actors_lab.experiments._status_rules import Span

__all__ = [
    "CALL_BOUND_S",
    "TIMED_OUT_SLACK_S",
    "WITHDRAWN_BOUND_S",
    "answer_released",
    "answered",
    "end",
    "fetch",
    "kept_unclaimed",
    "left",
    "outcome",
    "record_kept",
    "reported_lost",
    "retry_ended",
    "retry_kept",
    "timed_out",
    "withdrawn",
]

_SHOWN = 3
"""Rows of a `left` finding whose first line its window shows (besides the stop's)."""


def answered(  # noqa: PLR0912 - one branch per event kind
    steps: Sequence[Step], facts: Facts, wanted: Collection[tuple[str, str]]
) -> tuple[list[Finding], dict[tuple[str, str], list[Span]]]:
    """`answered`: each call's consumer side against its provider; the findings, and the spans
    each (consumer, query id) of `wanted` held it in (`status-reached`)."""
    findings: list[Finding] = []
    held: dict[str, dict[str, int]] = defaultdict(dict)  # consumer -> answered id -> line
    restored: dict[str, dict[str, int]] = defaultdict(dict)  # consumer -> restored id -> line
    spans: dict[tuple[str, str], list[Span]] = defaultdict(list)

    def found(message: str, lines: tuple[int, ...], *registrars: str) -> None:
        findings.append(Finding("answered", "violation", message, lines, registrars))

    def began(name: str, qid: str, life: int, stamp: int) -> None:
        key = (name, qid)
        if key in wanted:
            kept = spans[key]
            if not kept or kept[-1][0] != life or kept[-1][2] is not None:
                kept.append((life, stamp, None, 0))

    def ended(name: str, qid: str, stamp: int, line: int) -> None:
        key = (name, qid)
        if key in wanted and spans.get(key) and spans[key][-1][2] is None:
            life, since, _, _ = spans[key][-1]
            spans[key][-1] = (life, since, stamp, line)

    for name, line, event, new, life in steps:
        if new:
            held[name].clear()
            restored[name].clear()
        if isinstance(event, events.CatalogRestored):
            restored[name] = {row[0]: line for row in event.clients}
            for qid in restored[name]:
                began(name, qid, life, event.hlc)
        elif isinstance(event, events.CallAnswered):
            qid = event.query_id
            if qid in held[name] and not event.retry:
                found(
                    f"{name}: call {qid[:8]} answered twice, not as a retry",
                    (held[name][qid], line),
                    name,
                )
            if qid not in facts.added:
                found(
                    f"{name}: call {qid[:8]} answered, but {event.serving_rr} never added "
                    f"it (no ConsumerAdded)",
                    (line,),
                    name,
                    event.serving_rr,
                )
            held[name].setdefault(qid, line)
            began(name, qid, life, event.hlc)
        elif isinstance(event, events.QueryForgotten):
            qid = event.query_id
            if held[name].pop(qid, None) is None and qid not in restored[name]:
                found(
                    f"{name}: query {qid[:8]} forgotten ({event.reason}) but not held",
                    (line,),
                    name,
                )
            restored[name].pop(qid, None)
            ended(name, qid, event.hlc, line)
        elif isinstance(event, events.RegistrarStopped) and event.complete:
            listed = {row[0] for row in event.clients}
            for how, ids in (("answered", held[name]), ("restored", restored[name])):
                for qid, at in ids.items():
                    if qid not in listed:
                        found(
                            f"{name}: call {qid[:8]} {how}, but at its stop neither "
                            f"forgotten nor listed",
                            (at, line),
                            name,
                        )
            held[name].clear()
            restored[name].clear()
    return findings, spans


def answer_released(history: Sequence[Line]) -> list[Finding]:
    """`answer-released`: no consumer records an answer (`CallAnswered`) of an id its
    provider's reconcile had released (`ConsumerReleased` of reason `"reconcile"`, stamped
    before the answer) unless that provider added it again since (a retry that loaded
    afresh, its `ConsumerAdded` between the two stamps). A `Reconcile` lists every call whose
    answer is on its way (rule 20), so its provider never gives back an id its consumer is
    about to hold: the consumer would hold an id nobody serves (issue 68 item 7)."""
    # (consumer, query id, provider) -> the stamps and lines of its releases; its adds' stamps
    released: dict[tuple[str, str, str], list[tuple[int, int]]] = defaultdict(list)
    added: dict[tuple[str, str, str], list[int]] = defaultdict(list)
    answers: list[tuple[int, events.CallAnswered]] = []
    for line, event in history:
        if isinstance(event, events.ConsumerReleased) and event.reason == "reconcile":
            released[event.consumer, event.query_id, event.registrar].append((event.hlc, line))
        elif isinstance(event, events.ConsumerAdded):
            added[event.consumer, event.query_id, event.registrar].append(event.hlc)
        elif isinstance(event, events.CallAnswered):
            answers.append((line, event))
    findings = []
    for line, answer in answers:
        key = (answer.registrar, answer.query_id, answer.serving_rr)
        before = [(s, at) for s, at in released.get(key, ()) if 0 < s < answer.hlc]
        if not before:
            continue
        stamp, at = max(before)  # (the last release before it: added again since?)
        if any(stamp < again < answer.hlc for again in added.get(key, ())):
            continue
        findings.append(
            Finding(
                "answer-released",
                "violation",
                f"{answer.registrar}: call {answer.query_id[:8]} answered after "
                f"{answer.serving_rr}'s reconcile released it (its Reconcile left out a call "
                f"whose answer was on its way): it holds an id nobody serves (rule 20)",
                (at, line),
                (answer.registrar, answer.serving_rr),
            )
        )
    return findings


def record_kept(steps: Sequence[Step], history: Sequence[Line]) -> list[Finding]:
    """`record-kept` (rule 14, the consumer's side): a consumer with a backup keeps what it
    recorded. Its restore (a `CatalogRestored` that lists its rows) lists every id whose
    answer its life before recorded (`CallAnswered`, published once the record is committed)
    and had not forgotten (`QueryForgotten`); nor does that life hand back `in doubt` such
    an id of a top-level call (restored without a parent: `in doubt` is for a pending record
    of an older backup, or an orphaned dependency, not judged). Excused: an id its provider
    released before the restore (`ConsumerReleased` stamped before it: a release whose
    forget was committed just before the kill), and a dependency whose parent the restore
    lists `unloading` (rule 12: its release, under way, may have been committed and its
    events killed with the program before they left)."""
    released: dict[tuple[str, str], int] = {}  # (consumer, query id) -> first release stamp
    for _, event in history:
        if isinstance(event, events.ConsumerReleased):
            key = (event.consumer, event.query_id)
            released[key] = min(released.get(key, event.hlc), event.hlc)
    held: dict[str, dict[str, int]] = defaultdict(dict)  # consumer -> recorded id -> line
    parents: dict[tuple[str, str], str] = {}  # (consumer, recorded id) -> its parent resource
    kept: dict[str, dict[str, tuple[int, int]]] = defaultdict(dict)  # restored: -> (at, line)
    findings: list[Finding] = []

    def lost(name: str, qid: str, at: int, line: int, how: str) -> None:
        findings.append(
            Finding(
                "record-kept",
                "violation",
                f"{name}: call {qid[:8]} recorded, {how} (its record's write was lost: rule 14)",
                (at, line),
                (name,),
            )
        )

    for name, line, event, _new, _life in steps:
        if isinstance(event, events.CatalogRestored):
            kept[name] = {}
            if event.complete:
                listed = {row[0]: row for row in event.clients}
                unloading = {row[0] for row in event.resources if row[2] == "unloading"}
                for qid, at in held[name].items():
                    gone = released.get((base(name), qid))
                    parent = parents.get((name, qid))  # (its unload releases it: rule 12)
                    excused = bool(gone and 0 < gone < event.hlc) or parent in unloading
                    if qid not in listed and not excused:
                        lost(name, qid, at, line, "not forgotten, but its next restore lacks it")
                    elif qid in listed and not listed[qid][3]:  # (a top-level call's)
                        kept[name][qid] = (at, line)
            held[name] = {}
        elif isinstance(event, events.CallAnswered):
            held[name].setdefault(event.query_id, line)
            kept[name].pop(event.query_id, None)
            parents[name, event.query_id] = event.parent or ""
        elif isinstance(event, events.QueryForgotten):
            held[name].pop(event.query_id, None)
            restored = kept[name].pop(event.query_id, None)
            if event.reason == "in doubt" and restored is not None:
                lost(name, event.query_id, restored[0], line, "restored, then handed back in doubt")
    return findings


def base(name: str) -> str:
    """A registrar's name without a second server's `@pid` (its events' own name)."""
    return name.partition("@")[0]


def reported_lost(
    history: Sequence[Line],
    holdings: dict[tuple[str, str], list[Holding]],
    lives: dict[tuple[str, int], Life],
) -> list[Finding]:
    """`reported-lost`: a consumer tells itself `FATAL` for an id only if its provider lost it.

    `unknown at reconcile` (rule 20): the provider's life that answered had not added it, or
    had released it. `provider lost` (rule 19): the life that held it died; one seen alive
    after on the same host was not lost (across hosts a cut counts as lost), unless it let the
    id go at its reconcile with the consumer; nor was one whose next life, on the same host,
    restored it held for that consumer (its supervisor restarted it: rule 19's other half).
    """
    reconciled: set[tuple[str, str, str, int]] = {
        (e.registrar, e.consumer, e.query_id, e.hlc)
        for _, e in history
        if isinstance(e, events.ConsumerReleased) and e.reason == "reconcile"
    }
    restores = {line: e for line, e in history if isinstance(e, events.CatalogRestored)}
    by_name: dict[str, list[Life]] = defaultdict(list)  # name -> its lives, in order
    for (name, _), life in sorted(lives.items()):
        by_name[name].append(life)
    findings: list[Finding] = []
    seconds: dict[str, list[Life]] = defaultdict(list)  # name -> lives of second servers
    for life in lives.values():
        if life.beside is not None:
            seconds[life.beside[0]].append(life)
    for line, event in history:
        if not isinstance(event, events.QueryForgotten) or event.reason not in REPORTED:
            continue
        provider, qid, stamp = event.serving_rr, event.query_id, event.hlc
        if any(s.start <= stamp and not s.ended_before(stamp) for s in seconds[provider]):
            continue  # (two served the name, behind a cut: either may have answered)
        back = _restored(line, event, by_name[provider], restores)
        if back is not None:
            findings.append(back)
            continue
        for holding in holdings.get((provider, qid), ()):
            if holding.since >= stamp or (holding.until is not None and holding.until <= stamp):
                continue
            life = lives[provider, holding.life]
            if life.ended_before(stamp):
                continue
            if event.reason == "provider lost" and not (
                life.last > stamp and life.host and life.host == event.host
            ):
                continue
            if event.reason == "provider lost" and (
                (provider, event.registrar, qid, holding.until) in reconciled
            ):
                continue  # (behind a cut: reconciled once heard again)
            findings.append(
                Finding(
                    "reported-lost",
                    "violation",
                    f"{event.registrar}: query {qid[:8]} told FATAL ({event.reason}) and "
                    f"forgotten, but {provider} held it (added in its life that "
                    f"{'answered' if event.reason != 'provider lost' else 'ran on'}, not "
                    f"released)",
                    (holding.line, line),
                    (event.registrar, provider),
                )
            )
            break
    return findings


def _restored(
    line: int,
    event: events.QueryForgotten,
    lives: Sequence[Life],
    restores: Mapping[int, events.CatalogRestored],
) -> Finding | None:
    """`reported-lost`'s other half of rule 19 (a provider its supervisor restarts is not
    lost): a `provider lost` whose provider's life then (or next: a new process's first
    stamps may be below the consumer's) began by restoring the id held for that consumer,
    on its host."""
    if event.reason != "provider lost":
        return None
    now = next((life for life in lives if not life.ended_before(event.hlc)), None)
    back = None if now is None or now.beside else restores.get(now.first_line)
    if now is None or back is None or back.host != event.host:
        return None
    if not any(row[0] == event.query_id and row[2] == event.registrar for row in back.consumers):
        return None
    return Finding(
        "reported-lost",
        "violation",
        f"{event.registrar}: query {event.query_id[:8]} told FATAL (provider lost) and "
        f"forgotten, but {event.serving_rr} came back and restored it (restarted by its "
        f"supervisor: not lost, rule 19)",
        (line, now.first_line),
        (event.registrar, event.serving_rr),
    )


def end(steps: Sequence[Step], history: Sequence[Line]) -> list[Finding]:
    """`end`: at the end, no provider holds an id of a consumer that stopped, or that was lost
    for good (rule 19: its last life ended in a `ChildExited` and no life of it began after)
    before the provider's last stop or exit (life by life: a new life holds what its
    `CatalogRestored` lists, or nothing)."""
    stopped: dict[str, int] = {}  # consumer -> line of its (last) RegistrarStopped
    last_pid: dict[str, int] = {}
    exited: dict[tuple[str, int], int] = {}  # (child, pid) -> line of its ChildExited
    for line, event in history:
        if isinstance(event, events.ChildExited):
            exited.setdefault((event.child, event.pid), line)
    held: dict[str, dict[str, tuple[str, int]]] = defaultdict(dict)  # provider -> qid -> ...
    for name, line, event, new, _life in steps:
        if new:
            stopped.pop(name, None)  # it came back
            held[name].clear()  # (a restore lists what it holds again)
        if isinstance(event, events.RegistrarStopped):
            stopped[name] = line
            for qid, _rid, consumer, *_ in event.consumers:
                held[name].setdefault(qid, (consumer, line))
            continue
        last_pid[name] = event.pid
        if isinstance(event, events.CatalogRestored):
            held[name] = {qid: (c, line) for qid, _rid, c, *_ in event.consumers}
        elif isinstance(event, events.ConsumerAdded):
            held[name][event.query_id] = (event.consumer, line)
        elif isinstance(event, events.ConsumerReleased):
            held[name].pop(event.query_id, None)
    gone = {  # consumer -> the line it stopped at, or was lost for good at (its last exit)
        **{name: exited[name, pid] for name, pid in last_pid.items() if (name, pid) in exited},
        **stopped,
    }
    findings = []
    for provider, ids in held.items():
        down = stopped.get(provider, exited.get((provider, last_pid.get(provider, -1))))
        for qid, (consumer, line) in ids.items():
            # a provider down when its consumer stopped is told at its next start (rule 12),
            # or when it was lost (rule 19: at that start, as each lost since)
            up = consumer in gone and (down is None or down > gone[consumer])
            if up and consumer != provider:
                how = "stopped" if consumer in stopped else "was lost for good"
                findings.append(
                    Finding(
                        "end",
                        "violation",
                        f"{provider} still holds query {qid[:8]} of {consumer}, which {how}",
                        (line, gone[consumer]),
                        (provider, consumer),
                    )
                )
    return findings


Held = tuple[str, int, float, float]
"""A span a provider's life held an id: (its consumer, the line it began, since, until)."""

WITHDRAWN_BOUND_S = 1.0
"""Seconds by which a provider has released a withdrawn id it holds, counted from the
withdrawal or from when that life of the provider began to hold it, whichever is later
(its `Abandon`, or the reconcile after its restart, takes milliseconds)."""


def withdrawn(steps: Sequence[Step]) -> list[Finding]:
    """`withdrawn` (rules 17, 20): a call its consumer withdrew leaves nothing held, and
    gives back nothing held before it.

    A `CallWithdrawn` not answered later (a retry) is released by its `Abandon` or at the
    restarted provider's reconcile; a provider's life holding it `WITHDRAWN_BOUND_S` after
    the withdrawal (wall clock `at`) is a violation. A withdrawn retry of an id its consumer
    holds (answered or restored, not forgotten since; not at its stop) leaves it held: its
    provider's next release of it `"abandoned"`, or its consumer's next forget of it
    `"withdrawn"`, is a violation; one the retry added there again (the provider had lost
    it) is judged as a withdrawal, its consumer told `FATAL` (rule 20: `reported-lost`).
    """
    called: dict[tuple[str, str], tuple[int, float, str]] = {}  # (consumer, id) -> ...
    held: set[tuple[str, str]] = set()  # (consumer, id) answered, not forgotten since
    added: set[tuple[str, str]] = set()  # of those, added at the provider again since
    retried: dict[tuple[str, str], int] = {}  # (consumer, id) -> its withdrawn retry's line
    findings = []
    for name, line, event, new, _life in steps:
        if new:
            held -= {key for key in held if key[0] == name}
        key = (name, getattr(event, "query_id", ""))
        if isinstance(event, events.CatalogRestored):
            held.update((name, row[0]) for row in event.clients)
        elif isinstance(event, events.CallWithdrawn):
            if key in held - added and event.reason != "registrar stopped":
                retried[key] = line  # (a retry of an id it holds: kept)
            else:
                called[key] = (line, event.at, event.serving_rr)
        elif isinstance(event, events.CallAnswered):
            called.pop(key, None)  # (answered again: held, a retry)
            held.add(key)
            added.discard(key)
            retried.pop(key, None)
        elif isinstance(event, events.QueryForgotten):
            held.discard(key)
            added.discard(key)
            if (retry := retried.pop(key, None)) is not None and event.reason == "withdrawn":
                findings.append(_gave_back(key, retry, line, name))
        elif isinstance(event, events.ConsumerAdded | events.ConsumerReleased):
            key = (event.consumer, event.query_id)
            if isinstance(event, events.ConsumerAdded) and key in held:
                added.add(key)  # (its provider had lost it: a retry's new load, or a dedup hit)
            retry = retried.pop(key, None)
            if retry is not None and getattr(event, "reason", "") == "abandoned":
                findings.append(_gave_back(key, retry, line, name))
    return [*_held_on(called, _held_spans(steps)), *findings]


def _gave_back(key: tuple[str, str], retry: int, line: int, name: str) -> Finding:
    consumer, qid = key
    who = f"{consumer} forgot" if name == consumer else f"{name} released"
    of = "" if name == consumer else f" of {consumer}"
    return Finding(
        "withdrawn",
        "violation",
        f"{who} query {qid[:8]}{of} after a withdrawn retry of it: a hold it had before "
        "that retry, given back (rule 17: a withdrawal leaves things as they were)",
        (retry, line),
        (name, consumer) if name != consumer else (consumer,),
    )


def retry_ended(steps: Sequence[Step]) -> list[Finding]:
    """`retry-ended` (rule 17, issue 68 item 8): a dependency's id kept for a retry is given
    back once the load that made it ended, as no retry can come from it.

    A `CallFailed` that `may_have_executed`, of a `parent` load, not answered later (a
    retry), is released by its provider after that registrar's `LoadFailed` or
    `ResourceUnloaded` of the parent (its `Abandon`, or the reconcile after the provider's
    restart): a provider's life holding it `WITHDRAWN_BOUND_S` after that end (or after it
    began to hold it, if later) is a violation, as in `withdrawn`. Not judged: a failure
    whose consumer's life ended before its load did (the next life restores it in doubt).
    """
    failed: dict[tuple[str, str], tuple[str, str]] = {}  # (consumer, id) -> (parent, provider)
    ended: dict[tuple[str, str], tuple[int, float, str]] = {}  # (consumer, id) -> ...
    for name, line, event, new, _life in steps:
        if new:
            for gone in [key for key in failed if key[0] == name]:
                del failed[gone]
        key = (name, getattr(event, "query_id", ""))
        if isinstance(event, events.CallFailed) and event.may_have_executed and event.parent:
            failed[key] = (event.parent, event.serving_rr)
        elif isinstance(event, events.CallAnswered | events.CallWithdrawn):
            failed.pop(key, None)  # (answered again: held, a retry; or withdrawn)
            ended.pop(key, None)
        elif isinstance(event, events.LoadFailed | events.ResourceUnloaded):
            for (consumer, qid), (parent, provider) in list(failed.items()):
                if consumer == name and parent == event.resource_id:
                    del failed[consumer, qid]
                    ended[consumer, qid] = (line, event.at, provider)
    return _held_on(
        ended,
        _held_spans(steps),
        "retry-ended",
        "the load that made that call ended (no retry can come)",
    )


def _held_spans(steps: Sequence[Step]) -> dict[tuple[str, str], list[Held]]:
    """(provider, id) -> each span a life of that provider held the id: (consumer, the line
    it began, since, until: `at` wall clock; a life ends with its last event)."""
    holding: dict[str, dict[str, tuple[str, int, float]]] = defaultdict(dict)
    spans: dict[tuple[str, str], list[Held]] = defaultdict(list)
    last: dict[str, float] = {}  # provider -> `at` of its last event

    def close(name: str, qid: str, until: float) -> None:
        consumer, line, since = holding[name].pop(qid)
        spans[name, qid].append((consumer, line, since, until))

    for name, line, event, new, _life in steps:
        if new:
            for qid in list(holding[name]):  # (the life before ended with its last event)
                close(name, qid, last.get(name, event.at))
        last[name] = event.at
        if isinstance(event, events.CatalogRestored):
            holding[name] = {qid: (c, line, event.at) for qid, _rid, c, *_ in event.consumers}
        elif isinstance(event, events.ConsumerAdded):
            holding[name][event.query_id] = (event.consumer, line, event.at)
        elif isinstance(event, events.ConsumerReleased) and event.query_id in holding[name]:
            close(name, event.query_id, event.at)
    for name, held in holding.items():  # (held to the end of the run)
        for qid in list(held):
            close(name, qid, last[name])
    return spans


def retry_kept(steps: Sequence[Step]) -> list[Finding]:
    """`retry-kept` (rule 17 case 3, rule 20): a failed call's id waits for its retry.

    A call that failed as its provider died (`CallFailed.may_have_executed`) may have run; the
    next life that restores the id keeps it while its consumer could still retry it (no new
    life or stop of the consumer, no answer, withdrawal or forgetting of the id, no load or
    unload of its own ended). Releasing it by a reconcile meanwhile is a violation.
    """
    findings: list[Finding] = []
    # (consumer, id) -> (line of its failure, provider, the provider's life that restored
    # it since: None until one did)
    waiting: dict[tuple[str, str], tuple[int, str, int | None]] = {}
    lives: dict[str, int] = {}  # registrar -> its current life

    def forget_all(consumer: str) -> None:
        for key in [k for k in waiting if k[0] == consumer]:
            del waiting[key]

    for name, line, event, new, life in steps:
        lives[name] = life
        if new:
            forget_all(name)
        if isinstance(event, events.CallFailed):
            waiting.pop((name, event.query_id), None)
            if event.may_have_executed:
                waiting[name, event.query_id] = (line, event.serving_rr, None)
        elif isinstance(event, events.CallAnswered | events.CallWithdrawn | events.QueryForgotten):
            waiting.pop((name, event.query_id), None)
        elif isinstance(
            event, events.RegistrarStopped | events.LoadFailed | events.ResourceUnloaded
        ):
            forget_all(name)
        if isinstance(event, events.CatalogRestored):
            for qid, _rid, consumer, *_ in event.consumers:
                key = (consumer, qid)
                if key in waiting and waiting[key][1] == name:
                    failed, provider, restored = waiting[key]
                    if restored is None:
                        waiting[key] = (failed, provider, life)
                    elif restored != life:
                        del waiting[key]  # (a later life: it may release it)
        elif (
            isinstance(event, events.ConsumerReleased)
            and event.reason == "reconcile"
            and waiting.get((event.consumer, event.query_id), (0, "", None))[1:] == (name, life)
        ):
            failed = waiting.pop((event.consumer, event.query_id))[0]
            findings.append(
                Finding(
                    "retry-kept",
                    "violation",
                    f"{name} released query {event.query_id[:8]} of {event.consumer} at a "
                    f"reconcile of the life that restored it, while {event.consumer} could "
                    f"still retry that call, which failed as {name} died (rule 17)",
                    (failed, line),
                    (name, event.consumer),
                )
            )
    return findings


KEPT_SLACK_S = 1.0
"""Seconds past its consumer's `call_timeout` by which a restored id kept for a retry is given
back, counted from the restore (the reconcile that starts the consumer's wait follows it)."""

TIMED_OUT_SLACK_S = 0.05
"""Seconds a call's timeout may end before its `call_timeout` after its start and not be
judged: `started` and `at` are wall clock stamps, the timeout a monotonic one's."""

_CALLS = (events.CallAnswered, events.CallFailed, events.CallWithdrawn)


def timed_out(
    steps: Sequence[Step], timeouts: Mapping[str, float], managers: Collection[str]
) -> list[Finding]:
    """`timed-out` (rule 17, issue 68 item 8): a call times out only once its timeout ran
    out. A client's `CallWithdrawn` of reason `"timeout"` comes at least its `call_timeout`
    (`timeouts`, less `TIMED_OUT_SLACK_S`) after the earliest start (`started`) of that
    consumer's calls of that id: every try of `call_with_retry`, or of the workload's
    retries, shares its first try's deadline (a later call of the id, `again`, starts
    later). Judged for the consumers of `timeouts` that are no manager (`managers`: a
    manager's load may pass a timeout of its own); a call of unknown start (0.0) is not.
    """
    first: dict[tuple[str, str], tuple[float, int]] = {}  # (consumer, id) -> start, its line
    findings: list[Finding] = []
    for name, line, event, _new, _life in steps:
        if not isinstance(event, _CALLS) or name not in timeouts or name in managers:
            continue
        key = (name, event.query_id)
        if event.started > 0 and event.started < first.get(key, (event.started + 1, 0))[0]:
            first[key] = (event.started, line)
        if not isinstance(event, events.CallWithdrawn) or event.reason != "timeout":
            continue
        if key not in first:
            continue
        started, began = first[key]
        took, bound = event.at - started, timeouts[name]
        if took < bound - TIMED_OUT_SLACK_S:
            findings.append(
                Finding(
                    "timed-out",
                    "violation",
                    f"{name}'s call {event.query_id[:8]} to {event.serving_rr}/{event.server} "
                    f"timed out {took:.3f} s after it began, before its timeout of {bound:g} s "
                    "ran out (rule 17: CallTimeoutError once the timeout passed)",
                    tuple(sorted({began, line})),
                    (name,),
                )
            )
    return findings


_NAMING = (events.CallAnswered, events.CallFailed, events.CallWithdrawn, events.QueryForgotten)


def kept_unclaimed(  # noqa: PLR0912 - one branch per event kind
    steps: Sequence[Step], lives: dict[tuple[str, int], Life], timeouts: Mapping[str, float]
) -> list[Finding]:
    """`kept-unclaimed` (rule 17 case 3, issue 68 item 5): an id kept for a retry that never
    comes is given back. The life that restores the id of a call that failed as its provider
    died keeps it for the consumer's retry, at most the consumer's `call_timeout` after their
    reconcile: violated when that life still holds it `call_timeout + KEPT_SLACK_S` after its
    restore, both lives going on, and the consumer never names the id again (no retry's
    answer, failure or withdrawal, no forgetting). Judged for the consumers of `timeouts`
    (name -> `call_timeout`: the plan's clients' and managers'; no event carries it).
    """
    failed: dict[tuple[str, str], tuple[int, str, int]] = {}  # -> (line, provider, its life)
    # (consumer, id) -> (failure's line, restore's line, provider, its life, consumer's
    # life, the stamp by which it is given back)
    held: dict[tuple[str, str], tuple[int, int, str, int, int, int]] = {}
    late: dict[tuple[str, str], tuple[tuple[int, ...], str]] = {}  # -> (lines, provider)

    def alive(name: str, life: int, stamp: int) -> bool:
        record = lives.get((name, life))
        return record is None or not record.ended_before(stamp)

    for name, line, event, new, life in steps:
        for key, (at, restored, provider, plife, clife, due) in list(held.items()):
            if event.hlc > due:
                del held[key]
                if alive(provider, plife, due) and alive(key[0], clife, due):
                    late[key] = ((at, restored, line), provider)
        if new or isinstance(event, events.RegistrarStopped):  # (that life ended)
            for gone in [k for k, v in held.items() if name in (k[0], v[2])]:
                del held[gone]
            for gone in [k for k in failed if k[0] == name]:
                del failed[gone]
        key = (name, getattr(event, "query_id", ""))
        if isinstance(event, _NAMING):  # (a retry's outcome, a withdrawal: it was claimed)
            failed.pop(key, None)
            held.pop(key, None)
            late.pop(key, None)
            if isinstance(event, events.CallFailed) and event.may_have_executed:
                failed[key] = (line, event.serving_rr, life)
        elif isinstance(event, events.CatalogRestored):
            for qid, _rid, consumer, *_ in event.consumers:
                found = failed.get((consumer, qid))
                if found is not None and found[1] == name and consumer in timeouts:
                    del failed[consumer, qid]
                    bound = timeouts[consumer] + KEPT_SLACK_S
                    due = hlc.from_seconds(hlc.seconds(event.hlc) + bound)
                    held[consumer, qid] = (found[0], line, name, life, found[2], due)
        elif isinstance(event, events.ConsumerReleased):
            held.pop((event.consumer, event.query_id), None)
    return [
        Finding(
            "kept-unclaimed",
            "violation",
            f"{provider} still held query {qid[:8]} of {consumer} "
            f"{timeouts[consumer] + KEPT_SLACK_S:g} s after its restore, kept for a retry of "
            f"a call that failed as it died, which {consumer} never made (rule 17: given "
            "back after call_timeout)",
            lines,
            (provider, consumer),
        )
        for (consumer, qid), (lines, provider) in late.items()
    ]


def _held_on(
    called: dict[tuple[str, str], tuple[int, float, str]],
    spans: dict[tuple[str, str], list[Held]],
    rule: str = "withdrawn",
    after: str = "{consumer} withdrew that call",
) -> list[Finding]:
    """`withdrawn`'s findings (or `rule`'s, `after` what): each withdrawal (`called`) whose
    provider held the id for `WITHDRAWN_BOUND_S` after it, in one of the `spans` that life
    held it."""
    findings = []
    for (consumer, qid), (line, at, provider) in called.items():
        for holder, added, since, until in spans.get((provider, qid), ()):
            kept = until - max(since, at)
            if holder == consumer and kept >= WITHDRAWN_BOUND_S:
                findings.append(
                    Finding(
                        rule,
                        "violation",
                        f"{provider} held query {qid[:8]} of {consumer} for {kept:.1f} s "
                        f"after {after.format(consumer=consumer)}, and after that life of "
                        f"{provider} began to hold it",
                        (line, added),
                        (provider, consumer),
                    )
                )
                break
    return findings


def left(
    steps: Sequence[Step], history: Sequence[Line], lives: dict[tuple[str, int], Life]
) -> list[Finding]:
    """`left`: a registrar's last stop lists no row that a consumer still running does not hold.

    A client row is left unless it is a dependency of a resource that is not; a resource kept
    `unloading` is not left. Not judged: a stop that is not the registrar's last event, one
    not `complete`, a second server's, and a last life in or after which a supervisor gave up
    (its children stop with their consumers' rows).
    """
    gave_up = [line for line, e in history if isinstance(e, events.SupervisorGaveUp)]
    last_line: dict[str, int] = {}
    stops: dict[str, tuple[int, events.RegistrarStopped, int]] = {}
    came: dict[tuple[str, str], int] = {}  # (registrar, resource or query id) -> last line
    for name, line, event, _new, life in steps:
        last_line[name] = line
        if isinstance(event, events.RegistrarStopped):
            stops[name] = (line, event, life)
        elif isinstance(event, events.ResourceLoaded):
            came[name, event.resource_id] = line
        elif isinstance(event, events.CallAnswered):
            came[name, event.query_id] = line
        elif isinstance(event, events.CatalogRestored):  # (listed again: the latest shows it)
            for row in (*event.resources, *event.clients):
                came[name, row[0]] = line
    final = {name: line for name, (line, _, _) in stops.items() if last_line[name] == line}
    findings = []
    for name, (line, stop, life) in stops.items():
        begun = lives[name, life].first_line
        if final.get(name) != line or not stop.complete or "@" in name:
            continue
        if any(begun <= at for at in gave_up):  # (published once its children stopped)
            continue

        def running(consumer: str, stopped_at: int = line) -> bool:
            return not final.get(consumer, stopped_at) < stopped_at

        kept = {rid for _qid, rid, consumer, *_ in stop.consumers if running(consumer)}
        resources = [
            row[0] for row in stop.resources if row[0] not in kept and row[2] != "unloading"
        ]
        clients = [row[0] for row in stop.clients if row[3] not in kept]
        if not resources and not clients:
            continue
        shown = sorted({came[name, i] for i in (*resources, *clients) if (name, i) in came})
        findings.append(
            Finding(
                "left",
                "violation",
                f"{name} stopped at the end of the run with {len(resources)} resources and "
                f"{len(clients)} client records left that no running consumer holds",
                (*shown[:_SHOWN], line),
                (name,),
            )
        )
    return findings


def fetch(
    steps: Sequence[Step],
    holdings: dict[tuple[str, str], list[Holding]],
    lives: dict[tuple[str, int], Life],
) -> list[Finding]:
    """`fetch` (rule 10): a fetch lists what its provider held for its consumer.

    Within the window between the fetch's `started` and `hlc` stamps, each listed id was held
    at some instant, and each id the consumer had answered there before it (not withdrawn nor
    forgotten) and held throughout is listed. A `ServerQueriesListed` is judged alike, for any
    consumer. Not judged: a window a provider's life began or ended in; a second server's.
    """
    answers: dict[str, dict[str, tuple[str, str, int]]] = defaultdict(dict)
    by_name: dict[str, list[tuple[int, Life]]] = defaultdict(list)
    for (name, number), record in lives.items():
        by_name[name.partition("@")[0]].append((number, record))
    findings: list[Finding] = []
    throughout: dict[str, list[tuple[str, Holding]]] | None = None  # provider -> its ids
    for name, line, event, new, life in steps:
        if new:
            answers[name].clear()
        if isinstance(event, events.CallAnswered):
            answers[name][event.query_id] = (event.serving_rr, event.server, event.hlc)
        elif isinstance(event, events.QueryForgotten | events.CallWithdrawn | events.CallFailed):
            answers[name].pop(event.query_id, None)
        elif isinstance(event, events.QueriesFetched):
            spanning = _spanning(by_name[event.serving_rr], event.started, event.hlc)
            if spanning is not None:
                findings += _fetched(line, event, spanning, answers[name], holdings)
        elif isinstance(event, events.ServerQueriesListed) and name == event.registrar:
            if throughout is None:
                throughout = defaultdict(list)
                for (provider, qid), held in holdings.items():
                    throughout[provider] += [(qid, h) for h in held]
            findings += _listed(line, event, life, throughout[name], holdings)
    return findings


def _listed(
    line: int,
    event: events.ServerQueriesListed,
    life: int,
    held: list[tuple[str, Holding]],
    holdings: dict[tuple[str, str], list[Holding]],
) -> list[Finding]:
    """`fetch`'s findings about one listing of a provider's own server (at `line`, in
    its `life`); `held`: every holding of that provider the pass kept."""
    name, server, start, stop = event.registrar, event.server, event.started, event.hlc
    findings = [
        Finding(
            "fetch",
            "violation",
            f"{name}: a listing of its server {server} listed query {qid[:8]}, which "
            f"{name} did not hold while asked",
            (line,),
            (name,),
        )
        for qid in event.query_ids
        if not any(
            h.life == life and h.since < stop and (h.until is None or h.until > start)
            for h in holdings.get((name, qid), ())
        )
    ]
    listed = set(event.query_ids)
    for qid, h in held:
        if (
            qid not in listed
            and h.life == life
            and h.server == server
            and h.since < start
            and (h.until is None or h.until > stop)
        ):
            listed.add(qid)  # (one finding an id)
            findings.append(
                Finding(
                    "fetch",
                    "violation",
                    f"{name}: a listing of its server {server} did not list query "
                    f"{qid[:8]}, which it held throughout the listing",
                    (h.line, line),
                    (name,),
                )
            )
    return findings


def _spanning(lives: list[tuple[int, Life]], start: int, stop: int) -> int | None:
    """The one life of these (a provider's, its second servers' too) that spans the
    window from `start` to `stop` (stamps), or `None`: none does, or one began or ended
    in it."""
    overlapping = [
        (number, life)
        for number, life in lives
        if life.start <= stop and (life.end is None or life.end >= start)
    ]
    if len(overlapping) != 1:
        return None
    number, life = overlapping[0]
    if life.start > start or (life.end is not None and life.end <= stop):
        return None
    return number


def _fetched(
    line: int,
    event: events.QueriesFetched,
    life: int,
    answers: dict[str, tuple[str, str, int]],
    holdings: dict[tuple[str, str], list[Holding]],
) -> list[Finding]:
    """`fetch`'s findings about one fetch (at `line`), whose provider's `life` spans it;
    `answers`: its consumer's answered ids (id -> provider, server, stamp)."""
    name, provider, start, stop = event.registrar, event.serving_rr, event.started, event.hlc
    findings = [
        Finding(
            "fetch",
            "violation",
            f"{name}: a fetch from {provider}/{event.server} listed query "
            f"{qid[:8]}, which {provider} did not hold while asked",
            (line,),
            (name, provider),
        )
        for qid in event.query_ids
        if not any(
            h.since < stop and (h.until is None or h.until > start)
            for h in holdings.get((provider, qid), ())
        )
    ]
    listed = set(event.query_ids)
    for qid, (serving, server, stamp) in answers.items():
        if serving != provider or server != event.server or stamp >= start or qid in listed:
            continue
        held = [
            h
            for h in holdings.get((provider, qid), ())
            if h.life == life and h.since < start and (h.until is None or h.until > stop)
        ]
        if held:
            findings.append(
                Finding(
                    "fetch",
                    "violation",
                    f"{name}: a fetch from {provider}/{event.server} did not list query "
                    f"{qid[:8]}, which {provider} held for it throughout the fetch",
                    (held[0].line, line),
                    (name, provider),
                )
            )
    return findings


CALL_BOUND_S = 60.0
"""Seconds a call may take from its caller's send to its provider's `ConsumerAdded` (more
than any call timeout of the shipped plans): an add within that long of the start of its
caller's life may be of a call the life before made, and is not judged (`outcome`)."""

_OUTCOMES = (events.CallAnswered, events.CallFailed, events.CallWithdrawn)


def outcome(
    steps: Sequence[Step], lives: dict[tuple[str, int], Life], history: Sequence[Line]
) -> list[Finding]:
    """`outcome`: every call has an outcome. A call its provider took (`ConsumerAdded`)
    has at its caller an answer (`CallAnswered`), an error (`CallFailed`) or a withdrawal
    (`CallWithdrawn`) of its id, or its caller's life ended otherwise than by its own stop
    (a kill, a crash: the call died with it), or by a stop that ended its process.

    Judged: the caller's life at the add (its latest begun by the add's stamp, else its
    first: a caller's first event may be the call's answer) ended in
    its `RegistrarStopped` (a stop answers or withdraws what is in flight), and began
    `CALL_BOUND_S` before the add or is the caller's first (else a call of the life before
    may be the one added). Not judged: a caller with no event in the run, a run with no
    outcome at all (written before the consumer's side was published, schema 2), a
    caller whose process exited with that life (a `ChildExited` of its pid: a manager's
    stop withdraws its top-level calls, but a call of a load under way is settled by
    that load, and the process's end after the stop cuts the load, as a kill does:
    rule 16 reports it in doubt, rule 20 or 12 releases the id).
    """
    outcomes: set[tuple[str, str]] = set()  # (caller, id)
    adds: list[tuple[str, str, int, int, str]] = []  # (caller, id, line, stamp, provider)
    stops: dict[tuple[str, int], int] = {}  # (registrar, life) -> line of its stop
    for name, line, event, _new, life in steps:
        if isinstance(event, _OUTCOMES):
            outcomes.add((base(name), event.query_id))
        elif isinstance(event, events.ConsumerAdded):
            adds.append((event.consumer, event.query_id, line, event.hlc, name))
        elif isinstance(event, events.RegistrarStopped):
            stops.setdefault((name, life), line)
    of = _lives_of(lives)
    findings: list[Finding] = []
    if not outcomes:
        return findings
    exited = {
        (event.child, event.host, event.pid)
        for _, event in history
        if isinstance(event, events.ChildExited)
    }
    for caller, qid, line, stamp, provider in adds:
        if (caller, qid) in outcomes or not of.get(caller):
            continue
        begun = [item for item in of[caller] if item[0] <= stamp]
        start, life, record = begun[-1] if begun else of[caller][0]  # (none yet: its first)
        stop = stops.get((caller, life))
        if stop is None or (record.end is not None and record.end < stamp):
            continue  # (its life ended by a kill, or before the add: the call died with it)
        if len(begun) > 1 and hlc.seconds(stamp) - hlc.seconds(start) < CALL_BOUND_S:
            continue
        if (caller, record.host, record.pid) in exited:
            continue  # (its process ended after the stop: a load's calls ended with it)
        findings.append(
            Finding(
                "outcome",
                "violation",
                f"{provider} added query {qid[:8]} of {caller}, whose life went on to its "
                f"stop with no answer, error or withdrawal of that call",
                (line, stop),
                (provider, caller),
            )
        )
    return findings


def _lives_of(lives: dict[tuple[str, int], Life]) -> dict[str, list[tuple[int, int, Life]]]:
    """Each registrar's lives `(start, life, record)` by start (second servers left out)."""
    of: dict[str, list[tuple[int, int, Life]]] = defaultdict(list)
    for (name, life), record in lives.items():
        if record.beside is None:
            of[name].append((record.start, life, record))
    for found in of.values():
        found.sort(key=lambda item: item[0])
    return of


GONE_RELEASES = ("unload", "unload unanswered", "dependency", "stop")
"""`QueryForgotten` reasons of a consumer's own release of an id (`gone-told` judges them)."""


def gone_told(history: Sequence[Line], steps: Sequence[Step]) -> list[Finding]:
    """`gone-told` (rule 19): a registrar's life begun after a provider of its host was lost
    for good (a `temporary` child's crash, no event of that name after it) is told so at
    its start (its supervisor's death watch for those it missed): it forgets the ids it held
    there as `provider lost`, not by releasing them. A life that forgot any as `provider
    lost` was told: its releases before that raced the telling (a life that released every
    one in that race cannot be told apart from one never told)."""
    lost: dict[tuple[str, str], Line] = {}  # (host, provider) -> its exit, if its last event
    for line, e in history:
        if isinstance(e, events.ChildExited) and e.restart == "temporary" and not e.stopped:
            lost[e.host, e.child] = (line, e)
        elif (name := registrar_of(e) or getattr(e, "child", None)) is not None:
            lost.pop((e.host, name), None)  # (served again: not gone)
    released: dict[tuple[str, int, str, str], list[int]] = defaultdict(list)  # (life) -> lines
    told: set[tuple[str, int, str, str]] = set()  # (registrar, life, host, provider)
    began: dict[str, int] = {}  # registrar -> the stamp of its life now's first event
    for name, line, event, new, life in steps:
        if new:
            began[name] = event.hlc
        if not isinstance(event, events.QueryForgotten):
            continue
        exit_ = lost.get((event.host, event.serving_rr))
        if exit_ is None or exit_[1].hlc >= began.get(name, 0):
            continue
        key = (name, life, event.host, event.serving_rr)
        if event.reason == "provider lost":
            told.add(key)
        elif event.reason in GONE_RELEASES:
            released[key].append(line)
    return [
        Finding(
            "gone-told",
            "violation",
            f"{name} released {len(lines)} id(s) held at {provider}, lost for good before "
            f"this life of {name} began, and forgot none as `provider lost`: it was not "
            "told at its start (rule 19)",
            (lost[host, provider][0], *lines),
            (name,),
        )
        for (name, life, host, provider), lines in released.items()
        if (name, life, host, provider) not in told
    ]


def client_stopped(
    steps: Sequence[Step], timeouts: Mapping[str, float], managers: Collection[str]
) -> list[Finding]:
    """`client-stopped`: a client of the plan (a consumer of `timeouts` that is no manager,
    started by `Supervisor.registrar`) is stopped with the tree: its last life ends in its
    `RegistrarStopped` (the supervisor stops the registrars it started before its children)."""
    last: dict[str, tuple[int, int]] = {}  # client -> (its last life, that life's last line)
    stopped: set[tuple[str, int]] = set()
    for name, line, event, _new, life in steps:
        if name not in timeouts or name in managers:
            continue
        last[name] = (life, line)
        if isinstance(event, events.RegistrarStopped):
            stopped.add((name, life))
    return [
        Finding(
            "client-stopped",
            "violation",
            f"{name}, a registrar its supervisor started, did not stop with the tree (no "
            "`RegistrarStopped` in its last life)",
            (line,),
            (name,),
        )
        for name, (life, line) in sorted(last.items())
        if (name, life) not in stopped
    ]
