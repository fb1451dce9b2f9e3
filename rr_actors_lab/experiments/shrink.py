"""Shrink a violating seed to a small plan that still violates the same way (`--shrink`).

```
 shrink(plan, seed) ─ the seed's run: its first violation's kind (`violation_kind`: the
 │                    message, ids and numbers blotted out; the checker's or a `judge`'s)
 ├─ the plan as TOML data; its timed faults made explicit (one atom per injection)
 ├─ greedy passes, biggest cuts first, until the budget of runs is spent or a round at
 │  the widest search keeps nothing: supervisors, duration, shift, faults (delta
 │  debugging), pinned, triggers, idle, unpinned, tree, workload, options, knobs, made
 │  (the clients' calls, `workload.only`: a client's all, those about none of the
 │  finding's ids, then delta debugging), seeds, round (each pass: docs/how-to/simulate.md,
 │  "Shrink it")
 │  a candidate = its TOML text, validated (`parse_plan`) and run whole on the simulation
 │  with the current seed, then seeds 1, 2, ... (`tries`; the width grows 4 times at each
 │  fixpoint, up to `MOST_TRIES`); kept if one run shows the same kind and is smaller:
 │  a shorter story (`story_events`: the events up to its finding, when the checker finds
 │  the same violation without the rest), then fewer events, then a shorter text
 │  (shortlex, so the passes end)
 ◄── Shrunk: the plan's text, its seed, its run (history, hash, events), the kind
 write(shrunk, out): out/plan.toml (a header says what it shows), out/seeds.jsonl,
                     out/events-seed-S.jsonl: a run directory `rr-actors replay` reads
```
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import itertools
import json
import logging
import re
import time
import tomllib
from collections.abc import Callable, Collection, Iterator
from pathlib import Path
from typing import Any

from rr_actors.errors import ConfigError
from rr_actors_lab.experiments import check, simulate
from rr_actors_lab.experiments.plan import EVENT_TYPES, Plan
from rr_actors_lab.experiments.reading import parse_plan
from rr_actors_lab.experiments.schedule import fault_schedule

__all__ = [
    "BUDGET",
    "TRIES",
    "Judge",
    "Shrunk",
    "dump_plan",
    "shrink",
    "story",
    "story_events",
    "violation_kind",
    "violation_kinds",
    "violations",
    "write",
]

BUDGET = 2500
"""The most simulated runs one shrink makes (each seed of each candidate is one)."""

TRIES = 3
"""How many seeds a candidate runs with at first: the current one, then 1, 2, ..."""

WIDEN = 4
"""At a fixpoint, a candidate runs with this many times as many seeds from then on."""

MOST_TRIES = 1000
"""The most seeds a candidate runs with (the widest search: its fixpoint ends a shrink).

Any change of the plan gives another interleaving, so a violation that needs a rare one
is lost under the seed alone and found again under a few (a few hundred for a rare race).
"""

SHUFFLED = 12
"""The fewest seeds a candidate that drops a process or changes a client's draws runs with."""

CLIENT_TRIES = 24
"""The fewest seeds a candidate that drops a client (all its calls) runs with: a client
fewer is a big cut, worth a wider search than a number's (unload-held's was found again
at seed 20 only)."""

SEEDS = 20
"""The seeds the seed pass runs the current plan with: 1 to this (or the width)."""

KNOB_SCALES = (0.25, 0.5, 2, 4)
"""What the knobs pass multiplies a number by (after trying 0): smaller and larger both (a
longer interval makes fewer events as a smaller count does)."""

PINS = 3
"""How many of the events just before a timed injection the pinned pass tries to fire it
after (each distinct: its type and the names it carries)."""

CUT_S = 0.01
"""Seconds after an injection whose events say what it cut (the pinned pass)."""

MARGIN = 0.05
"""Seconds of the run kept after the violation, when the duration is cut there."""

NARROW = 0.005
"""The same, tried first: what comes after the violation is the end of the run (the calls
still on their way failing at the end, say), unless the violation needs more of it."""

_NOT_RUN = ("description", "repeat", "seed")
"""Top-level keys a simulated run does not read (its seed is the sweep's): left out."""

_TIMED_KEYS = ("at", "every", "start", "stop", "count")
"""A fault's keys of when it fires: an explicit injection keeps only `at`."""

_PIN_FIELDS = ("registrar", "consumer", "serving_rr", "child")
"""The fields of an event a pinned injection's trigger matches: the managers it names
(never ids, nor a client: its name is gone once the workload has fewer clients)."""

_ID_FIELDS = ("query_id", "resource_id")
"""The fields naming what an event is about: an event before an injection about what one
just after it is about began what the injection cut (a call whose release it lost)."""

_NOT_KNOBS = frozenset({"at", "max_restarts"})
"""The numbers the knobs pass leaves alone (the other passes move them)."""


@dataclasses.dataclass(frozen=True)
class Shrunk:
    """A shrunk run: a plan, a seed, and their run showing the violation kind again.

    Attributes:
        text: the shrunk plan's TOML (what `write` puts in `plan.toml`, without its header).
        plan: that text, parsed (its `source` the original's: its setups' folder).
        seed: the seed the shrunk plan violates with.
        run: its run (history, hash, events, findings).
        kind: the violation kind kept (`violation_kind`).
        original_seed: the seed shrunk.
        original_events: the events of the original run.
        runs: the simulated runs the shrink made.
        steps: what each kept candidate changed, in order.
        story: the events of `run` its story shows (`story_events`: those up to its
            finding, when the checker finds the same violation without the rest).
    """

    text: str
    plan: Plan
    seed: int
    run: simulate.SimulatedRun
    kind: str
    original_seed: int
    original_events: int
    runs: int
    steps: tuple[str, ...]
    story: int = 0


def violation_kind(rule: str, message: str) -> str:
    """`[rule] message` with ids and numbers blotted out: the same bug in another run
    (`"[end] db still holds query … of api, which stopped"`)."""
    text = re.sub(r"\b[0-9a-f]{8}\b", "…", message)
    text = re.sub(r"[0-9]+(?:\.[0-9]+)?", "N", text)
    return f"[{rule}] {text}"


Judge = Callable[[simulate.SimulatedRun], list[check.Finding]]
"""What a run violates: its findings of kind `"violation"`, the one to shrink first."""


def violations(run: simulate.SimulatedRun, resolve: str = "first_served") -> list[check.Finding]:
    """The checker's violations of a run (none unless it violated): the default `Judge`
    (`shrink` gives it its plan's rule 22 policy, `resolve`, as `simulate` checks it)."""
    if run.verdict != "violated":
        return []
    numbered = check.read_runs(run.history.splitlines()).get(simulate.RUN, [])
    verdict = check.check(numbered, resolve)
    return [f for f in verdict.findings if f.kind == "violation"]


def violation_kinds(run: simulate.SimulatedRun, judge: Judge = violations) -> list[str]:
    """The kinds of a run's violations as `judge` orders them (none if held); a crashed
    run's one: `[crashed] Type: message` (ids and numbers blotted out)."""
    if run.verdict == "crashed":
        crash = json.loads(run.history.splitlines()[-1])
        return [violation_kind("crashed", f"{crash['error_type']}: {crash['message']}")]
    return list(dict.fromkeys(violation_kind(f.rule, f.message) for f in judge(run)))


