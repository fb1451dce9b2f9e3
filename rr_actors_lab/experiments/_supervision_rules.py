"""The supervisors' side of a run (rules `intensity`, `strategy`, `escalation`, `life-end`,
`damaged-backup`, `backup-readable`).

```
 ChildExited (counted) + SupervisorGaveUp ──► per supervisor ──► OTP's intensity: more
   than `max_restarts` counted exits within `period` s ──► findings
 ChildStarted / ChildExited / ChildRestarted / SupervisorGaveUp ──► Strategies: each
   decision against OTP's strategy and restart types (siblings stopped in reverse start
   order, the group restarted in start order; a group due that never comes back within
   `DUE_S`, its supervisor neither giving up nor shutting down) ──► `strategy`
   + a nested supervisor's give-up ──► its parent's next exit of it (`escalation`)
 ChildExited's reason ──► a fault, a stop or its supervisor ended it, else `life-end`
 a backup damaged after its manager's kill (`damaged`) ──► its next starts: refused with
   `CatalogCorruptError` (a deleted one: none), then one that restores nothing
   ──► `damaged-backup`; the refusals excused from `life-end`, the restore's lost ids
   judged by `kept` as a lost backup's
 the backups `read_backup` refused at the run's end ──► `backup-readable`
```

A supervisor's events come from its own thread in the order it decided: a group's stops
right after the exit that decided it, its restarts in one step. A supervisor started
again (after its give-up, or a second `ChildStarted` of a name) counts afresh (OTP).
Each rule's windows and what it excuses: docs/how-to/check-a-run.md.
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict
from collections.abc import Mapping, Sequence

from rr_actors import events
from rr_actors_lab.experiments._backup_faults import CORRUPT, REFUSED
from rr_actors_lab.experiments._history import Finding, Kind, Line

__all__ = [
    "DUE_S",
    "ENDED_BY",
    "ESCALATED_S",
    "FAILED_BY",
    "SLACK_S",
    "Strategies",
    "counted",
    "damaged_backup",
    "group",
    "intensity",
    "life_end",
    "strategy",
]

SLACK_S = 0.01
"""Seconds an exit may lie either side of a window's edge and not be judged: the
supervisor reads its own clock a moment after it stamps `ChildExited.at`."""


ENDED_BY = (
    (
        "killed",
        "a fault (a signal from outside: the plan's kill), or its supervisor (no "
        "clean stop within its timeout)",
    ),
    ("hung: ", "its supervisor: killed as hung (the plan's hang)"),
    ("shutdown", "a stop: its supervisor's shutdown"),
    ("normal", "a stop: its code stopped its registrar"),
    ("its supervisor gave up", "its supervisor's give-up"),
    ("gave up", "a nested supervisor's own give-up"),
    (
        "crashed (registrar actor died)",
        "a thread manager's: the plan's kill of it crashes its "
        "actor (`rr_actors.testing.crash`), not told apart from a crash of its own",
    ),
)
"""The `ChildExited` reasons (their beginnings) of a life ended by a fault, a stop or its
supervisor, with what ended it; `life-end` judges every other one a crash. A start that
failed (`failed to start: `) is one when its error is in `FAILED_BY`."""

FAILED_BY = ("DuplicateNameError", "RegistrarUnavailableError", "killed")
"""Errors of a start that failed by a fault or by rule 22 (a restart into a name another
serves, a kill or a cut during its setup), not by a crash of its own."""


STOP_FAILED = "stop failed: "
"""The `ChildExited` reason of a child whose stop raised in its supervisor (`ManagerExit`)."""


@dataclasses.dataclass
class _Damaged:
    """A manager's backup damaged after its kill, until its next restore."""

    how: str  # `corrupt_backup`'s `how`
    pid: int  # the process killed
    line: int  # its `ChildExited`
    refused: bool = False  # a start refused it since


