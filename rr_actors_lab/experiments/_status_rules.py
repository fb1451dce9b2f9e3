"""A status's deliveries (rules `status-once`, `status-path`, `status-reached`).

```
 StatusDelivered ──► status_once: each (status, holder's id) once
                 └─► status_path: on a dependency path from its send (hop 1: a holder
                     of the resource it was sent about; hop n: a holder of a resource
                     one of whose dependencies got it at hop n-1)
 Expected (the provider pass: the holders at the send, and up each dependency that got
 it) ──► status_reached: each got it, unless it let its id go before the status's last
         delivery (not on the answer to an Unload its sender released it on after the
         send: that answer carried it), or the one to send it on died first (or
         soon after, before anything it sent that registrar later arrived: it may
         have waited in the sender)
 StatusHandled ──► status_order: each id's callbacks one at a time, in arrival order;
                   one sender's statuses (StatusSent) arrive in the order sent; each
                   callback of a process has a place of its own in that order (1, 2, ...)
 StatusAnswered ──► status_answered: a send answered after the callbacks it reached returned
                └─► status_patient: ... and not after its patience (StatusSent.patience)
```

Each rule's windows and what it excuses: docs/how-to/check-a-run.md.
"""

from __future__ import annotations

import bisect
import dataclasses
from collections import defaultdict
from collections.abc import Callable, Sequence

from rr_actors import events
from rr_actors._core import hlc
from rr_actors_lab.experiments._history import Facts, Finding, Life, Line, Step, holder_at
from rr_actors_lab.experiments._provider_rules import Expected

__all__ = ["ANSWERED", "Span", "status_once", "status_order", "status_path", "status_reached"]

Span = tuple[int, int, int | None, int]
"""A consumer holding a query id in one of its lives: `(life, stamp it began holding it,
stamp it let it go or None, line of that QueryForgotten or 0)`."""


def status_once(history: Sequence[Line]) -> list[Finding]:
    """`status-once`: each status send reaches each holder once per path."""
    findings: list[Finding] = []
    seen: dict[tuple[str, str, str], int] = {}
    for line, event in history:
        if not isinstance(event, events.StatusDelivered) or not event.status_id:
            continue
        key = (event.status_id, event.registrar, event.query_id)
        first = seen.get(key)
        if first is None:
            seen[key] = line
            continue
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
    return findings


def status_order(history: Sequence[Line]) -> list[Finding]:
    """`status-order` (rule 9): each id's status callbacks run one at a time, in arrival order,
    and a provider's statuses arrive in the order it sent them.

    A callback may begin once every earlier-arrived one of its id returned, or `opened` (waited
    for a registrar). A callback that never returned is not judged. The statuses of one
    sender (a registrar in one process: its `StatusSent`, in its actor's order) arrive at
    each id in the order sent; a status coalesced away or given up on before it ran is not
    judged, nor one whose send is not in the history.
    """
    sent: dict[str, tuple[tuple[str, int, str], int, int]] = {}  # status id -> (sender, hlc, line)
    by_id: dict[tuple[str, int, str, str], list[tuple[int, events.StatusHandled]]]
    by_id = defaultdict(list)
    for line, event in history:
        if isinstance(event, events.StatusHandled):
            by_id[event.host, event.pid, event.registrar, event.query_id].append((line, event))
        elif isinstance(event, events.StatusSent) and event.status_id:
            sent[event.status_id] = ((event.host, event.pid, event.registrar), event.hlc, line)
    findings: list[Finding] = _unnumbered(history)
    for handled in by_id.values():
        handled.sort(key=lambda entry: entry[1].arrived)
        limit, before = 0, handled[0]  # (the latest a next one may begin, and whose)
        for line, event in handled:
            if event.began < limit:
                findings.append(_out_of_order(before, (line, event)))
            free = event.opened or event.hlc
            if free > limit:
                limit, before = free, (line, event)
        findings.extend(_overtaken(handled, sent))
    return findings