def story_events(run: simulate.SimulatedRun, kind: str, judge: Judge = violations) -> int:
    """How many of a run's events its story shows: those up to the last line of `kind`'s
    first finding, if the checker finds `kind` in that cut history and no violation the
    whole run does not have; else every one (a crashed run's, a run without `kind`).

    What comes after a finding at its instant is the run going on to its end (restarts
    failing again on the same bug, the supervisor giving up, the tree stopping, what the
    clients held released), which a cut of the duration cannot drop. The finding does not
    need it when the checker, judging the cut history as a whole run, gives the same
    violation. A rule judged at the run's end names a line there, so nothing of it is
    cut; a cut that makes another violation (an id left held where the history stops)
    tells another story, and the whole run is kept.
    """
    if run.verdict == "crashed":
        return run.events
    finding = next((f for f in judge(run) if violation_kind(f.rule, f.message) == kind), None)
    if finding is None:
        return run.events
    last = max((n for n in finding.lines if 0 < n <= run.events), default=run.events)
    if last >= run.events:
        return run.events
    cut = dataclasses.replace(run, history=_cut(run, last), events=last)
    kinds = violation_kinds(cut, judge)
    if kind not in kinds or not set(kinds) <= set(violation_kinds(run, judge)):
        return run.events
    return last


def story(run: simulate.SimulatedRun, kind: str, judge: Judge = violations) -> str:
    """A run's history as its story shows it: its first `story_events` events, then the
    lines of the faults injected by the last of them."""
    return _cut(run, story_events(run, kind, judge))


def _cut(run: simulate.SimulatedRun, events: int) -> str:
    """The run's first `events` events' lines, then those of its faults injected by then."""
    lines = run.history.splitlines(keepends=True)
    if events >= run.events:
        return run.history
    kept = lines[:events]
    until = json.loads(kept[-1])["at"] if kept else float("-inf")
    faults = [
        line
        for line in lines[run.events :]
        if (at := json.loads(line).get("at")) is not None and at <= until
    ]
    return "".join(kept + faults)


# -- the plan as TOML data, and back ----------------------------------------------------------

_SECTIONS = frozenset({"tree", "workload", "hosts", "compare"})
"""The top-level keys written as `[tables]`."""
_ARRAYS = frozenset({"children", "calls", "faults"})
"""The keys whose tables are written as `[[arrays of tables]]`."""


def dump_plan(data: dict[str, Any]) -> str:
    """A plan's TOML data (as `tomllib` reads it) as TOML text that reads back to it.

    Raises:
        ConfigError: a value TOML cannot write (`None`, a date is not a plan's).
    """
    lines: list[str] = []
    _table(lines, data, "", top=True)
    return "\n".join(lines).strip() + "\n"


def _table(lines: list[str], table: dict[str, Any], path: str, *, top: bool = False) -> None:
    def nested(key: str, value: Any) -> bool:
        if top and key in _SECTIONS and isinstance(value, dict):
            return True
        return (
            key in _ARRAYS
            and isinstance(value, list)
            and bool(value)
            and all(isinstance(v, dict) for v in value)
        )

    for key, value in table.items():
        if not nested(key, value):
            lines.append(f"{_key(key)} = {_value(value)}")
    for key, value in table.items():
        if not nested(key, value):
            continue
        name = f"{path}.{_key(key)}" if path else _key(key)
        for item in value if isinstance(value, list) else [value]:
            lines.extend(["", f"[[{name}]]" if isinstance(value, list) else f"[{name}]"])
            _table(lines, item, name)


def _key(key: str) -> str:
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else json.dumps(key)


def _value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, list | tuple):
        return f"[{', '.join(map(_value, value))}]"
    if isinstance(value, dict):
        inner = ", ".join(f"{_key(k)} = {_value(v)}" for k, v in value.items())
        return f"{{ {inner} }}" if inner else "{}"
    raise ConfigError(f"a plan value TOML cannot write: {value!r}")


def _dump_atoms(data: dict[str, Any]) -> dict[str, Any]:
    """The data with its fault atoms grouped back into `[[faults]]` tables: the explicit
    injections of one kind, target and settings as one table with their `at` times."""
    tables: list[dict[str, Any]] = []
    groups: dict[str, dict[str, Any]] = {}
    for atom in data.get("faults", []):
        at = atom.get("at")
        if not isinstance(at, int | float):  # a fault kept whole
            tables.append(atom)
            continue
        rest = {k: v for k, v in atom.items() if k != "at"}
        group = groups.setdefault(json.dumps(rest, sort_keys=True), {**rest, "at": []})
        if not group["at"]:
            tables.append(group)
        group["at"].append(at)
    for group in groups.values():
        group["at"] = sorted(group["at"])
    out = {k: v for k, v in data.items() if k != "faults"}
    return out | ({"faults": tables} if tables else {})


# -- the shrink ---------------------------------------------------------------------------------


def shrink(
    plan: Plan,
    seed: int,
    *,
    budget: int = BUDGET,
    tries: int = TRIES,
    on_step: Callable[[str], None] | None = None,
    on_run: Callable[[int], None] | None = None,
    text: str | None = None,
    judge: Judge = violations,
    cpu_until: float | None = None,
    keep: Collection[str] = (),
) -> Shrunk:
    """Shrink `plan` at `seed` (a violating run) to a small plan that violates the same way.

    Args:
        plan: a plan read from a file or text (its `source` names where its setups are).
        seed: a seed it violates with.
        budget: the most simulated runs to make (at least 1: the seed's own).
        tries: seeds per candidate at first (the current seed, then 1, 2, ...); four
            times as many after each fixpoint, up to `MOST_TRIES`.
        on_step: called with a line for each kept candidate (progress).
        on_run: called with the number of runs made after each run (a progress bar).
        text: the plan's TOML (default: its file's; a run directory's copy, say).
        judge: what a run violates (default: the checker's rules; a kit's rules too,
            `rr_actors_lab.teach.grade`): the first of the seed's run is the kind kept.
        cpu_until: a `time.process_time()` after which no run starts (the budget
            spent then, if not before: a check's bound of CPU seconds).
        keep: parts of the plan left as written, dotted keys of its TOML (`"tree"`: its
            supervisors, their settings, each child's place and restart type, not the
            managers' options; `"hosts.resolve"`): a candidate that changes one is not
            tried (a classroom check keeps the student's part, `rr_actors_lab.teach`).

    Returns:
        The smallest plan found, its seed and run.

    Raises:
        ConfigError: no `text` and the plan was not read from a file, the seed does not
            violate, `budget` or `tries` below 1, or `text` is not the plan's.
        RrError: a run failed (as `simulate.run_seed`).
    """
    if budget < 1 or tries < 1:
        raise ConfigError(f"the budget and the tries must be at least 1 (got {budget}, {tries})")
    if text is None and plan.source is None:
        raise ConfigError("give the plan's text: it is what a shrink starts from")
    if text is None:
        text = Path(str(plan.source)).read_text(encoding="utf-8")
    say = on_step or (lambda _line: None)
    ran = on_run or (lambda _runs: None)
    if judge is violations:  # (by the plan's rule 22 policy, as its runs were checked)
        resolve = plan.hosts.resolve if plan.hosts is not None else "first_served"
        judge = functools.partial(violations, resolve=resolve)
    shrinker = _Shrinker(plan, seed, text, budget, tries, say, ran, judge, cpu_until)
    shrinker.kept = {part: _part(shrinker.data, part) for part in keep}
    return shrinker.run()


