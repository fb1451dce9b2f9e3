"""The kit's own rules: what an exercise asks of a student's code that the checker's rules
(`rr_actors_lab.experiments.check.RULES`) do not judge, over the same numbered events.

Each rule takes a run's `(line, event)`s and the plan's managers' names, and gives
findings (`check.Finding`) in line order.

- `dependency` (rule 7): a call a manager makes is made while it loads a resource (so
  `CallAnswered.parent` is set): released with it, never held for nothing.
- `survives`: no supervisor gives up under the exercise's faults.
- `alone`: a crashed manager is restarted alone, no sibling stopped with it.
- `back`: a manager that exited is started again unless its supervisor gave up (a
  `temporary` child, or a `transient` one that ended normally, never is).
- `once` (rules 2, 16): a retry loads nothing while the first load holds its id: no
  second `ResourceLoaded` for a query id at a registrar unless the first's id was
  released (`ConsumerReleased`) or reported `InDoubt` before it.
- `warned` (rule 9): a provider's round of statuses (`StatusSent`s less than `ROUND_S`
  apart) names every resource of its servers that had a consumer throughout it (from
  `MARGIN_S` before to `ROUND_S` after), one status each; a round its provider's exit
  cut short is not judged.
- `loaded`: every load the run started succeeded (no `LoadFailed`).
- `kept` (rule 22): at a heal, the registrar of a name that yields is not the one that
  served a majority of the hosts during the cut.
- `holds` (rule 7; settings: a manager's name to another's, `[holds]` of the exercise):
  every resource the first loads holds a resource of the second as a dependency (an
  answer that skips the exercise by never calling it does not pass).
- `warns` (rule 9; settings: a provider's name to a server of it, `[warns]`): each load of
  that server while a resource of the provider's other servers is in use sends a status.

And one of the run's fault lines, not of its events (`faults`, `FAULTS`): each
`[[faults]]` table of the plan fired at least once in the run (the faults happen).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections import defaultdict
from collections.abc import Callable, Collection, Sequence
from typing import Any

from rr_actors import events
from rr_actors_lab.experiments import check, simulate
from rr_actors_lab.experiments.check import Finding, Line

__all__ = ["FAULTS", "MARGIN_S", "ROUND_S", "RULES", "faults", "judge"]

ROUND_S = 0.05
"""`warned`: statuses of one provider less than this many seconds apart are one round."""

MARGIN_S = 0.02
"""`warned`: a resource is owed a round's status if it had a consumer this many seconds
before the round began (one loaded meanwhile may come after the provider's listing)."""


def dependency(history: Sequence[Line], managers: Collection[str]) -> list[Finding]:
    """`dependency`: every call a manager made was a dependency of one of its resources."""
    return [
        Finding(
            "dependency",
            "violation",
            f"{e.registrar} holds {e.serving_rr}/{e.server} query {e.query_id[:8]} as a call of "
            "its own, not as a dependency of a resource it loads (no parent): nothing "
            "releases it with a resource",
            (line,),
            (e.registrar,),
        )
        for line, e in history
        if isinstance(e, events.CallAnswered) and e.registrar in managers and e.parent is None
    ]


def survives(history: Sequence[Line], managers: Collection[str]) -> list[Finding]:
    """`survives`: no supervisor gave up. A give-up is told at the crash it gave up at
    (the supervisor's last `ChildExited` before it that it did not stop itself), not at
    `SupervisorGaveUp`, published once its children stopped: what their stop leaves (a
    consumer stopped before its provider) is not the first thing wrong."""
    found = []
    crashed: dict[str, tuple[int, str]] = {}  # supervisor -> its last crash: line, child
    for line, e in history:
        if isinstance(e, events.ChildExited) and not e.stopped:
            crashed[e.supervisor] = (line, e.child)
        elif isinstance(e, events.SupervisorGaveUp):
            at, child = crashed.get(e.supervisor, (line, ""))
            said = f" at this exit of {child}" if child else ""
            found.append(
                Finding(
                    "survives",
                    "violation",
                    f"supervisor {e.supervisor} gave up{said}: {e.reason}",
                    (at,),
                    (e.supervisor, *managers),  # (its children's exits: the story before it)
                )
            )
    found.sort(key=lambda f: f.lines)
    return found


_Crash = tuple[int, events.ChildExited]
"""A supervisor's crash of a child: its line, the exit."""


def alone(history: Sequence[Line], managers: Collection[str]) -> list[Finding]:
    """`alone`: a crashed manager is restarted with no sibling stopped (its catalog restores);
    the stops of a give-up or of the run's end are not judged."""
    crashed: dict[str, _Crash] = {}  # supervisor -> its last crash
    stopped: dict[tuple[str, str], tuple[int, _Crash]] = {}  # (supervisor, child) -> stop
    found = []
    for line, e in history:
        if isinstance(e, events.ChildExited) and not e.stopped:
            crashed[e.supervisor] = (line, e)
        elif isinstance(e, events.ChildExited) and e.supervisor in crashed:
            stopped[(e.supervisor, e.child)] = (line, crashed[e.supervisor])
        elif isinstance(e, events.ChildRestarted) and (e.supervisor, e.child) in stopped:
            at, (crash_line, crash) = stopped.pop((e.supervisor, e.child))
            found.append(
                Finding(
                    "alone",
                    "violation",
                    f"supervisor {e.supervisor} stopped {e.child} to restart it with "
                    f"{crash.child}'s crash ({crash.strategy or 'its strategy'}): "
                    f"{e.child} had not crashed, and a restarted manager restores its "
                    "catalog, so its siblings need not stop",
                    (crash_line, at),
                    (e.supervisor, crash.child, e.child, *managers),
                )
            )
    found.sort(key=lambda f: f.lines)
    return found


def back(history: Sequence[Line], managers: Collection[str]) -> list[Finding]:
    """`back`: every exit of a manager (not a stop of its supervisor's) is followed by its
    restart, or by its supervisor's give-up (`survives` judges that)."""
    exited: dict[tuple[str, str], tuple[int, events.ChildExited]] = {}  # not restarted yet
    for line, e in history:
        if isinstance(e, events.ChildExited) and not e.stopped and e.child in managers:
            exited.setdefault((e.supervisor, e.child), (line, e))
        elif isinstance(e, events.ChildRestarted):
            exited.pop((e.supervisor, e.child), None)
        elif isinstance(e, events.SupervisorGaveUp):
            for key in [k for k in exited if k[0] == e.supervisor]:
                del exited[key]
    return [
        Finding(
            "back",
            "violation",
            f"supervisor {e.supervisor} never started {e.child} again after this exit "
            f"({e.reason}): its restart type is {e.restart or 'not restarted'!r} (a "
            "temporary child is never restarted, a transient one only after a crash), so "
            f"the tree went on without {e.child} to the end of the run",
            (line,),
            (e.supervisor, e.child, *managers),
        )
        for line, e in sorted(exited.values(), key=lambda item: item[0])
    ]


def once(history: Sequence[Line], managers: Collection[str]) -> list[Finding]:
    """`once`: no call loaded twice while its first load holds it (not released, not in
    doubt)."""
    del managers
    first: dict[tuple[str, str], tuple[int, str]] = {}  # (registrar, query): line, resource
    doubted: set[tuple[str, str]] = set()  # (registrar, resource id)
    found = []
    for line, e in history:
        if isinstance(e, events.InDoubt):
            doubted.add((e.registrar, e.query_id))
        elif isinstance(e, events.ConsumerReleased):
            first.pop((e.registrar, e.query_id), None)
        elif isinstance(e, events.ResourceLoaded):
            key = (e.registrar, e.query_id)
            if key in first and (e.registrar, first[key][1]) not in doubted:
                found.append(
                    Finding(
                        "once",
                        "violation",
                        f"{e.registrar}/{e.server} loaded query {e.query_id[:8]} a second "
                        f"time (resource {e.resource_id[:8]}): its first load (resource "
                        f"{first[key][1][:8]}) was committed and still held it (not released, "
                        "not in doubt), yet the retry of the same call ran the load again",
                        (first[key][0], line),
                        (e.registrar,),
                    )
                )
            first[key] = (line, e.resource_id)
    return found


Span = tuple[float, float]
"""When a resource had a consumer: from, until (seconds; `math.inf`: to the end)."""


@dataclasses.dataclass
class _Uses:
    """What `warned` reads of a run: each resource's spans in use, its server, each
    provider's rounds of statuses (line, time, resource) and its process's exits."""

    spans: dict[tuple[str, str], list[Span]] = dataclasses.field(
        default_factory=lambda: defaultdict(list)
    )
    server: dict[tuple[str, str], str] = dataclasses.field(default_factory=dict)
    rounds: dict[str, list[list[tuple[int, float, str]]]] = dataclasses.field(
        default_factory=lambda: defaultdict(list)
    )
    exits: dict[str, list[float]] = dataclasses.field(default_factory=lambda: defaultdict(list))
    users: dict[tuple[str, str], set[str]] = dataclasses.field(
        default_factory=lambda: defaultdict(set)
    )
    since: dict[tuple[str, str], float] = dataclasses.field(default_factory=dict)
    resource: dict[tuple[str, str], str] = dataclasses.field(default_factory=dict)

    def close(self, key: tuple[str, str], at: float) -> None:
        self.users.pop(key, None)
        if key in self.since:
            self.spans[key].append((self.since.pop(key), at))

    def use(self, key: tuple[str, str], query: str, at: float) -> None:
        self.resource[(key[0], query)] = key[1]
        self.since.setdefault(key, at)
        self.users[key].add(query)

    def restored(self, e: events.CatalogRestored) -> None:
        kept = {(e.registrar, str(held)) for _query, held, _consumer in e.consumers}
        for key in [k for k in self.since if k[0] == e.registrar and k not in kept]:
            self.close(key, e.at)
        for key in kept:
            self.users.pop(key, None)
        for query, held, _consumer in e.consumers:
            self.use((e.registrar, str(held)), str(query), e.at)

    def sent(self, line: int, e: events.StatusSent) -> None:
        mine = self.rounds[e.registrar]
        if not mine or e.at - mine[-1][-1][1] >= ROUND_S:
            mine.append([])
        mine[-1].append((line, e.at, self.resource.get((e.registrar, e.query_id), "")))

    def read(self, history: Sequence[Line]) -> _Uses:
        for line, e in history:
            if isinstance(e, events.ResourceLoaded):
                self.server[(e.registrar, e.resource_id)] = e.server
            elif isinstance(e, events.ConsumerAdded):
                self.use((e.registrar, e.resource_id), e.query_id, e.at)
            elif isinstance(e, events.ConsumerReleased):
                key = (e.registrar, e.resource_id)
                self.users[key].discard(e.query_id)
                if not self.users[key]:
                    self.close(key, e.at)
            elif isinstance(e, events.ResourceUnloaded):
                self.close((e.registrar, e.resource_id), e.at)
            elif isinstance(e, events.InDoubt):
                self.close((e.registrar, e.query_id), e.at)
            elif isinstance(e, events.CatalogRestored) and e.complete:  # (what it kept)
                self.restored(e)
            elif isinstance(e, events.ChildExited):
                self.exits[e.child].append(e.at)
            elif isinstance(e, events.StatusSent):
                self.sent(line, e)
        for key in list(self.since):
            self.close(key, math.inf)
        return self


def warned(history: Sequence[Line], managers: Collection[str]) -> list[Finding]:
    """`warned`: each round of a provider's statuses names every resource in use."""
    del managers
    uses = _Uses().read(history)
    found = []
    for registrar, mine in uses.rounds.items():
        for sends in mine:
            begun, ended = sends[0][1], sends[-1][1]
            if any(begun <= at <= ended + ROUND_S for at in uses.exits[registrar]):
                continue  # (a kill cut the round short: its provider sends no more)
            named = {r for _, _, r in sends}
            servers = {uses.server.get((registrar, r)) for r in named}
            owed = sorted(
                r
                for (who, r), spans in uses.spans.items()
                if who == registrar
                and r not in named
                and uses.server.get((who, r)) in servers
                and any(a <= begun - MARGIN_S and b > ended + ROUND_S for a, b in spans)
            )
            if owed:
                found.append(
                    Finding(
                        "warned",
                        "violation",
                        f"{registrar} sent {len(sends)} status(es) in a round, about "
                        f"{len(named)} resource(s) of {len(named) + len(owed)} in use: "
                        f"the consumers of {', '.join(r[:8] for r in owed)} never heard "
                        "of it (a status reaches the consumers of the resource behind "
                        "the id it names, no other)",
                        (sends[-1][0],),
                        (registrar,),
                    )
                )
    found.sort(key=lambda f: f.lines)
    return found


def loaded(history: Sequence[Line], managers: Collection[str]) -> list[Finding]:
    """`loaded`: no load failed."""
    del managers
    return [
        Finding(
            "loaded",
            "violation",
            f"{e.registrar}/{e.server}'s load for query {e.query_id[:8]} raised "
            f"{e.error_type}: {e.message}",
            (line,),
            (e.registrar,),
        )
        for line, e in history
        if isinstance(e, events.LoadFailed)
    ]


def kept(history: Sequence[Line], managers: Collection[str]) -> list[Finding]:
    """`kept`: no registrar that served a majority of the hosts during a cut yields."""
    hosts = {e.host for _, e in history}
    lives: dict[tuple[str, int], tuple[int, str]] = {}  # (name, pid) -> first line, host
    ended: dict[tuple[str, int], int] = {}  # (name, pid) -> the line of its exit
    added: dict[tuple[str, int], list[tuple[int, str]]] = defaultdict(list)  # line, consumer
    asked: dict[tuple[str, str], tuple[int, tuple[str, int]]] = {}  # not answered yet
    yielded: dict[tuple[str, int], list[int]] = defaultdict(list)  # lines of its releases
    host_of: dict[str, str] = {}  # a consumer registrar -> its host
    yields: list[tuple[int, events.ChildExited]] = []
    for line, e in history:
        name = getattr(e, "registrar", None)
        if isinstance(name, str) and name in managers and isinstance(getattr(e, "pid", None), int):
            lives.setdefault((name, e.pid), (line, e.host))
        if isinstance(e, events.ConsumerAdded):
            asked[(e.consumer, e.query_id)] = (line, (e.registrar, e.pid))
        elif isinstance(e, events.CallAnswered):  # (an acknowledgement its consumer heard)
            host_of[e.registrar] = e.host
            if (e.registrar, e.query_id) in asked:
                at, life = asked.pop((e.registrar, e.query_id))
                added[life].append((at, e.registrar))
        elif isinstance(e, events.ConsumerReleased) and e.reason == "name yielded":
            yielded[(e.registrar, e.pid)].append(line)
        elif isinstance(e, events.ChildExited) and e.child in managers:
            if e.normal and not e.stopped and e.reason == "normal":
                yields.append((line, e))
            ended.setdefault((e.child, e.pid), line)

    def side(life: tuple[str, int], since: int, until: int) -> set[str]:
        """Its host and the hosts of the consumers it acknowledged between two lines."""
        acked = {host_of.get(c, "") for n, c in added[life] if since < n <= until}
        return {lives[life][1]} | acked - {""}

    found = []
    for line, e in yields:
        mine = (e.child, e.pid)
        rivals = [
            life
            for life, (first, _host) in lives.items()
            if life[0] == e.child
            and life[1] != e.pid
            and first < line
            and ended.get(life, line + 1) > line
        ]
        if mine not in lives or not rivals:
            continue
        other = rivals[0]
        since = max(lives[mine][0], lives[other][0])  # (both served from here: the cut)
        until = max((n for n, _ in added[mine]), default=since)  # (its last: the cut's end)
        served, theirs = side(mine, since, until), side(other, since, until)
        if 2 * len(served) <= len(hosts):
            continue
        undone = yielded[mine]
        acked = sum(1 for n, _ in added[mine] if n > since)
        found.append(
            Finding(
                "kept",
                "violation",
                f"at the heal, {e.child} of host {lives[mine][1]}, which served hosts "
                f"{', '.join(sorted(served))} during the cut ({len(served)} of {len(hosts)}: "
                f"the majority, {acked} load(s) acknowledged), yielded to {e.child} of host "
                f"{lives[other][1]}, which served {', '.join(sorted(theirs))}: the minority's "
                f"registrar was kept, and {len(undone)} load(s) the majority still held were "
                "undone (FATAL to their consumers)",
                (min(undone, default=line),),
                (e.child,),
            )
        )
    found.sort(key=lambda f: f.lines)
    return found


def holds(history: Sequence[Line], managers: Collection[str], /, **held: str) -> list[Finding]:
    """`holds`: every resource a manager of `held` loads holds, as a dependency, a resource
    of the manager `held` names for it (a call of its load answered before it loaded)."""
    del managers
    answered: set[tuple[str, str]] = set()  # (registrar, parent resource) with a dependency
    found = []
    for line, e in history:
        if isinstance(e, events.CallAnswered) and held.get(e.registrar) == e.serving_rr:
            if e.parent is not None:
                answered.add((e.registrar, e.parent))
        elif (
            isinstance(e, events.ResourceLoaded)
            and e.registrar in held
            and (e.registrar, e.resource_id) not in answered
        ):
            found.append(
                Finding(
                    "holds",
                    "violation",
                    f"{e.registrar}/{e.server} loaded resource {e.resource_id[:8]} "
                    f"without holding anything of {held[e.registrar]}: its load made no "
                    f"call to {held[e.registrar]}, so no dependency keeps what it needs",
                    (line,),
                    (e.registrar,),
                )
            )
    return found


def warns(history: Sequence[Line], managers: Collection[str], /, **servers: str) -> list[Finding]:
    """`warns`: each load of a provider's warning server (`servers`: provider -> server)
    while a resource of its other servers was in use throughout the `ROUND_S` before it
    (and the provider did not exit meanwhile) comes after a status the provider sent in
    that time."""
    del managers
    uses = _Uses().read(history)
    sent: dict[str, list[float]] = defaultdict(list)
    found = []
    for line, e in history:
        if isinstance(e, events.StatusSent):
            sent[e.registrar].append(e.at)
        elif isinstance(e, events.ResourceLoaded) and servers.get(e.registrar) == e.server:
            since = e.at - ROUND_S
            if any(since - MARGIN_S <= at <= e.at for at in uses.exits[e.registrar]):
                continue  # (its provider restarted meanwhile: what it had in use is new)
            in_use = [
                r
                for (who, r), spans in uses.spans.items()
                if who == e.registrar
                and uses.server.get((who, r)) != e.server
                and any(a <= since - MARGIN_S and b >= e.at for a, b in spans)
            ]
            if in_use and not any(since <= at <= e.at for at in sent[e.registrar]):
                found.append(
                    Finding(
                        "warns",
                        "violation",
                        f"{e.registrar}/{e.server} loaded {e.resource_id[:8]} while "
                        f"{len(in_use)} resource(s) of its other servers were in use, and "
                        "sent no status about any of them: their consumers never heard",
                        (line,),
                        (e.registrar,),
                    )
                )
    return found


FAULTS = "faults"
"""The rule of the run's fault lines (`faults`): not in `RULES`, which read its events."""


def faults(lines: Sequence[str], tables: int) -> list[Finding]:
    """`faults`: each of the plan's `tables` `[[faults]]` tables fired at least once among a
    run's history `lines` (a `FaultInjected` line of that `fault`)."""
    fired: set[int] = set()
    skipped: dict[int, str] = {}
    for text in lines:
        if '"Fault' not in text:
            continue
        line = json.loads(text)
        if line.get("type") == "FaultInjected":
            fired.add(int(line["fault"]))
        elif line.get("type") == "FaultSkipped":
            skipped.setdefault(int(line["fault"]), f"{line.get('kind')}: {line.get('detail')}")
    return [
        Finding(
            FAULTS,
            "violation",
            f"the plan's fault #{index + 1} never happened in this run"
            + (f" (skipped, {skipped[index]})" if index in skipped else "")
            + ": the exercise is to hold out under its faults, not without them",
            (),
            (),
        )
        for index in range(tables)
        if index not in fired
    ]


RULES: dict[str, Callable[..., list[Finding]]] = {
    "dependency": dependency,
    "survives": survives,
    "alone": alone,
    "back": back,
    "once": once,
    "warned": warned,
    "loaded": loaded,
    "kept": kept,
    "holds": holds,
    "warns": warns,
}
"""The kit's rules by name (what an exercise's `rules` lists, with `FAULTS`): each takes the
run's numbered events and the plan's managers' names, and the exercise's settings of it
(`[holds]`, `[warns]`) as keywords."""


def judge(
    history: str,
    names: Sequence[str],
    options: dict[str, dict[str, Any]],
    managers: Collection[str],
    resolve: str,
    tables: int,
) -> tuple[list[Line], list[Finding]]:
    """A run's numbered events and its violations, the first broken first: the checker's
    (by the plan's rule 22 policy `resolve`), then the kit's `names` (with their `options`,
    `FAULTS` over the plan's `tables` of faults).

    Raises:
        ConfigError: a line of `history` is not an event's (`check.read_runs`).
    """
    lines = history.splitlines()
    numbered = check.read_runs(lines).get(simulate.RUN, [])
    verdict = check.check(numbered, resolve)
    found = [f for f in verdict.findings if f.kind == "violation"]
    for name in names:
        if name == FAULTS:
            found += faults(lines, tables)
        else:
            found += RULES[name](numbered, managers, **options.get(name, {}))
    # (broken at its last event; a fault that never happened: at the run's end)
    found.sort(key=lambda f: max(f.lines, default=len(numbered) + 1))
    return numbered, found