def damaged_backup(
    history: Sequence[Line], damaged: Mapping[int, str]
) -> tuple[list[Finding], set[int], set[int]]:
    """`damaged-backup`: after a manager's process `pid` was killed and its backup damaged
    (`damaged`: pid -> `how`), its next start refuses the file with `CatalogCorruptError`
    naming it (a `ChildExited` whose reason says so) before any start serves, unless it
    was deleted, and the start that serves restores nothing (rule 15; "What the backup
    survives", failure-semantics.md). Returns the findings, the lines of the refusals
    (`life-end` excuses them: the fault ended those starts) and of the empty restores
    (`kept` judges their ids as a lost backup's)."""
    findings: list[Finding] = []
    refusals: set[int] = set()
    restores: set[int] = set()
    pending: dict[str, _Damaged] = {}
    for line, event in history:
        if isinstance(event, events.ChildExited):
            state = pending.get(event.child)
            if state is not None and event.pid != state.pid and CORRUPT in event.reason:
                refusals.add(line)
                state.refused = True
                if state.how not in REFUSED:
                    findings.append(_damage_finding(event.child, state, line, "refused"))
            if event.pid in damaged:
                pending[event.child] = _Damaged(damaged[event.pid], event.pid, line)
            continue
        if isinstance(event, events.CatalogRestored | events.ChildRestarted):
            name = event.registrar if isinstance(event, events.CatalogRestored) else event.child
            state = pending.get(name)
            if state is None or event.pid == state.pid:
                continue
            del pending[name]
            if state.how in REFUSED and not state.refused:
                findings.append(_damage_finding(name, state, line, "served from it"))
            elif isinstance(event, events.CatalogRestored):
                restores.add(line)
                if any(event.counts):
                    findings.append(_damage_finding(name, state, line, f"restored {event.counts}"))
    for name, state in pending.items():
        message = f"{name}'s backup was damaged ({state.how}) after pid {state.pid} was killed, "
        message += "and no start of it is shown after"
        findings.append(Finding("damaged-backup", "unverifiable", message, (state.line,), (name,)))
    return findings, refusals, restores


def _damage_finding(name: str, state: _Damaged, line: int, what: str) -> Finding:
    done = "deleted" if state.how == "delete" else f"damaged ({state.how})"
    promise = (
        "a deleted backup's restart starts empty"
        if state.how not in REFUSED
        else "a damaged backup is refused with CatalogCorruptError naming it, never used"
    )
    return Finding(
        "damaged-backup",
        "violation",
        f"{name}'s backup was {done} after pid {state.pid} was killed, and its next start "
        f"{what}: {promise}",
        (state.line, line),
        (name,),
    )


def life_end(history: Sequence[Line], excused: set[int] | None = None) -> list[Finding]:
    """`life-end`: a life ends only by a fault, a stop or its supervisor. A child's exit
    (`ChildExited`) that its supervisor did not cause (not `stopped`) gives a reason
    `ENDED_BY` names; any other (`crashed (registrar actor died)`, `exit code N`, a start
    that failed by an error of its own) is a registrar that ended itself. A life its
    supervisor stopped whose registrar stopped cleanly (`RegistrarStopped`, same pid) ended
    by that stop: its `ChildExited` does not say the stop failed (`STOP_FAILED`). The
    `excused` lines are exits a fault caused otherwise (`damaged_backup`'s refusals)."""
    findings = []
    clean: set[tuple[str, int]] = set()  # (registrar, pid) that published RegistrarStopped
    for line, event in history:
        if excused and line in excused:  # (a start a fault's damaged backup ended)
            continue
        if isinstance(event, events.RegistrarStopped):
            clean.add((event.registrar, event.pid))
        if not isinstance(event, events.ChildExited):
            continue
        if event.stopped:
            if (event.child, event.pid) in clean and event.reason.startswith(STOP_FAILED):
                findings.append(
                    Finding(
                        "life-end",
                        "violation",
                        f"{event.child} (pid {event.pid}) stopped cleanly, yet its "
                        f"supervisor reported its stop as: {event.reason[:200]}",
                        (line,),
                        (event.child,),
                    )
                )
            continue
        reason = event.reason
        if any(reason.startswith(begins) for begins, _ in ENDED_BY):
            continue
        failed = reason.removeprefix("failed to start: ")
        if failed != reason and any(name in failed for name in FAILED_BY):
            continue
        findings.append(
            Finding(
                "life-end",
                "violation",
                f"{event.child} (pid {event.pid}) ended by itself, neither by a fault, a "
                f"stop nor its supervisor: {reason[:200]}",
                (line,),
                (event.child,),
            )
        )
    return findings