class _Shrinker:
    """The state of one shrink: the smallest violating candidate so far and the runs made."""

    def __init__(
        self,
        plan: Plan,
        seed: int,
        text: str,
        budget: int,
        tries: int,
        say: Callable[[str], None],
        ran: Callable[[int], None],
        judge: Judge = violations,
        cpu_until: float | None = None,
    ) -> None:
        self.source = plan.source or "<plan>"
        self.judge, self.cpu_until = judge, cpu_until
        self.budget, self.tries, self.say, self.ran = budget, tries, say, ran
        self.runs = 0
        self.width = tries  # seeds a candidate runs with at most (`attempt`)
        self.tried: set[tuple[str, int]] = set()
        self.steps: list[str] = []
        first = self.run_one(plan, seed)
        kinds = violation_kinds(first, judge)
        if not kinds:
            raise ConfigError(f"seed {seed} does not violate a rule: nothing to shrink")
        self.kind, self.original_seed, self.original_events = kinds[0], seed, first.events
        try:
            self.data: dict[str, Any] = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"the plan's text is not TOML: {exc}") from exc
        for key in _NOT_RUN:
            self.data.pop(key, None)
        self.data["duration"] = plan.duration  # (a run directory's may differ from its file's)
        self.plan, self.seed, self.best = plan, seed, first
        self.best_size = self.size(first)
        self.kept: dict[str, Any] = {}  # (dotted keys left as written: their values)
        self.say(f"shrinking seed {seed} ({first.events} events): {self.kind}")

    def run_one(self, plan: Plan, seed: int) -> simulate.SimulatedRun:
        logger = logging.getLogger("rr_actors")
        level = logger.level
        logger.setLevel(logging.CRITICAL)  # (a candidate's supervisor giving up: not news)
        try:
            run = simulate.run_seed(plan, seed)
        finally:
            logger.setLevel(level)
        self.runs += 1
        if self.cpu_until is not None and time.process_time() >= self.cpu_until:
            self.budget = min(self.budget, self.runs)  # (its CPU spent: no run after this)
        self.ran(self.runs)
        return run

    def run(self) -> Shrunk:
        self.explicit()
        passes = (
            self.supervisors,
            self.durations,
            self.shift,
            self.faults,
            self.pinned,
            self.triggers,
            self.idle,
            self.unpinned,
            self.tree,
            self.workload,
            self.options,
            self.knobs,
            self.made,
            self.seeds,
            self.rounded,
        )
        while self.runs < self.budget:
            before = len(self.steps)
            for step in passes:
                step()
            if len(self.steps) > before:
                continue
            if self.width >= MOST_TRIES:
                break  # (a fixpoint at the widest search)
            self.width = min(self.width * WIDEN, MOST_TRIES)
            self.say(f"run {self.runs}: a fixpoint: {self.width} seeds a candidate from here")
        spent = self.runs >= self.budget
        left = f"the budget ({self.budget} runs) spent" if spent else "a fixpoint"
        self.say(
            f"done after {self.runs} runs ({left}): {self.best.events} events, "
            f"its story {self.best_size[0]}"
        )
        return Shrunk(
            text=self.text(self.data),
            plan=self.plan,
            seed=self.seed,
            run=self.best,
            kind=self.kind,
            original_seed=self.original_seed,
            original_events=self.original_events,
            runs=self.runs,
            steps=tuple(self.steps),
            story=self.best_size[0],
        )

    def text(self, data: dict[str, Any]) -> str:
        return dump_plan(_dump_atoms(data))

    def attempt(
        self, what: str, data: dict[str, Any], *, same: bool = False, width: int | None = None
    ) -> bool:
        """Run the candidate `data` (up to `width` seeds); keep it if it shows the kind and is
        `smaller`."""
        if any(_part(data, part) != value for part, value in self.kept.items()):
            return False  # (it changes what is kept as written: not a candidate)
        text = self.text(data)
        try:
            plan = parse_plan(text, source=self.source, name=self.plan.name)
        except ConfigError:
            return False  # (a cut that left the plan invalid: not a candidate)
        for seed in self.candidate_seeds(self.width if width is None else width):
            if self.runs >= self.budget:
                return False
            if (text, seed) in self.tried:
                continue
            self.tried.add((text, seed))
            run = self.run_one(plan, seed)
            if self.kind not in violation_kinds(run, self.judge):
                continue
            size = self.size(run)
            if (size <= self.best_size) if same else self.smaller(size, text):
                self.data, self.plan, self.seed, self.best = data, plan, seed, run
                self.best_size = size
                self.steps.append(what)
                self.say(f"run {self.runs}: {what}: {self.shown(size)} (seed {seed})")
                return True
        return False

    def size(self, run: simulate.SimulatedRun) -> tuple[int, int]:
        """What a shrink makes smaller: the events of a run's story (`story_events`), then
        all its events."""
        return story_events(run, self.kind, self.judge), run.events

    def shown(self, size: tuple[int, int]) -> str:
        story, events = size
        return f"{events} events" + (f" (its story {story})" if story < events else "")

    def candidate_seeds(self, width: int) -> Iterator[int]:
        """The current seed, then 1, 2, ...: `width` seeds in all."""
        yield self.seed
        yield from itertools.islice((s for s in itertools.count(1) if s != self.seed), width - 1)

    def smaller(self, size: tuple[int, int], text: str) -> bool:
        """A shorter story (`size`); as long and fewer events; as many and a shorter text,
        or one as long that sorts first (the shortlex order: every kept candidate is
        smaller, so the passes end)."""
        best = self.text(self.data)
        return (*size, len(text), text) < (*self.best_size, len(best), best)

    def shuffled(self) -> int:
        """The seeds a candidate with fewer processes or other draws runs with: at least
        `SHUFFLED` (it changes the scheduler's every choice as another seed does)."""
        return max(self.width, SHUFFLED)

    def first(
        self, candidates: Iterator[tuple[str, dict[str, Any]]], width: int | None = None
    ) -> bool:
        """Try `candidates` in order until one is kept."""
        return any(self.attempt(what, data, width=width) for what, data in candidates)

    def repeat(
        self,
        candidates: Callable[[], Iterator[tuple[str, dict[str, Any]]]],
        width: int | None = None,
    ) -> None:
        """Try the candidates of the current best again after each one kept."""
        while self.runs < self.budget and self.first(candidates(), width):
            pass

    # -- the passes --------------------------------------------------------------------------

    def explicit(self) -> None:
        """Every timed fault as the injections this seed made: one atom per injection."""
        faults = self.data.get("faults", [])
        schedule = fault_schedule(self.plan, self.seed)
        atoms: list[dict[str, Any]] = []
        for index, fault in enumerate(faults):
            if "after" in fault:
                atoms.append(fault)
                continue
            rest = {k: v for k, v in fault.items() if k not in (*_TIMED_KEYS, "target")}
            for injection in (s for s in schedule if s.fault == index):
                target = {} if injection.target is None else {"target": injection.target}
                atoms.append({**rest, **target, "at": injection.at})
        data = {**self.data, "faults": atoms}
        if not faults or self.text(data) == self.text(self.data):
            self.data = data
            return
        if not self.attempt(f"faults made explicit ({len(atoms)} injections)", data, same=True):
            self.say("faults kept as they are: made explicit, the run did not violate")
            # (ddmin then deletes whole faults)

    def faults(self) -> None:
        """Delete injections: chunks of halves, then quarters, ... then single ones."""
        self.chunks(
            lambda data: data.get("faults", []),
            lambda data, kept: {**data, "faults": kept},
            "injections",
        )

    def made(self) -> None:
        """The clients' calls made explicit (`workload.only`: each client's calls due, by
        number), then deleted: a client's all, those about none of the finding's ids, then
        as the injections are; a call left out still makes its draws, so the calls kept
        come when and as they came."""
        workload = self.data.get("workload")
        if not workload or not workload.get("calls"):
            return
        clients = workload.get("clients", _DEFAULTS["clients"])
        if "only" not in workload:
            if not clients:
                return
            counts = _calls_made(self.best.history, workload.get("awaited", 0))
            only = [[c, n] for c in range(clients) for n in range(1, counts.get(c, 0) + 2)]
            data = {**self.data, "workload": {**workload, "only": only}}
            if not self.attempt(f"the calls made explicit ({len(only)} calls)", data, same=True):
                return
        self.repeat(self.fewer_clients, max(self.width, CLIENT_TRIES))
        self.repeat(self.unrelated_calls, max(self.width, CLIENT_TRIES))
        self.chunks(
            lambda data: data["workload"]["only"],
            lambda data, kept: {**data, "workload": {**data["workload"], "only": kept}},
            "calls",
            self.shuffled(),  # (fewer calls: every choice of the scheduler another)
        )

    def fewer_clients(self) -> Iterator[tuple[str, dict[str, Any]]]:
        """One client's calls deleted (all of them: it is not started), each client in turn,
        the one with the most calls first; then the clients numbered again from 0, as many
        as make calls (the plan reads `clients = 2`, not 3 with client 0 making none).

        The calls pass deletes evenly split blocks; a client's calls are not one, and its
        loss changes every choice of the scheduler: `CLIENT_TRIES` seeds each at least."""
        workload = self.data["workload"]
        only = [list(pair) for pair in workload["only"]]
        calls: dict[int, int] = {}
        for client, _ in only:
            calls[client] = calls.get(client, 0) + 1
        for client in sorted(calls, key=lambda c: (-calls[c], c)) if len(calls) > 1 else []:
            kept = [pair for pair in only if pair[0] != client]
            data = {**self.data, "workload": {**workload, "only": kept}}
            yield f"client {client}'s calls deleted ({calls[client]} calls)", data
        number = {client: index for index, client in enumerate(sorted(calls))}
        if len(number) < workload.get("clients", _DEFAULTS["clients"]):
            renumbered = [[number[client], n] for client, n in only]
            data = {
                **self.data,
                "workload": {**workload, "clients": len(number), "only": renumbered},
            }
            yield f"workload.clients = {len(number)} (the clients making calls, from 0)", data

    def unrelated_calls(self) -> Iterator[tuple[str, dict[str, Any]]]:
        """The calls about none of the finding's ids deleted: all of them, then those about one
        resource (the most first), each group a cut the calls pass's even blocks miss.

        A call is about the ids its events name (its query's, the resource it loaded or
        shared); the finding's are those its lines name, with the resources of its queries.
        One may still be needed (the call to db a kill waits for): the run decides."""
        workload = self.data["workload"]
        finding = next(
            (f for f in self.judge(self.best) if violation_kind(f.rule, f.message) == self.kind),
            None,
        )
        if finding is None:
            return
        only = [list(pair) for pair in workload["only"]]
        groups = _unrelated(self.best.history, finding.lines, only, workload.get("awaited", 0))
        every = [pair for group in groups for pair in group]
        cuts = ([every] if len(groups) > 1 else []) + groups
        for cut in cuts:
            kept = [pair for pair in only if pair not in cut]
            data = {**self.data, "workload": {**workload, "only": kept}}
            calls = f"{len(cut)} calls" if len(cut) > 1 else "a call"
            yield f"{calls} about none of the finding's ids deleted", data

    def chunks(
        self,
        items: Callable[[dict[str, Any]], list[Any]],
        put: Callable[[dict[str, Any], list[Any]], dict[str, Any]],
        what: str,
        width: int | None = None,
    ) -> None:
        """Delete `items` of the plan (delta debugging): chunks of halves, then quarters, ...
        then single ones; `put` gives the data with the items kept (each candidate run with
        `width` seeds, default the search's)."""
        size = len(items(self.data)) // 2
        while size >= 1 and self.runs < self.budget:
            start = 0
            while start < len(atoms := items(self.data)) and self.runs < self.budget:
                kept = atoms[:start] + atoms[start + size :]
                gone = len(atoms) - len(kept)
                said = f"{gone} of {len(atoms)} {what} deleted"
                if not self.attempt(said, put(self.data, kept), width=width):
                    start += size
            size //= 2

    def durations(self) -> None:
        """A shorter run: its end cut (the injections after it dropped), or its start (the
        injections before it dropped, the others that much earlier), largest cuts first."""
        self.repeat(self.duration_cuts)

    def duration_cuts(self) -> Iterator[tuple[str, dict[str, Any]]]:
        """The candidates of `durations`: the end `NARROW`, then `MARGIN` after the
        violation; then the end or the start cut at fractions of the duration."""
        duration = self.data["duration"]
        seen = _violation_at(self.best, self.kind, duration, self.judge)
        for margin in (NARROW, MARGIN):
            if seen is not None and (shorter := round(seen + margin, 3)) < duration:
                yield (
                    f"duration {duration:g} -> {shorter:g} s (the violation at {seen:.3f} s)",
                    (self.until(shorter)),
                )
        for fraction in (0.125, 0.25, 0.5, 0.75, 0.9):
            shorter = round(duration * fraction, 3)
            if not 0 < shorter < duration:
                continue
            yield f"duration {duration:g} -> {shorter:g} s", self.until(shorter)
            if (cut := self.from_(round(duration - shorter, 6))) is not None:
                yield f"the first {duration - shorter:g} s of {duration:g} cut", cut

    def from_(self, by: float) -> dict[str, Any] | None:
        """The data from `by` seconds on (earlier injections dropped); `None` if a fault has no
        time."""
        atoms = self.data.get("faults", [])
        if not all(_timed(a) or "after" in a for a in atoms):
            return None
        duration = round(self.data["duration"] - by, 6)
        faults = [
            {**a, "at": round(a["at"] - by, 6)} if _timed(a) else a
            for a in atoms
            if (a["at"] >= by if _timed(a) else _fires_within(a, duration))
        ]
        return {**self.data, "duration": duration, "faults": faults}

    def until(self, duration: float) -> dict[str, Any]:
        """The data with another duration; the injections (and `after` delays) reaching it
        dropped."""
        faults = [
            atom
            for atom in self.data.get("faults", [])
            if (atom["at"] < duration if _timed(atom) else _fires_within(atom, duration))
        ]
        return {**self.data, "duration": duration, "faults": faults}

    def seeds(self) -> None:
        """The current plan under seeds 1 to `SEEDS`: the seed showing the kind in the fewest
        events."""
        text = self.text(self.data)
        for seed in range(1, max(SEEDS, self.width) + 1):
            if self.runs >= self.budget:
                return
            if (text, seed) in self.tried:
                continue
            self.tried.add((text, seed))
            run = self.run_one(self.plan, seed)
            if self.kind not in violation_kinds(run, self.judge):
                continue
            if (size := self.size(run)) < self.best_size:
                self.seed, self.best, self.best_size = seed, run, size
                self.steps.append(f"seed {seed}")
                self.say(f"run {self.runs}: seed {seed}: {self.shown(size)}")

    def supervisors(self) -> None:
        """Fewer restarts before a supervisor gives up (a crash loop ends sooner)."""
        for index in range(len(_supervisors(self.data))):
            where = ("*supervisors", index)
            self.repeat(functools.partial(self.counts, where, "max_restarts"))

    def counts(
        self, where: tuple[Any, ...], key: str, least: int = 0
    ) -> Iterator[tuple[str, dict[str, Any]]]:
        """Smaller values of a count of at least `least` (0 or 1), smallest first: 0, 1, 2,
        4, 8, ... (the first kept is about the smallest that still violates)."""
        current = _at(self.data, where).get(key, _DEFAULTS.get(key))
        if isinstance(current, bool) or not isinstance(current, int):
            return
        wanted = [0, *itertools.takewhile(lambda v: v < current, (2**i for i in itertools.count()))]
        yield from self.values(where, key, [v for v in wanted if least <= v < current])

    def shift(self) -> None:
        def candidates() -> Iterator[tuple[str, dict[str, Any]]]:
            times = [a["at"] for a in self.data.get("faults", []) if _timed(a)]
            if not times or min(times) <= 0:
                return
            for by in (min(times), round(min(times) / 2, 6)):
                if (data := self.from_(by)) is not None:
                    yield f"every injection {by:g} s earlier", data

        self.repeat(candidates)

    def pinned(self) -> None:
        """Each timed injection fired `after` an event before it instead (`delay` the time between).

        A kill at a narrow moment then stays there when a later pass changes the schedule.
        """
        for index in range(len(self.data.get("faults", []))):
            for what, data in self.pins(index):
                if self.runs >= self.budget or self.attempt(what, data, same=True):
                    break

    def pins(self, index: int) -> Iterator[tuple[str, dict[str, Any]]]:
        """The `pinned` candidates for atom `index`: events about what it cut first, then the
        nearest."""
        atom = self.data["faults"][index]
        if not _timed(atom):
            return
        lines = [json.loads(line) for line in self.best.history.splitlines()]
        fired = next(
            (
                line
                for line in lines
                if line.get("type") == "FaultInjected"
                and line.get("kind") == atom.get("kind")
                and abs(line.get("scheduled_s", -1.0) - atom["at"]) < 1e-6
                and (line.get("target") is None or {line["target"]} >= _aimed(atom))
            ),
            None,
        )
        if fired is None:
            return
        t0 = fired["at"] - fired["injected_s"]
        before = [
            line
            for line in lines
            if line.get("type") in EVENT_TYPES
            and line["type"] != "FaultInjected"
            and line["at"] < fired["at"] - 1e-6  # (at its time: what it caused)
        ]
        after = [
            line
            for line in lines
            if line.get("type") in EVENT_TYPES
            and line["type"] != "FaultInjected"
            and fired["at"] - 1e-6 <= line["at"] <= fired["at"] + CUT_S
        ]
        cut = {line[k] for line in after for k in _ID_FIELDS if isinstance(line.get(k), str)}
        nearest = list(reversed(before))
        began = [e for e in nearest if {e.get(k) for k in _ID_FIELDS} & cut]
        managers = {m.get("name") for m in _managers(self.data)}
        seen: set[str] = set()
        for event in began[:PINS] + nearest[:PINS]:
            match = {
                k: event[k]
                for k in _PIN_FIELDS
                if isinstance(event.get(k), str) and (k == "child" or event[k] in managers)
            }
            key = json.dumps([event["type"], match], sort_keys=True)
            if key in seen:
                continue
            seen.add(key)
            nth = sum(
                line["type"] == event["type"]
                and line["at"] <= event["at"]
                and all(line.get(k) == v for k, v in match.items())
                for line in before
            )
            delay = round(max(0.0, atom["at"] - (event["at"] - t0)), 6)
            pinned = {k: v for k, v in atom.items() if k != "at"}
            pinned["after"] = {"event": event["type"], **match, "nth": nth}
            if delay:
                pinned["delay"] = delay
            data = copy.deepcopy(self.data)
            data["faults"][index] = pinned
            said = ", ".join(f"{k} {v}" for k, v in match.items())
            yield f"the injection at {atom['at']:g} s after {event['type']} #{nth} ({said})", data

    def triggers(self) -> None:
        """An `after` fault fired sooner: at the 1st, 2nd, 4th, ... matching event, not its
        `nth` (a kill after a client's 20th withdrawn call: the 19 before it go)."""
        for index, atom in enumerate(self.data.get("faults", [])):
            if not isinstance(atom.get("after"), dict):
                continue
            trigger = ("faults", index, "after")
            self.repeat(functools.partial(self.counts, trigger, "nth", least=1))

    def idle(self) -> None:
        """Drop the managers that only started and stopped (with their call kinds, `uses`,
        faults)."""
        self.repeat(self.idle_managers, self.shuffled())

    def unpinned(self) -> None:
        """No clients, each fault `after` an event fired at the time it fired in the best run
        instead."""

        def candidates() -> Iterator[tuple[str, dict[str, Any]]]:
            workload = self.data.get("workload")
            if not workload or workload.get("clients", _DEFAULTS["clients"]) == 0:
                return
            faults = self.unpin(self.data.get("faults", []))
            data = {**self.data, "faults": faults, "workload": {**workload, "clients": 0}}
            yield "no clients (each fault after an event at the time it fired)", data

        self.repeat(candidates)

    def idle_managers(self) -> Iterator[tuple[str, dict[str, Any]]]:
        busy = _busy(self.best.history)
        idle = [m["name"] for m in _managers(self.data) if m["name"] not in busy]
        for names in ([idle] if len(idle) > 1 else []) + [[name] for name in idle]:
            unpinned = {**self.data, "faults": self.unpin(self.data.get("faults", []), set(names))}
            if (data := _without(unpinned, names)) is not None:
                said = f"managers {', '.join(names)}" if len(names) > 1 else f"manager {names[0]}"
                yield f"idle {said} dropped", data

    def unpin(
        self, atoms: list[dict[str, Any]], names: set[str] | None = None
    ) -> list[dict[str, Any]]:
        """The fault atoms with those `after` an event (all, or naming `names`) at their fired
        times."""
        fired: dict[int, list[dict[str, Any]]] = {}
        for line in map(json.loads, self.best.history.splitlines()):
            if line.get("type") == "FaultInjected":
                fired.setdefault(line["fault"], []).append(line)
        faults: list[dict[str, Any]] = []
        for atom, table in zip(atoms, _tables(atoms), strict=True):
            after = atom.get("after")
            named = {v for v in after.values() if isinstance(v, str)} if after else set()
            if not after or (names is not None and not named & names):
                faults.append(atom)
                continue
            rest = {k: v for k, v in atom.items() if k not in ("after", "delay", "target")}
            for line in fired.get(table, []):
                target = {"target": line["target"]} if line.get("target") else {}
                faults.append({**rest, **target, "at": round(line["injected_s"], 6)})
        return faults

    def tree(self) -> None:
        self.repeat(self.direct_calls)
        self.repeat(self.cut_uses)
        self.repeat(self.unused_managers, self.shuffled())

    def direct_calls(self) -> Iterator[tuple[str, dict[str, Any]]]:
        """A workload call to a manager that `uses` another, to that other instead."""
        managers = {m["name"]: m for m in _managers(self.data)}
        for index, call in enumerate(self.data.get("workload", {}).get("calls", [])):
            for use in managers.get(call.get("manager"), {}).get("options", {}).get("uses", []):
                name, _, server = str(use).partition("/")
                data = copy.deepcopy(self.data)
                data["workload"]["calls"][index] |= {
                    "manager": name,
                    "server": server or "resource",
                }
                yield f"calls to {call['manager']} made to {name}", data

    def cut_uses(self) -> Iterator[tuple[str, dict[str, Any]]]:
        for manager in _managers(self.data):
            for use in manager.get("options", {}).get("uses", []):
                data = copy.deepcopy(self.data)
                found = next(m for m in _managers(data) if m["name"] == manager["name"])
                found["options"]["uses"] = [u for u in found["options"]["uses"] if u != use]
                if not found["options"]["uses"]:
                    del found["options"]["uses"]
                yield f"{manager['name']} no longer uses {use}", data

    def unused_managers(self) -> Iterator[tuple[str, dict[str, Any]]]:
        """Drop a manager nobody calls or uses, with the injections aimed at it and calls to it."""
        workload = self.data.get("workload", {})
        calls = workload.get("calls", []) if workload.get("clients", 1) else []
        used = {c.get("manager") for c in calls}
        for manager in _managers(self.data):
            used |= {str(u).partition("/")[0] for u in manager.get("options", {}).get("uses", [])}
        for manager in _managers(self.data):
            name = manager["name"]
            if name in used:
                continue
            unpinned = {**self.data, "faults": self.unpin(self.data.get("faults", []), {name})}
            if (data := _without(unpinned, [name])) is not None:
                yield f"manager {name} dropped", data

    def workload(self) -> None:
        self.repeat(self.fewer_awaited)
        fewer = functools.partial(self.numbers, ("workload",), "clients", [1, 0.5, -1])
        self.repeat(functools.partial(fewer, whole=True), self.shuffled())
        self.repeat(self.fewer_calls, self.shuffled())
        self.repeat(lambda: self.numbers(("workload",), "rate", [0.125, 0.25, 0.5]))
        if self.data.get("workload", {}).get("cancel"):
            self.repeat(lambda: self.numbers(("workload",), "cancel_within", [0, 0.5]))
        if self.data.get("workload", {}).get("fetch_every"):
            self.repeat(lambda: self.values(("workload",), "fetch_every", [0]))
            self.repeat(lambda: self.numbers(("workload",), "fetch_every", [1, 0.5], whole=True))
        for index in range(len(self.data.get("workload", {}).get("calls", []))):
            call = ("workload", "calls", index)
            self.repeat(functools.partial(self.numbers, call, "keys", [1, 0.5, -1], whole=True))
            self.repeat(functools.partial(self.values, call, "shared", [1.0, 0.0]))
        self.repeat(lambda: self.numbers(("workload",), "hold", [0, 0.5]))

    def fewer_awaited(self) -> Iterator[tuple[str, dict[str, Any]]]:
        """Fewer calls awaited at once (1, a quarter, a half); each with `nth` scaled alike, then
        not."""
        for what, data in self.numbers(("workload",), "awaited", [1, 0.25, 0.5], whole=True):
            fraction = data["workload"]["awaited"] / self.data["workload"]["awaited"]
            scaled = copy.deepcopy(data)
            triggers = [
                a["after"] for a in scaled.get("faults", []) if a.get("after", {}).get("nth")
            ]
            for trigger in triggers:
                trigger["nth"] = max(1, round(trigger["nth"] * fraction))
            if scaled != data:
                nths = ", ".join(str(t["nth"]) for t in triggers)
                yield f"{what} (and the triggers' nth: {nths})", scaled
            yield what, data

    def fewer_calls(self) -> Iterator[tuple[str, dict[str, Any]]]:
        calls = self.data.get("workload", {}).get("calls", [])
        for index in range(len(calls) if len(calls) > 1 else 0):
            data = copy.deepcopy(self.data)
            del data["workload"]["calls"][index]
            yield f"workload.calls[{index}] deleted", data

    def options(self) -> None:
        for index, manager in enumerate(_managers(self.data)):
            for key in ("load_s", "unload_s"):
                if manager.get("options", {}).get(key):
                    where = ("*managers", index, "options")
                    self.repeat(functools.partial(self.numbers, where, key, [0, 0.5]))

    def knobs(self) -> None:
        """Every other number of the plan (workload, managers, faults, supervisors that gave up or
        restarted as often as they may): 0, a quarter, a half, twice, four times it."""
        tables: list[tuple[Any, ...]] = [("workload",)]
        calls = self.data.get("workload", {}).get("calls", [])
        tables += [("workload", "calls", index) for index in range(len(calls))]
        for index, manager in enumerate(_managers(self.data)):
            tables.append(("*managers", index))
            if isinstance(manager.get("options"), dict):
                tables.append(("*managers", index, "options"))
        tables += [("faults", index) for index in range(len(self.data.get("faults", [])))]
        restarts = _restarts(self.best.history)
        for index, supervisor in enumerate(_supervisors(self.data)):
            most = supervisor.get("max_restarts", _DEFAULTS["max_restarts"])
            if restarts.get(supervisor.get("name", "root"), 0) >= most:  # (else moot)
                tables.append(("*supervisors", index))
        for where in tables:
            if where[0] == "workload" and "workload" not in self.data:
                continue
            for key, value in list(_at(self.data, where).items()):
                if key not in _NOT_KNOBS and _number(value):
                    self.repeat(functools.partial(self.scaled, where, key))

    def scaled(self, where: tuple[Any, ...], key: str) -> Iterator[tuple[str, dict[str, Any]]]:
        """`key`'s value 0, then times each of `KNOB_SCALES` (an int's rounded, 1 at least)."""
        current = _at(self.data, where).get(key)
        if isinstance(current, bool) or not isinstance(current, int | float):
            return
        wanted: list[float] = [0]
        for scale in KNOB_SCALES:
            value = current * scale
            wanted.append(max(1, round(value)) if isinstance(current, int) else round(value, 6))
        yield from self.values(where, key, [v for v in dict.fromkeys(wanted) if v != current])

    def rounded(self) -> None:
        def candidates() -> Iterator[tuple[str, dict[str, Any]]]:
            for digits in (1, 2):
                faults = [
                    {**a, "at": round(a["at"], digits)} if _timed(a) else a
                    for a in self.data.get("faults", [])
                ]
                duration = self.data["duration"]
                longer = round(duration + 0.5 * 10**-digits, digits)
                data = {**self.data, "faults": faults, "duration": longer}
                if self.text(data) != self.text(self.data):
                    yield f"times to {digits} decimals", data

        self.repeat(candidates, self.tries)  # (for the reader: not worth a wide search)

    # -- numbers of a table ------------------------------------------------------------------

    def numbers(
        self, where: tuple[Any, ...], key: str, steps: list[float], *, whole: bool = False
    ) -> Iterator[tuple[str, dict[str, Any]]]:
        """Smaller values of a number: a step below 1 scales it, -1 takes one off, 0 and 1
        are themselves (an int's below 1 is left out)."""
        current = _at(self.data, where).get(key, _DEFAULTS.get(key))
        if isinstance(current, bool) or not isinstance(current, int | float):
            return
        wanted = []
        for step in steps:
            value = current - 1 if step == -1 else (step if step in (0, 1) else current * step)
            value = int(value) if whole else round(value, 6)
            if (value >= 1 or not whole) and value < current and value not in wanted:
                wanted.append(value)
        yield from self.values(where, key, wanted)

    def values(
        self, where: tuple[Any, ...], key: str, values: list[Any]
    ) -> Iterator[tuple[str, dict[str, Any]]]:
        for value in values:
            if _at(self.data, where).get(key, _DEFAULTS.get(key)) == value:
                continue
            data = copy.deepcopy(self.data)
            _at(data, where)[key] = value
            if where[:1] == ("*managers",):
                where_shown = (_managers(self.data)[where[1]]["name"], *where[2:])
            elif where[:1] == ("*supervisors",):
                name = _supervisors(self.data)[where[1]].get("name", "tree")
                where_shown = (name, *where[2:])
            else:
                where_shown = where
            shown = ".".join(map(str, where_shown))
            yield f"{shown}.{key} = {value:g}".lstrip("."), data