def status_answered(history: Sequence[Line]) -> list[Finding]:
    """`status-answered` (rule 9): a `send_status` is answered once the callbacks it reached
    returned. A `StatusHandled` of a consumer id its `StatusAnswered` lists as reached, stamped
    after that answer (its acknowledgement came back first), is a finding (one given up on is
    listed in `gave_up`); not one whose id its provider released on an `Unload` before (the
    status may have come on the answer, after the send's own notice found it seen)."""
    answered: dict[str, tuple[int, events.StatusAnswered]] = {}  # status id -> (line, answer)
    handled: list[tuple[int, events.StatusHandled]] = []
    released: dict[str, int] = {}  # query id -> the stamp of its first release on an Unload
    for line, event in history:
        if isinstance(event, events.StatusAnswered):
            answered.setdefault(event.status_id, (line, event))
        elif isinstance(event, events.StatusHandled):
            handled.append((line, event))
        elif isinstance(event, events.ConsumerReleased) and event.reason == "unload":
            released.setdefault(event.query_id, event.hlc)
    findings: list[Finding] = []
    for line, event in handled:
        at, answer = answered.get(event.status_id, (0, None))
        if (
            answer is None
            or event.query_id not in answer.reached
            or event.hlc <= answer.hlc
            or released.get(event.query_id, event.hlc) < event.hlc
        ):
            continue
        findings.append(
            Finding(
                "status-answered",
                "violation",
                f"{answer.registrar}'s send of status {event.status_id[:8]} "
                f"({event.status.name}) was answered with query {event.query_id[:8]} of "
                f"{event.registrar} reached before its callback returned (rule 9)",
                (at, line),
                (answer.registrar, event.registrar),
            )
        )
    return findings


PATIENCE_SLACK_S = 0.5
"""Seconds past a send's patience by which a callback it reached has returned or been given
up on (the status runner's watchdog looks every 50 ms: `SLICE`)."""


def status_patient(history: Sequence[Line]) -> list[Finding]:
    """`status-patient` (rule 9, issue 68 item 8): a `send_status` waits for a callback at
    most its patience (`StatusSent.patience`), then gives it up. A `StatusHandled` of a
    consumer id its `StatusAnswered` lists as reached (not given up on), stamped more than
    `PATIENCE_SLACK_S` past the send's patience after its `StatusSent` (and before the
    answer: the answer waited for it), is a finding. A send of no patience is not judged."""
    sent: dict[str, tuple[int, events.StatusSent]] = {}  # status id -> (line, send)
    answered: dict[str, events.StatusAnswered] = {}
    handled: list[tuple[int, events.StatusHandled]] = []
    for line, event in history:
        if isinstance(event, events.StatusSent):
            sent.setdefault(event.status_id, (line, event))
        elif isinstance(event, events.StatusAnswered):
            answered.setdefault(event.status_id, event)
        elif isinstance(event, events.StatusHandled):
            handled.append((line, event))
    findings: list[Finding] = []
    for line, event in handled:
        at, send = sent.get(event.status_id, (0, None))
        answer = answered.get(event.status_id)
        if send is None or send.patience is None or answer is None:
            continue
        took = hlc.seconds(event.hlc) - hlc.seconds(send.hlc)
        if (
            event.query_id not in answer.reached
            or event.hlc > answer.hlc
            or took <= send.patience + PATIENCE_SLACK_S
        ):
            continue
        findings.append(
            Finding(
                "status-patient",
                "violation",
                f"{send.registrar}'s send of status {event.status_id[:8]} "
                f"({event.status.name}) waited {took:.2f} s, past its patience of "
                f"{send.patience:g} s, for the callback of query {event.query_id[:8]} of "
                f"{event.registrar}, not given up on (rule 9)",
                (at, line),
                (send.registrar, event.registrar),
            )
        )
    return findings