def counted(event: events.ChildExited) -> bool:
    """Whether OTP counts `event` against its supervisor's restart intensity: an exit it
    did not cause, of a child its restart type restarts after it (`permanent` always,
    `transient` after an abnormal end; `temporary` never)."""
    if event.stopped:
        return False
    return event.restart == "permanent" or (event.restart == "transient" and not event.normal)


def intensity(history: Sequence[Line]) -> list[Finding]:
    """`intensity`: a supervisor gives up exactly when more than `max_restarts` counted exits
    fall within `period` seconds (OTP), at the exit that makes them so.

    Not judged: schema 3 or older (`restart` unknown), an exit within `SLACK_S` of the edge.
    """
    decisions: dict[str, list[tuple[int, events.Event]]] = defaultdict(list)
    for line, event in history:
        judged = isinstance(event, events.ChildExited) and event.restart and counted(event)
        if judged or isinstance(event, (events.SupervisorGaveUp, events.ChildStarted)):
            decisions[event.supervisor].append((line, event))  # type: ignore[union-attr]
    findings: list[Finding] = []
    for supervisor, seen in decisions.items():
        window: list[tuple[float, int]] = []  # (at, line) of the counted exits, in order
        started: set[str] = set()  # the children this run of it started
        for index, (line, event) in enumerate(seen):
            if isinstance(event, events.ChildStarted):
                if event.child in started:  # (a new run of it: it counts afresh)
                    window.clear()
                    started.clear()
                started.add(event.child)
                continue
            if not isinstance(event, events.ChildExited):
                window.clear()  # (a supervisor started again counts afresh)
                continue
            after = seen[index + 1] if index + 1 < len(seen) else None  # (its decision)
            gave_up = after is not None and isinstance(after[1], events.SupervisorGaveUp)
            period, most = event.period, event.max_restarts
            window = [(at, at_line) for at, at_line in window if event.at - at < period + SLACK_S]
            window.append((event.at, line))
            surely = [
                at_line
                for at, at_line in window
                if at_line == line or event.at - at < period - SLACK_S
            ]
            if len(surely) > most and not gave_up:
                lines = tuple(surely[-(most + 1) :])
                findings.append(
                    Finding(
                        "intensity",
                        "violation",
                        f"supervisor {supervisor} did not give up at {event.child}'s exit: "
                        f"{len(surely)} restarts within {period:g} s, more than its "
                        f"max_restarts {most}",
                        lines,
                    )
                )
            elif len(window) <= most and gave_up:
                assert after is not None
                lines = (*(at_line for _, at_line in window), after[0])
                findings.append(
                    Finding(
                        "intensity",
                        "violation",
                        f"supervisor {supervisor} gave up at {event.child}'s exit after "
                        f"{len(window)} restarts within {period:g} s, not more than its "
                        f"max_restarts {most}",
                        lines,
                    )
                )
    return findings


# -- strategy: which children a decision stops and restarts, in which order (OTP) -------------


ESCALATED_S = 1.0
"""Seconds after a nested give-up within which its parent may stop it instead (a shutdown)."""

DUE_S = 2.0
"""Seconds of events after an exit that restarts its group within which the group's restart
must begin (`ChildRestarted`), unless its supervisor gives up, is stopped or stops a child
(a shutdown): a plan's `backoff` delay is added (the events do not carry it)."""


def group(strategy: str, children: Sequence[str], crashed: str) -> tuple[str, ...]:
    """The children OTP's `strategy` restarts with `crashed`, in start order (itself too).

    Args:
        strategy: `"one_for_one"` (itself), `"one_for_all"` (every child) or
            `"rest_for_one"` (itself and the children started after it).
        children: the supervisor's children, in start order.
        crashed: the child whose exit decides.
    """
    if crashed not in children or strategy == "one_for_one":
        return (crashed,)
    if strategy == "one_for_all":
        return tuple(children)
    return tuple(children[children.index(crashed) :])


def _restarts_after(event: events.ChildExited) -> bool:
    """Whether OTP restarts a child after `event` (an exit its supervisor did not cause)."""
    return event.restart == "permanent" or (event.restart == "transient" and not event.normal)


@dataclasses.dataclass(slots=True)
class _Group:
    """The children one decision restarts, in start order."""

    line: int  # of the exit that decided it
    at: float  # that exit's
    crashed: str
    strategy: str
    members: tuple[str, ...]