_DEFAULTS = {
    "nth": 1,
    "awaited": 0,
    "cancel_within": 0.05,
    "fetch_every": 0,
    "shared": 0.5,
    "hold": 0.5,
    "clients": 1,
    "rate": 5.0,
    "keys": 4,
    "max_restarts": 3,
}
"""The plan's defaults of the keys the passes make smaller (`plan.py`)."""


def _at(data: dict[str, Any], where: tuple[Any, ...]) -> dict[str, Any]:
    """The table at `where` (`("*managers", i, ...)`: the i-th manager), made if missing."""
    node: Any = data
    steps = list(where)
    if steps and steps[0] == "*managers":
        node, steps = _managers(data)[steps[1]], steps[2:]
    elif steps and steps[0] == "*supervisors":
        node, steps = _supervisors(data)[steps[1]], steps[2:]
    for step in steps:
        node = node[step] if isinstance(step, int) else node.setdefault(step, {})
    found: dict[str, Any] = node
    return found


_MISSING = object()
"""What `_part` gives for a key the data does not have."""


def _part(data: dict[str, Any], dotted: str) -> Any:
    """The value at a dotted key of the plan's data (`_MISSING`: none); of `"tree"`, its
    shape: the supervisors with their settings, each child's place, name and restart type
    (a manager's options, `uses` among them, are the world's: they may shrink)."""
    node: Any = data
    for key in dotted.split("."):
        if not isinstance(node, dict) or key not in node:
            return _MISSING
        node = node[key]
    return _shape(node) if dotted == "tree" else copy.deepcopy(node)