def _overtaken(
    handled: Sequence[tuple[int, events.StatusHandled]],
    sent: dict[str, tuple[tuple[str, int, str], int, int]],
) -> list[Finding]:
    """The callbacks of one id (in arrival order) whose status arrived after one its sender
    sent later: `status-order`'s findings, with the two sends and the two callbacks."""
    latest: dict[tuple[str, int, str], tuple[int, int, int, events.StatusHandled]] = {}
    seen: set[str] = set()
    findings: list[Finding] = []
    for line, event in handled:
        send = sent.get(event.status_id)
        if send is None or event.status_id in seen:  # (one arrival a status: status-once's)
            continue
        seen.add(event.status_id)
        sender, stamp, sent_line = send
        last = latest.get(sender)
        if last is None or stamp > last[0]:
            latest[sender] = (stamp, sent_line, line, event)
            continue
        _stamp, later_sent, later_line, later = last
        findings.append(
            Finding(
                "status-order",
                "violation",
                f"{event.registrar}: status {event.status_id[:8]} ({event.status.name}) "
                f"reached query {event.query_id[:8]} after status {later.status_id[:8]} "
                f"({later.status.name}), which {sender[2]} sent after it",
                tuple(sorted({sent_line, later_sent, later_line, line})),
                (event.registrar,),
            )
        )
    return findings


def _unnumbered(history: Sequence[Line]) -> list[Finding]:
    """`status-order`'s findings about arrival places: a `StatusHandled` whose `arrived` is
    not a place (below 1), or is the place of another callback of its process (host, pid;
    numbered afresh after a `ChildExited` of that pid: a pid used again), whose order then
    cannot be judged. The same event twice (its `seq`) is one callback."""
    places: dict[tuple[str, int], dict[int, tuple[int, int]]] = defaultdict(dict)
    findings: list[Finding] = []
    for line, event in history:
        if isinstance(event, events.ChildExited):
            places.pop((event.host, event.pid), None)
            continue
        if not isinstance(event, events.StatusHandled):
            continue
        taken = places[event.host, event.pid]
        first = taken.setdefault(event.arrived, (line, event.seq))
        if event.arrived >= 1 and (first[0] == line or (event.seq and first[1] == event.seq)):
            continue
        where = "" if event.arrived < 1 else f", the place of the callback at line {first[0]}"
        findings.append(
            Finding(
                "status-order",
                "violation",
                f"{event.registrar}: the callback of status {event.status_id[:8]} "
                f"({event.status.name}) for query {event.query_id[:8]} arrived at place "
                f"{event.arrived} of its process's status runner{where}: its arrival order "
                f"cannot be judged",
                tuple(sorted({first[0], line})),
                (event.registrar,),
            )
        )
    return findings


def _out_of_order(
    before: tuple[int, events.StatusHandled], late: tuple[int, events.StatusHandled]
) -> Finding:
    """`status-order`'s finding: `late` began before `before` (arrived first) let it."""
    first, event = before[1], late[1]
    how = "before it began" if event.began < first.began else "while it ran"
    return Finding(
        "status-order",
        "violation",
        f"{event.registrar}: the callback of status {event.status_id[:8]} "
        f"({event.status.name}) for query {event.query_id[:8]} began {how}: the callback "
        f"of status {first.status_id[:8]} ({first.status.name}), which arrived before "
        f"it, had neither returned nor waited for a registrar",
        tuple(sorted((before[0], late[0]))),
        (event.registrar,),
    )


def status_path(history: Sequence[Line], facts: Facts) -> list[Finding]:
    """`status-path`: each delivery of a status is on a dependency path from its send."""
    # (status id, registrar, hop) -> the resources of that registrar it climbed to
    climbed: dict[tuple[str, str, int], set[str]] = defaultdict(set)
    deliveries = [
        (line, event)
        for line, event in history
        if isinstance(event, events.StatusDelivered) and event.status_id
    ]
    for _, event in deliveries:
        parent = facts.parent.get((event.registrar, event.query_id))
        if parent is not None:
            climbed[event.status_id, event.registrar, event.hop].add(parent)
    findings: list[Finding] = []
    lost_tail = _lost_tail(history)
    for line, event in deliveries:
        holder = holder_at(facts, event.query_id, event.hlc)
        if holder is None:
            continue  # (whose it is, the run does not say)
        provider, rid, added = holder
        message = _off_path(event, provider, rid, facts, climbed)
        if message is None or (message == _NOT_SENT and lost_tail(provider, event.hlc)):
            continue
        findings.append(
            Finding(
                "status-path",
                "violation",
                f"{event.registrar}: status {event.status_id[:8]} ({event.status.name}) "
                f"reached query {event.query_id[:8]} at hop {event.hop} off any path: "
                f"{message}",
                (added, line),
                (event.registrar, provider),
            )
        )
    return findings