@dataclasses.dataclass(slots=True)
class _Decision:
    """An exit that restarts its child (or makes its supervisor give up), and the stops
    that followed it."""

    line: int
    event: events.ChildExited
    running: frozenset[str]  # the children running as it was decided (not the crashed one)
    stops: list[tuple[int, str, float]] = dataclasses.field(default_factory=list)  # line, at


@dataclasses.dataclass(slots=True)
class _Supervisor:
    """One supervisor's children, as its events show them."""

    running: set[str] = dataclasses.field(default_factory=set)
    types: dict[str, str] = dataclasses.field(default_factory=dict)  # child -> restart type
    exits: dict[str, tuple[int, events.ChildExited]] = dataclasses.field(default_factory=dict)
    pending: dict[str, _Group] = dataclasses.field(default_factory=dict)  # due to restart
    deciding: _Decision | None = None
    stopped_at: float | None = None  # a child stopped outside any decision (a shutdown)
    batch: tuple[_Group, int] | None = None  # a group being restarted, its latest line
    owed: dict[str, tuple[_Group, int, tuple[str, ...]]] = dataclasses.field(
        default_factory=dict
    )  # the first child a restart left out -> its group, that restart's line, those left


class Strategies:
    """Follows every supervisor's decisions, line by line (`see`), then `end`.

    `findings` holds the `strategy` and `escalation` violations found.
    """

    def __init__(self, due_s: float = DUE_S) -> None:
        self.due_s = due_s
        self.supervisors: dict[tuple[str, str], _Supervisor] = {}
        self.parents: dict[tuple[str, str], str] = {}  # (host, child) -> its supervisor
        self.gave_up: dict[tuple[str, str], tuple[int, float, str]] = {}  # line, at, parent
        self.findings: list[Finding] = []
        self.last_at = 0.0

    def see(self, line: int, event: events.Event) -> None:
        """Take the history's next line."""
        self.last_at = max(self.last_at, event.at)
        if not isinstance(
            event,
            events.ChildStarted
            | events.ChildExited
            | events.ChildRestarted
            | events.SupervisorGaveUp,
        ):
            return
        key = (event.host, event.supervisor)
        s = self.supervisors.setdefault(key, _Supervisor())
        stopped = isinstance(event, events.ChildExited) and event.stopped
        if s.deciding is not None and not stopped:
            self._decided(key, s, gave_up=isinstance(event, events.SupervisorGaveUp))
        if s.batch is not None and not (
            isinstance(event, events.ChildRestarted) and s.pending.get(event.child) is s.batch[0]
        ):
            self._batch_ended(s)
        if isinstance(event, events.SupervisorGaveUp):
            self._unescalated(key, line, "gave up again")
            parent = self.parents.get(key)
            if parent is not None:
                self.gave_up[key] = (line, event.at, parent)
            self._never_restarted(key, s, event.at)
            self.supervisors[key] = _Supervisor()  # (it starts afresh, if restarted)
            return
        self.parents[event.host, event.child] = event.supervisor
        if isinstance(event, events.ChildStarted | events.ChildRestarted):
            self._unescalated((event.host, event.child), line, "was started again")
        if isinstance(event, events.ChildStarted):
            s.running.add(event.child)
        elif isinstance(event, events.ChildExited):
            self._exited(key, s, line, event)
        else:
            self._restarted(key, s, line, event)

    def end(self) -> None:
        """The history ended: judge what it shows already."""
        for key, s in self.supervisors.items():
            if s.deciding is not None:
                self._decided(key, s, gave_up=False, ended=True)
            if s.batch is not None:
                self._batch_ended(s)
            self._never_restarted(key, s, self.last_at)
            for first, (g, line, left) in s.owed.items():
                self._found(
                    "strategy",
                    f"supervisor {key[1]} ({g.strategy}) restarted {_names(g.members, left)}"
                    f" after {g.crashed}'s exit but never {_listed(left)} ({first} did not "
                    f"fail to start): its group, {_listed(g.members)}, restarts together",
                    (g.line, line),
                )
        for (_, nested), (line, at, parent) in self.gave_up.items():
            if self.last_at - at > ESCALATED_S:
                self._found(
                    "escalation",
                    f"supervisor {nested} gave up and its parent {parent} never saw it "
                    f"exit ({self.last_at - at:.3f} s of events after)",
                    (line,),
                )

    # -- each event ---------------------------------------------------------------------

    def _unescalated(self, nested: tuple[str, str], line: int, then: str) -> None:
        """`nested` gave up, and `then` (at `line`) before its parent took its exit."""
        gave_up = self.gave_up.pop(nested, None)
        if gave_up is not None:
            self._found(
                "escalation",
                f"supervisor {nested[1]} gave up and {then} before its parent "
                f"{gave_up[2]} saw it exit",
                (gave_up[0], line),
            )

    def _exited(
        self, key: tuple[str, str], s: _Supervisor, line: int, event: events.ChildExited
    ) -> None:
        child = event.child
        nested = (event.host, child)
        if nested in self.supervisors:  # a nested supervisor ended: it starts afresh
            inner = self.supervisors[nested]
            if inner.deciding is not None:
                self._decided(nested, inner, gave_up=False, ended=True)
            self._never_restarted(nested, inner, event.at)
            self.supervisors[nested] = _Supervisor()
        gave_up = self.gave_up.pop(nested, None)
        if gave_up is not None and event.stopped and event.at - gave_up[1] > ESCALATED_S:
            self._found(
                "escalation",
                f"supervisor {child} gave up and its parent {key[1]} stopped it "
                f"{event.at - gave_up[1]:.3f} s later without taking its exit",
                (gave_up[0], line),
            )
        s.running.discard(child)
        if event.restart:
            s.types[child] = event.restart
        if not event.strategy:
            s.exits.pop(child, None)  # (a line of schema 5 or older: not judged)
            return
        s.exits[child] = (line, event)
        if event.stopped:
            if s.deciding is not None:
                s.deciding.stops.append((line, child, event.at))
            elif s.stopped_at is None:
                s.stopped_at = event.at  # (a shutdown: the restarts due may be cancelled)
            return
        s.owed.pop(child, None)  # (its start failed: this exit decides again)
        if _restarts_after(event):
            s.deciding = _Decision(line, event, frozenset(s.running))
        else:
            s.pending.pop(child, None)

    def _decided(
        self, key: tuple[str, str], s: _Supervisor, *, gave_up: bool, ended: bool = False
    ) -> None:
        """The stops after a decision are all seen: were they its group's?"""
        decision, s.deciding = s.deciding, None
        assert decision is not None
        event = decision.event
        crashed, children = event.child, event.children
        members = children if gave_up else group(event.strategy, children, crashed)
        expected = [c for c in reversed(members) if c != crashed and c in decision.running]
        stops = decision.stops
        shown = [c for _, c, _ in stops]
        fine = shown == expected
        if ended and not fine:  # (the history ended, or a stop of them all came after)
            rest = [c for c in reversed(children) if c in decision.running and c not in expected]
            after = shown[len(expected) :]
            fine = expected[: len(shown)] == shown or (
                shown[: len(expected)] == expected and rest[: len(after)] == after
            )
        if not fine:
            what = "gave up" if gave_up else f"restarts {crashed}"
            whose = "every running child" if gave_up else f"its {event.strategy} group"
            self._found(
                "strategy",
                f"supervisor {key[1]} {what} at {crashed}'s exit and stopped "
                f"{_listed(shown) or 'none'}, not {_listed(expected) or 'none'} "
                f"({whose}, in reverse start order)",
                (decision.line, *(stop_line for stop_line, _, _ in stops)),
            )
        if gave_up:
            return
        shutdown = [at for _, c, at in stops if c not in expected]
        if shutdown and s.stopped_at is None:
            s.stopped_at = shutdown[0]  # (a stop of no group after it: a shutdown)
        back = tuple(
            m
            for m in members
            if m == crashed
            or (
                s.types.get(m) != "temporary"
                and (
                    m in decision.running
                    or m in s.pending
                    or (m in s.exits and not s.exits[m][1].stopped)
                )
            )
        )
        restarted = _Group(decision.line, event.at, crashed, event.strategy, back)
        s.pending.update(dict.fromkeys(back, restarted))

    def _restarted(
        self, key: tuple[str, str], s: _Supervisor, line: int, event: events.ChildRestarted
    ) -> None:
        child = event.child
        s.running.add(child)
        s.stopped_at = None
        exit_ = s.exits.get(child)
        restarted = s.pending.pop(child, None)
        if exit_ is None:
            return  # (its exit is of schema 5 or older, or not in the history: not judged)
        if s.types.get(child) == "temporary" or restarted is None:
            exit_line, last = exit_
            if last.stopped:
                why = "it was stopped, in no group restarted since"
            else:
                how = "a normal" if last.normal else "an abnormal"
                why = f"a {last.restart} child after {how} exit"
            self._found(
                "strategy",
                f"supervisor {key[1]} restarted {child}, which OTP leaves down: {why}",
                (exit_line, line),
            )
            return
        before = restarted.members[: restarted.members.index(child)]
        skipped = tuple(m for m in before if s.pending.get(m) is restarted)
        if skipped:
            self._found(
                "strategy",
                f"supervisor {key[1]} ({restarted.strategy}) restarted {child} before "
                f"{_listed(skipped)}: the group of {restarted.crashed}'s exit restarts "
                f"{_listed(restarted.members)}, in start order",
                (restarted.line, line),
            )
            for m in skipped:  # (found once: not owed again)
                s.pending.pop(m, None)
        s.batch = (restarted, line)

    def _never_restarted(self, key: tuple[str, str], s: _Supervisor, until: float) -> None:
        """`s` ends (gives up, is stopped, or the history ends `until`): a group due to
        restart none of which came back within `due_s` of its exit (OTP restarts it at once,
        after the backoff), nor did `s` shut down (stop a child of no group) by then."""
        until = until if s.stopped_at is None else min(until, s.stopped_at)
        seen: set[int] = set()
        for g in s.pending.values():
            if id(g) in seen or any(s.pending.get(m) is not g for m in g.members):
                continue  # (reported once; a group whose restart began is `owed`'s)
            seen.add(id(g))
            if until - g.at > self.due_s:
                self._found(
                    "strategy",
                    f"supervisor {key[1]} ({g.strategy}) never restarted "
                    f"{_listed(g.members)} after {g.crashed}'s exit, nor gave up or shut "
                    f"down, within {until - g.at:.3f} s",
                    (g.line,),
                )

    def _batch_ended(self, s: _Supervisor) -> None:
        """A group's restart ended: every member it left must have failed to start."""
        assert s.batch is not None
        restarted, line = s.batch
        s.batch = None
        left = tuple(m for m in restarted.members if s.pending.get(m) is restarted)
        if left:
            s.owed[left[0]] = (restarted, line, left)

    def _found(self, rule: str, message: str, lines: tuple[int, ...]) -> None:
        self.findings.append(Finding(rule, "violation", message, tuple(sorted(set(lines)))))