def _shape(node: Any) -> Any:
    if not isinstance(node, dict):
        return copy.deepcopy(node)
    if "children" not in node:
        return {"name": node.get("name"), "restart": node.get("restart")}
    children = node["children"]
    shaped = {k: copy.deepcopy(v) for k, v in node.items() if k != "children"}
    return shaped | {
        "children": [_shape(c) for c in children] if isinstance(children, list) else children
    }


def _managers(data: dict[str, Any]) -> list[dict[str, Any]]:
    """The manager tables of the tree, depth first."""

    def walk(node: dict[str, Any]) -> Iterator[dict[str, Any]]:
        for child in node.get("children", []):
            yield from walk(child) if "children" in child else [child]

    return list(walk(data.get("tree", {})))


def _supervisors(data: dict[str, Any]) -> list[dict[str, Any]]:
    """The supervisor tables of the tree (the top one first), depth first."""

    def walk(node: dict[str, Any]) -> Iterator[dict[str, Any]]:
        yield node
        for child in node.get("children", []):
            if "children" in child:
                yield from walk(child)

    return list(walk(data["tree"])) if "tree" in data else []


def _violation_at(
    run: simulate.SimulatedRun, kind: str, duration: float, judge: Judge
) -> float | None:
    """When (seconds after the run's first event) the last event that shows `kind`'s
    first finding happened, of those within `duration` (`None`: no such event)."""
    lines = run.history.splitlines()
    finding = next((f for f in judge(run) if violation_kind(f.rule, f.message) == kind), None)
    if finding is None or not lines:
        return None
    start = json.loads(lines[0])["at"]
    times = [json.loads(lines[n - 1])["at"] - start for n in finding.lines if 0 < n <= len(lines)]
    times = [t for t in times if t < duration]
    return max(times) if times else None