_NOT_SENT = "no StatusSent at its provider"


def _lost_tail(history: Sequence[Line]) -> Callable[[str, int], bool]:
    """Whether `name`'s life at a stamp wrote nothing after it and then exited (its last events
    may have died unwritten with it: a SIGKILL takes the journal's tail)."""
    own: dict[str, list[tuple[int, int]]] = defaultdict(list)  # name -> (stamp, pid)
    exited: set[int] = set()
    for _, event in history:
        if isinstance(event, events.ChildExited):
            exited.add(event.pid)
        name, pid = getattr(event, "registrar", None), getattr(event, "pid", None)
        if isinstance(name, str) and isinstance(pid, int) and event.hlc is not None:
            own[name].append((event.hlc, pid))
    for stamps in own.values():
        stamps.sort()

    def lost(name: str, stamp: int) -> bool:
        stamps = own.get(name, [])
        at = bisect.bisect_right(stamps, (stamp, float("inf"))) - 1
        if at < 0:
            return False
        pid = stamps[at][1]
        return pid in exited and not any(p == pid for _, p in stamps[at + 1 :])

    return lost


def _off_path(
    event: events.StatusDelivered,
    provider: str,
    rid: str,
    facts: Facts,
    climbed: dict[tuple[str, str, int], set[str]],
) -> str | None:
    """Why delivery `event` (of an id held at `provider`'s `rid`) is on no path, or `None`."""
    if event.hop > 1:
        if rid in climbed.get((event.status_id, provider, event.hop - 1), ()):
            return None
        return f"no dependency of {rid[:8]} got it at {provider} one hop before"
    if (event.registrar, event.query_id) in facts.reported:
        return None  # its consumer told it FATAL itself (rules 19, 20)
    about = facts.sent.get(event.status_id)
    if about is None:
        return _NOT_SENT
    sent_on = holder_at(facts, about, event.hlc)
    if sent_on is not None and sent_on[:2] != (provider, rid):
        return f"it was sent about {sent_on[1][:8]}, not {rid[:8]}"
    return None


def _passes(history: Sequence[Line]) -> dict[tuple[str, str], list[int]]:
    """The lines of each registrar's events of each status (`StatusSent`, `StatusDelivered`),
    by `(registrar, status id)`, in order."""
    found: dict[tuple[str, str], list[int]] = defaultdict(list)
    for line, e in history:
        if isinstance(e, (events.StatusSent, events.StatusDelivered)):
            found[e.registrar, e.status_id].append(line)
    return found


def _pass_end(passes: dict[tuple[str, str], list[int]], want: Expected, last: int) -> int:
    """The last line of the sender's events of `want`'s status in the life that ends at
    `last`, from `want.line` on: a sender whose life wrote nothing after them (killed as it
    climbed: a real `simshare` run, 2026-11-27, api SIGKILLed after 11 deliveries at hop 1
    and one climb sent) may have lost the climb with it."""
    lines = passes.get((want.sender, want.status_id), [])
    at = bisect.bisect_right(lines, last)
    return max(want.line, lines[at - 1]) if at else want.line