def _listed(names: Sequence[str]) -> str:
    return ", ".join(names)


def _names(members: Sequence[str], left: Sequence[str]) -> str:
    return _listed([m for m in members if m not in left]) or "none"


def strategy(history: Sequence[Line], due_s: float = DUE_S) -> tuple[list[Finding], list[Finding]]:
    """`strategy` and `escalation` as OTP defines them (`Strategies`); the two lists of findings.

    Args:
        history: the run's numbered events.
        due_s: seconds after an exit within which its group's restart must begin (`DUE_S`
            plus the plan's longest backoff).

    Not judged: schema 5 or older, a restart due less than `due_s` before the last event
    or after a child stopped outside any decision (a shutdown), a give-up less than
    `ESCALATED_S` before the last event.
    """
    judge = Strategies(due_s)
    for line, event in history:
        judge.see(line, event)
    judge.end()
    return (
        [f for f in judge.findings if f.rule == "strategy"],
        [f for f in judge.findings if f.rule == "escalation"],
    )


def backup_readable(
    history: Sequence[Line], unreadable: Mapping[str, str], *, damaged: bool
) -> list[Finding]:
    """`backup-readable`: every backup a run leaves is a catalog `read_backup` reads (rule
    15); unverifiable where the run's faults damaged backups (a damage its end kept)."""
    last = (history[-1][0],) if history else ()
    kind: Kind = "unverifiable" if damaged else "violation"
    return [
        Finding(
            "backup-readable", kind, f"the backup of {name} left by the run: {why}", last, (name,)
        )
        for name, why in sorted(unreadable.items())
    ]