_IDLE_EVENTS = frozenset({"CatalogRestored", "ChildStarted", "RegistrarStopped"})
"""The events of a manager or client doing nothing: its start and its stop."""

_NAME_FIELDS = ("registrar", "consumer", "serving_rr", "child", "target")
"""The fields of an event naming a manager or a client (`_busy`)."""


def _busy(history: str) -> set[str]:
    """The names (managers, clients) a history's events name, but those of a start or a
    stop (a `ChildExited` of the shutdown) and of an empty listing of ids."""
    names: set[str] = set()
    for line in map(json.loads, history.splitlines()):
        kind = line.get("type")
        if kind in _IDLE_EVENTS or (kind == "ChildExited" and line.get("stopped")):
            continue
        if kind == "ServerQueriesListed" and not line.get("query_ids"):
            continue
        names |= {v for k in _NAME_FIELDS if isinstance(v := line.get(k), str)}
    return names


def _calls_made(history: str, awaited: int) -> dict[int, int]:
    """How many calls each client (by index) made in a history: its calls' ids (answered,
    failed or withdrawn, not a dependency's), per batch of `awaited` calls."""
    ids: dict[int, set[str]] = {}
    for line in map(json.loads, history.splitlines()):
        name = line.get("registrar")
        if line.get("type") not in ("CallAnswered", "CallFailed", "CallWithdrawn"):
            continue
        if isinstance(name, str) and (found := re.fullmatch(r"client-([0-9]+)", name)):
            ids.setdefault(int(found[1]), set()).add(line["query_id"])
    return {c: -(-len(made) // max(1, awaited)) for c, made in ids.items()}


def _unrelated(
    history: str, finding: tuple[int, ...], only: list[list[int]], awaited: int
) -> list[list[list[int]]]:
    """The calls of `only` (`[client, n]` pairs) whose events name none of the ids of the
    history's lines `finding` (numbered from 1), grouped by the resource they are about,
    the biggest group first. A client's made calls are its kept numbers in order (its
    calls' ids by when they started, per batch of `awaited`); a number not made is left."""
    lines = [json.loads(line) for line in history.splitlines()]
    named = {
        v for n in finding if 0 < n <= len(lines) for k in _ID_FIELDS if (v := lines[n - 1].get(k))
    }
    about: dict[str, set[str]] = {}  # a query's ids: its own, its resources'
    started: dict[int, dict[str, float]] = {}
    for line in lines:
        if isinstance(query := line.get("query_id"), str):
            about.setdefault(query, {query}).update(
                v for k in _ID_FIELDS if isinstance(v := line.get(k), str)
            )
        name = line.get("registrar")
        if line.get("type") not in ("CallAnswered", "CallFailed", "CallWithdrawn"):
            continue
        if isinstance(name, str) and (found := re.fullmatch(r"client-([0-9]+)", name)):
            calls = started.setdefault(int(found[1]), {})
            calls.setdefault(line["query_id"], line.get("started", line["at"]))
    resources = named | {r for q in named for r in about.get(q, ())}
    groups: dict[str, list[list[int]]] = {}
    for client, calls in started.items():
        ids = sorted(calls, key=calls.__getitem__)
        numbers = sorted(n for c, n in only if c == client)
        size = max(1, awaited)
        for index, number in enumerate(numbers[: -(-len(ids) // size)]):
            batch = ids[index * size : (index + 1) * size]
            if any(about.get(q, {q}) & resources for q in batch):
                continue
            key = min(sorted(about.get(batch[0], {batch[0]}) - {batch[0]}) or [batch[0]])
            groups.setdefault(key, []).append([client, number])
    return sorted(groups.values(), key=lambda group: (-len(group), group))


def _restarts(history: str) -> dict[str, float]:
    """The restarts each supervisor made in a history (infinitely many if it gave up)."""
    counts: dict[str, float] = {}
    for line in map(json.loads, history.splitlines()):
        if line.get("type") == "ChildRestarted":
            counts[line["supervisor"]] = counts.get(line["supervisor"], 0) + 1
        elif line.get("type") == "SupervisorGaveUp":
            counts[line["supervisor"]] = float("inf")
    return counts


def _without(data: dict[str, Any], names: list[str]) -> dict[str, Any] | None:
    """The data without managers `names` and what names them (`None`: one is a last child)."""
    data = copy.deepcopy(data)
    if not all(_drop(data["tree"], name) for name in names):
        return None
    gone = set(names)
    workload = data.get("workload", {})
    if "calls" in workload:
        workload["calls"] = [c for c in workload["calls"] if c.get("manager") not in gone]
        if not workload["calls"]:
            workload["clients"] = 0  # (nothing left to call)
    for manager in _managers(data):
        options = manager.get("options", {})
        if "uses" in options:
            options["uses"] = [u for u in options["uses"] if str(u).partition("/")[0] not in gone]
            if not options["uses"]:
                del options["uses"]
    faults = []
    for atom in data.get("faults", []):
        aimed = _aimed(atom)
        after = atom.get("after", {})
        if (aimed and aimed <= gone) or gone & {v for v in after.values() if isinstance(v, str)}:
            continue
        if isinstance(atom.get("target"), list):
            atom["target"] = [t for t in atom["target"] if t not in gone]
        faults.append(atom)
    if "faults" in data:
        data["faults"] = faults
    return data


def _tables(atoms: list[dict[str, Any]]) -> list[int]:
    """The index of each fault atom's `[[faults]]` table in the plan's text (as
    `_dump_atoms` groups them: the number a `FaultInjected`'s `fault` gives)."""
    groups: dict[str, int] = {}
    out: list[int] = []
    tables = 0
    for atom in atoms:
        if not _timed(atom):  # (a table of its own)
            out.append(tables)
            tables += 1
            continue
        key = json.dumps({k: v for k, v in atom.items() if k != "at"}, sort_keys=True)
        if key not in groups:
            groups[key] = tables
            tables += 1
        out.append(groups[key])
    return out


def _drop(node: dict[str, Any], name: str) -> bool:
    """Remove the manager `name` from the tree (never a supervisor's last child)."""
    children = node.get("children", [])
    for index, child in enumerate(children):
        if "children" in child:
            if _drop(child, name):
                return True
        elif child.get("name") == name and len(children) > 1:
            del children[index]
            return True
    return False


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _timed(atom: dict[str, Any]) -> bool:
    return isinstance(atom.get("at"), int | float)


def _fires_within(atom: dict[str, Any], duration: float) -> bool:
    """A fault not at a time (after an event, or kept whole) can fire in a run of
    `duration`: its `delay` (after its event) is shorter."""
    delay = atom.get("delay", 0)
    return not ("after" in atom and _number(delay) and delay >= duration)


def _aimed(atom: dict[str, Any]) -> set[str]:
    target = atom.get("target", [])
    return {target} if isinstance(target, str) else set(target)


# -- the output ---------------------------------------------------------------------------------


def write(shrunk: Shrunk, out: Path, line: dict[str, Any]) -> None:
    """Write the shrunk run as a run directory: `plan.toml` (a header saying what it
    shows), `seeds.jsonl` (`line`: the run's, as a sweep writes it) and its history."""
    out.mkdir(parents=True, exist_ok=True)
    run = shrunk.run
    header = [
        f"# Shrunk from {shrunk.plan.source}, seed {shrunk.original_seed} "
        f"({shrunk.original_events} events), in {shrunk.runs} simulated runs.",
        f"# Seed {shrunk.seed} of this plan violates with {run.events} events:",
        *(f"# {f.strip()}" for f in run.findings if "violation" in f or "crashed:" in f),
        *(
            [
                f"# Its story is its first {shrunk.story} events: the checker finds the same "
                f"violation without the {run.events - shrunk.story} after its finding."
            ]
            if 0 < shrunk.story < run.events
            else []
        ),
        f"#   rr-actors replay {out} --story",
        f"#   rr-actors experiment plan.toml --simulate --seeds {shrunk.seed} --out DIR",
    ]
    if shrunk.plan.base_dir is not None and Path(shrunk.plan.base_dir) != out.resolve():
        header.append(  # (replay finds them: seeds.jsonl names the original file)
            f"# (its setups are imported as the original's, from {shrunk.plan.base_dir} "
            "first: a module of yours there needs that folder on PYTHONPATH)"
        )
    (out / "plan.toml").write_text("\n".join(header) + "\n\n" + shrunk.text, encoding="utf-8")
    (out / "seeds.jsonl").write_text(json.dumps(line) + "\n", encoding="utf-8")
    (out / f"events-seed-{shrunk.seed}.jsonl").write_text(run.history, encoding="utf-8")