def status_reached(
    expected: Sequence[Expected],
    facts: Facts,
    spans: dict[tuple[str, str], list[Span]],
    lives: dict[tuple[str, int], Life],
    history: Sequence[Line],
    steps: Sequence[Step],
) -> list[Finding]:
    """`status-reached`: every holder that held its id throughout a status got it.

    Throughout: from before it was sent on to it (`Expected.since`) until after its last
    delivery, in one life; for an id not a dependency, until it reached another id of its
    registrar at that hop (a status desk delivers those in one pass). The sender must have gone
    on after the send, and after its other events of that status (`_pass_end`).
    Excused: a holder cut off its sender (rule 19: each let the id go); a
    holder killed within `LOST_WITH_HOLDER_S` of a send that reached nobody; a holder restarted
    but not serving yet (failure-semantics.md); a holder whose registrar nothing the
    sender's life sent at or after it reached in the holder's process of the send, that
    life ending within `LOST_WITH_SENDER_S` of the send (`_queued`).

    Letting the id go early excuses no holder whose release crossed the status (rule 9): the
    answer to its `Unload` carried every status not yet acknowledged, delivered before it
    forgets the id (`ANSWERED`). One forgotten as its `Unload` went unanswered, the life that
    sent the status on having ended by then (or just after), is not owed it (`_unanswered`),
    unless the status reached another id of its registrar at that hop while it held this one.
    """
    cut_off = _cut_off(history)
    way = _on_its_way(history)
    queued = _queued(expected, way, lives)
    released = _released_on_unload(steps)
    restarts = _restarts(history)
    reasons = {line: e.reason for line, e in history if isinstance(e, events.QueryForgotten)}
    passes = _passes(history)
    findings: list[Finding] = []
    for line, holder, qid in facts.told_self:
        if facts.fatal.get(qid, line) >= line:
            findings.append(
                Finding(
                    "status-reached",
                    "violation",
                    f"{holder}: query {qid[:8]} forgotten as lost, but the FATAL it tells "
                    f"itself never reached it",
                    (line,),
                    (holder,),
                )
            )
    for want in expected:
        if (want.status_id, want.query_id) in facts.delivered:
            continue
        if (want.sender, want.holder, want.query_id) in cut_off:
            continue
        sender = lives.get((want.sender, want.life))
        if (
            sender is None
            or sender.last_line <= _pass_end(passes, want, sender.last_line)
            or queued(want)
        ):
            continue  # it may have died before it sent it on (or before it left its process)
        end = facts.last_delivery.get(want.status_id, want.since)
        beside = None
        if (want.holder, want.query_id) not in facts.parent:
            beside = way.first.get((want.status_id, want.holder, want.hop))
            end = min(end, end if beside is None else beside)
        end = max(end, want.since)
        for life, began, until, forgot_at in spans.get((want.holder, want.query_id), ()):
            if began >= want.since:
                continue  # (held from before the send only)
            record = lives[want.holder, life]
            arrived = beside is not None and began < beside < (until or record.last + 1)
            if _not_serving_yet(want, record, life, restarts) or (
                not arrived and _unanswered(reasons.get(forgot_at), sender, until)
            ):
                continue
            let_go = until if until is not None else record.last
            release = released.get((want.sender, want.query_id))
            carried = (
                until is not None
                and reasons.get(forgot_at) in ANSWERED
                and _released_after(want, release, sender, until)
            )
            if not carried and (
                let_go <= end
                or (until is None and record.ended_before(end))
                or (until is None and _died_with_it(want, record, facts))
            ):
                continue
            how = "held it throughout"
            lines: tuple[int, ...] = (want.line, forgot_at) if forgot_at else (want.line,)
            if let_go <= end and release is not None:
                how = "the answer to its Unload carried it (its release crossed the status)"
                lines = (want.line, release[1], forgot_at)
            findings.append(
                Finding(
                    "status-reached",
                    "violation",
                    f"{want.holder}: status {want.status_id[:8]} never reached query "
                    f"{want.query_id[:8]} (hop {want.hop}, from {want.sender}), though {how}",
                    lines,
                    (want.holder, want.sender),
                )
            )
            break
    return findings


def _restarts(history: Sequence[Line]) -> dict[str, list[tuple[int, int]]]:
    """Child name -> `(stamp, pid)` of each of its `ChildRestarted`, in order."""
    restarts: dict[str, list[tuple[int, int]]] = defaultdict(list)
    for _, event in history:
        if isinstance(event, events.ChildRestarted):
            restarts[event.child].append((event.hlc, event.pid))
    return restarts


def _not_serving_yet(
    want: Expected, record: Life, life: int, restarts: dict[str, list[tuple[int, int]]]
) -> bool:
    """Whether `want`'s holder, in its life `record` (a restart: not its first life), was
    not serving yet when the status was sent on to it: the `ChildRestarted` that says
    its process (`record.pid`) serves again comes after the send."""
    if life == 0:
        return False
    for stamp, pid in restarts.get(want.holder, ()):
        if stamp >= record.start and pid == record.pid:
            return stamp > want.since
    return False


LOST_WITH_HOLDER_S = 1.0
"""Seconds after a status's send within which its holder's death loses it (`status-reached`,
for a status that reached nobody): it was on its way to the process that died."""


def _died_with_it(want: Expected, record: Life, facts: Facts) -> bool:
    """Whether `want`'s status reached nobody and its holder's life `record` ended within
    `LOST_WITH_HOLDER_S` of the send (it died with the status on its way to it)."""
    if record.end is None or want.status_id in facts.last_delivery:
        return False
    since = hlc.unpack(want.since)[0]
    return hlc.unpack(record.end)[0] - since <= LOST_WITH_HOLDER_S * 1_000_000


LOST_WITH_SENDER_S = 0.5
"""Seconds from a send to a holder's registrar within which the sender life's end may lose
it (`status-reached`, `_queued`): what a connection cannot take yet waits in the sender and
dies with it, and a connection to a registrar is made at the first send there (a real
`simslow` run, CI load 20: db killed 62 ms after the first status of its life, which
reached three registrars of a process, not the fourth, whose connection was still being
made; a holder restarted in a new process is connected to anew: `simdoubt` seed 58, db
killed 1.7 ms after its first status to api's restart; a real `simways` run, load 18:
db's statuses took 165 ms to arrive, and the 13 it sent in the 43 ms before its SIGKILL
reached nobody, or only the registrar whose connection was ahead;
docs/explanation/failure-semantics.md)."""


def _holder_pid(lives: dict[tuple[str, int], Life]) -> Callable[[str, int], int]:
    """The process of a registrar's life at a stamp (that of the last life begun before it;
    0: none shows it)."""
    starts: dict[str, list[tuple[int, int]]] = defaultdict(list)  # name -> (start, pid)
    for (name, _number), life in lives.items():
        starts[name].append((life.start, life.pid))
    for each in starts.values():
        each.sort()

    def pid(name: str, stamp: int) -> int:
        each = starts.get(name, [])
        at = bisect.bisect_right(each, (stamp, float("inf"))) - 1
        return each[at][1] if at >= 0 else 0

    return pid


def _queued(
    expected: Sequence[Expected], way: Ways, lives: dict[tuple[str, int], Life]
) -> Callable[[Expected], bool]:
    """Whether an expected status may have waited in its sender when the sender's life ended:
    nothing that life sent its holder registrar's process at or after it reached that
    registrar, and the life ended within `LOST_WITH_SENDER_S` of its send (what a connection
    cannot take yet, or is still being made for, waits in the sender and dies with it; a
    restarted holder's new process is connected to anew). Not when that sender reached the
    holder in none of its lives that sent it something (more than this one): the way itself
    is broken. A later send that arrived shows this one left (one way at a time, frames in
    order: rule 9): it is owed. One an `Unload`'s answer may have carried shows no such
    thing (`Ways`)."""
    holder_pid = _holder_pid(lives)

    def key_of(want: Expected) -> tuple[str, int, str, int]:
        return (want.sender, want.life, want.holder, holder_pid(want.holder, want.since))

    latest: dict[tuple[str, int, str, int], int] = {}  # key -> its last send that arrived
    sent: set[tuple[str, int, str, int]] = set()
    for want in expected:
        key = key_of(want)
        sent.add(key)
        if (want.status_id, want.query_id) in way.delivered:
            latest[key] = max(latest.get(key, want.since), want.since)
    ways: dict[tuple[str, str], list[bool]] = defaultdict(list)  # (sender, holder) -> by life
    for key in sent:
        ways[key[0], key[2]].append(key in latest)
    bound = LOST_WITH_SENDER_S * 1_000_000

    def queued(want: Expected) -> bool:
        key = key_of(want)
        life = lives.get(key[:2])
        if life is None or life.end is None or latest.get(key, -1) >= want.since:
            return False
        each = ways[key[0], key[2]]
        if len(each) > 1 and not any(each):
            return False
        return hlc.unpack(life.end)[0] - hlc.unpack(want.since)[0] <= bound

    return queued


@dataclasses.dataclass(slots=True)
class Ways:
    """The deliveries that came the status's own way (`_on_its_way`).

    Attributes:
        delivered: (status id, query id) of each.
        first: (status id, registrar, hop) -> the least stamp of those.
    """

    delivered: set[tuple[str, str]] = dataclasses.field(default_factory=set)
    first: dict[tuple[str, str, int], int] = dataclasses.field(default_factory=dict)


def _on_its_way(history: Sequence[Line]) -> Ways:
    """The deliveries no `Unload`'s answer carried: none after its provider released its id
    on an `Unload` (the answer leaves after the release, on the consumer's connection to
    the provider, and carries the statuses on their way to that id alone, `ANSWERED`). Such
    a delivery shows neither that the provider's own way to that registrar was made nor that
    a status desk's pass reached its other ids (a real `simways` run, load 27: db's statuses
    to client-1 waited for a connection 134 ms until db was killed; the first two reached
    one of its three ids on its `Unload`'s answer)."""
    released: dict[str, int] = {}  # query id -> the stamp of its first release on an Unload
    for _, event in history:
        if isinstance(event, events.ConsumerReleased) and event.reason == "unload":
            released[event.query_id] = min(released.get(event.query_id, event.hlc), event.hlc)
    way = Ways()
    for _, event in history:
        if not isinstance(event, events.StatusDelivered) or not event.status_id:
            continue
        if released.get(event.query_id, event.hlc + 1) < event.hlc:
            continue  # (it may have come on the answer)
        way.delivered.add((event.status_id, event.query_id))
        key = (event.status_id, event.registrar, event.hop)
        way.first[key] = min(way.first.get(key, event.hlc), event.hlc)
    return way


ANSWERED = ("unload", "dependency", "stop")
"""How a consumer forgets an id on the answer to its `Unload` (which carries the statuses
on their way to it, `consumer.py`'s `Releases`)."""


def _released_on_unload(steps: Sequence[Step]) -> dict[tuple[str, str], tuple[int, int, int]]:
    """(provider, query id) -> (its life, line, stamp) of each release on an `Unload`."""
    return {
        (name, event.query_id): (life, line, event.hlc)
        for name, line, event, _, life in steps
        if isinstance(event, events.ConsumerReleased) and event.reason == "unload"
    }


def _released_after(
    want: Expected, release: tuple[int, int, int] | None, sender: Life, forgot: int
) -> bool:
    """Whether `want`'s sender released its id on an `Unload` (`release`: life, line,
    stamp) after it sent the status on to it, in that life, and went on after (its answer
    left), before its holder forgot it (stamp `forgot`: on that answer)."""
    return (
        release is not None
        and release[0] == want.life
        and want.line < release[1] < sender.last_line
        and release[2] < forgot
    )


def _unanswered(reason: str | None, sender: Life, until: int | None) -> bool:
    """Whether the holder forgot its id (at stamp `until`) as its `Unload` went unanswered,
    the life that sent the status on having ended by then, or within `LOST_WITH_HOLDER_S`
    after (its `ChildExited` is stamped as its supervisor hears of the kill, which may be
    after the holder did): the answer that would carry it died with that life, and what came
    after found the id forgotten (failure-semantics.md, "Reconciling after a restart"; real
    `simways` runs, seeds 3 and 6)."""
    if reason != "unload unanswered" or until is None or sender.end is None:
        return False
    return hlc.unpack(sender.end)[0] - hlc.unpack(until)[0] <= LOST_WITH_HOLDER_S * 1_000_000


_UNREACHED = ("unknown at reconcile", "unload unanswered")
"""How a consumer forgets an id at a provider it could not hear (`_cut_off`)."""


def _cut_off(history: Sequence[Line]) -> set[tuple[str, str, str]]:
    """(provider, consumer, query id) of each id both sides let go as unreachable (a cut)."""
    released: set[tuple[str, str, str]] = set()
    cut: set[tuple[str, str, str]] = set()
    for _, event in history:
        if isinstance(event, events.ConsumerReleased) and event.reason == "death watch":
            released.add((event.registrar, event.consumer, event.query_id))
        elif isinstance(event, events.QueryForgotten) and event.reason in _UNREACHED:
            key = (event.serving_rr, event.registrar, event.query_id)
            if key in released:
                cut.add(key)
    return cut
