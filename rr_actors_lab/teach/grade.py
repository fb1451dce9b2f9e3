"""Check a student's folder: its plan over the exercise's seeds on the simulation.

```
 check_folder(folder) ─ the exercise (folder's .teach.json); what is not the student's
 │   compared with the shipped starter (`kit.changed`: a change is refused, one line);
 │   the plan's TOML read here (its managers, policy, intensities), never imported here
 ├─ one child process for the whole check (`_seeds.py`): the plan read and its setups
 │  imported there, a protocol exercise's step.py in the registrar's slot there, the kit
 │  hidden from the student's code; it runs seeds 1..N (or one: `seed`) and answers each
 │  with the run's history (JSON lines: plain data)
 ├─ here: each history judged, by the checker's rules and the kit's (`rules.judge`); the
 │  first seed that breaks one ends it; its run shrunk in the child (the student's part
 │  of the plan kept as written) and the shrunk history judged here again
 └─► Report: passed; seeds run; interleavings; CPU seconds (both processes); the first
     failure: the rule in words, the finding, its first violating event, a story of at
     most `STORY` steps of the shrunk run, the command that replays it
```

A replay (`seed_run`, `rerun`, `replay_story`) runs in this process: it is the student's
own look at a seed, not a grade.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import msgspec

from rr_actors.errors import ConfigError, RrError
from rr_actors.events.text import describe
from rr_actors_lab._tools import files
from rr_actors_lab.experiments import check, shrink, simulate, story
from rr_actors_lab.experiments.plan import Plan, SupervisorPlan
from rr_actors_lab.experiments.reading import PLAN_LIMIT, load_plan
from rr_actors_lab.experiments.sweep import HASH_SEED
from rr_actors_lab.teach import _seeds, rules
from rr_actors_lab.teach.kit import Exercise, changed, folder_exercise

__all__ = [
    "STORY",
    "Failure",
    "Report",
    "SubmissionError",
    "check_folder",
    "judge",
    "replay_story",
    "rerun",
    "seed_run",
]

STORY = 20
"""The most steps of the story a failing check prints."""

SHRINK_BUDGET = 200
"""The most simulated runs a failing check's shrink makes (0.01-0.5 CPU s each: survive's
starter 349 events to 15 in 200, 23 in 40; cut's 916 to 26, 70 in 40)."""

CPU_S = 55.0
"""CPU seconds of a check after which its shrink makes no more runs (the kit's bound is 60
a check: the shrunk story so far is told)."""

SHRUNK = "shrunk.toml"
"""The shrunk plan a failing check writes into the folder (the replay command runs it)."""


class SubmissionError(ConfigError):
    """A folder's own files cannot be checked, so no seed was judged: its plan is missing,
    is not a regular file, is too big or is not a plan the simulation runs (its setups do
    not import, among others); a protocol exercise's `step.py` is missing, does not import
    or lacks its step's function; it changed what is not the student's; or the process
    that ran the student's code ended before it answered. The message names the file and
    why."""


@dataclasses.dataclass(frozen=True)
class Failure:
    """The first seed that broke a rule, told for a student.

    Attributes:
        seed: the seed.
        rule: the rule's name (`check.RULES`, `rules.RULES`, or `"crashed"`, `"setup"`).
        words: the exercise's rule in words.
        message: what broke it, in this run.
        first_event: the first violating event: `#LINE: what happened` (`None`: no event
            shows it, a setup that raised).
        story: the story's lines (at most `STORY` steps and the violation's line).
        story_events: how many steps of the run the story kept.
        run_events: how many events the whole run had.
        replay: the command that tells the seed's whole story (the shrunk plan's, if shrunk;
            `""`: the plan broke the rule before any run).
        shrunk_seed: the seed of the shrunk plan (`SHRUNK` in the folder) the story tells;
            `None`: the story is the run's own.
        shrunk_events: the shrunk run's events (`None`: not shrunk).
    """

    seed: int
    rule: str
    words: str
    message: str
    first_event: str | None
    story: tuple[str, ...]
    story_events: int
    run_events: int
    replay: str
    shrunk_seed: int | None = None
    shrunk_events: int | None = None


@dataclasses.dataclass(frozen=True)
class Report:
    """A check's result (what `--json` writes, `dataclasses.asdict`).

    Attributes:
        exercise: the exercise's name.
        passed: every seed held every rule.
        seeds: the seeds asked for (the exercise's, or the one `--seed`).
        seeds_run: the seeds run (fewer than `seeds` when one failed).
        interleavings: distinct histories among them (different schedules and faults).
        events: events recorded over the seeds run.
        cpu_s: CPU seconds the check took (this process and the child that ran the
            student's code).
        failure: the first failure (`None`: passed).
        plan: the plan run when not the folder's own (`--plan`: a replay of a shrunk
            failure, not a grade); `None`: the folder's `plan.toml`.
    """

    exercise: str
    passed: bool
    seeds: int
    seeds_run: int
    interleavings: int
    events: int
    cpu_s: float
    failure: Failure | None
    plan: str | None = None

    @property
    def outcome(self) -> str:
        """`"passed"`; `"failed"`: a seed broke a rule; `"not-loaded"`: the folder's code
        did not start (its setup raised: rule `"setup"`)."""
        if self.failure is None:
            return "passed"
        return "not-loaded" if self.failure.rule == "setup" else "failed"

    def as_dict(self) -> dict[str, Any]:
        """The report as JSON data (its fields and `outcome`)."""
        return {**dataclasses.asdict(self), "outcome": self.outcome}


def check_folder(
    folder: Path,
    *,
    seed: int | None = None,
    seeds: int | None = None,
    plan_file: Path | None = None,
    shrink_budget: int = SHRINK_BUDGET,
    on_seed: Callable[[int], None] | None = None,
    on_shrink: Callable[[int], None] | None = None,
) -> Report:
    """Check a student's folder over its exercise's seeds (or `seed` alone, or 1..`seeds`).

    What is not the student's (`Exercise.yours`) must be as shipped; the student's code
    runs in a child process (`_seeds.py`), which hands this one each seed's history, and
    this one judges it.

    Args:
        folder: the folder `start` wrote, as the student changed it.
        seed: one seed to run (a replay).
        seeds: run seeds 1 to this instead of the exercise's (at least 1).
        plan_file: run this plan instead of `folder/plan.toml` (a shrunk one, `SHRUNK`),
            its setups imported from its own folder: a replay of a failure, not a grade
            (the report names it: `Report.plan`).
        shrink_budget: the most runs a failure's shrink makes (0: no shrink).
        on_seed: called with each seed once it was judged (progress; in this thread); a
            failing seed's shrink runs before.
        on_shrink: called in this thread with the runs a failing seed's shrink made so far
            (0 as it starts, then after each run).

    Raises:
        ConfigError: `folder` is not an exercise's folder; `seeds` below 1.
        SubmissionError: it changed what is not the student's (`kit.changed`: the message
            names the change); its `plan.toml` is missing or wrong (file, line, key); a
            protocol exercise's `step.py` is missing, does not import or lacks its step's
            function; the child process ended before it answered (its exit code).
    """
    chosen, _state = folder_exercise(folder)
    count = chosen.seeds if seeds is None else seeds
    if count < 1:
        raise ConfigError(f"seeds must be at least 1, got {count}")
    try:
        said = changed(chosen, folder)
    except files.RefusedFileError as exc:
        raise SubmissionError(str(exc)) from None
    if said is not None:
        raise SubmissionError(f"{folder}: {said}")
    chosen_seeds = [seed] if seed is not None else list(range(1, count + 1))
    path = folder / "plan.toml" if plan_file is None else plan_file
    facts = _Facts.read(path)
    started = time.process_time()
    tally = _Tally(failure=_intensity(chosen, facts, chosen_seeds[0]))
    if tally.failure is None:
        with _Child(chosen, folder, path, facts, on_shrink) as child:
            budget = (shrink_budget, started + CPU_S)
            _run_seeds(chosen, folder, path, facts, child, chosen_seeds, budget, tally, on_seed)
            tally.child_cpu_s = child.cpu_s
    failure = tally.failure
    if failure is None and plan_file is None:  # (a shrunk plan of a failure fixed since)
        (folder / SHRUNK).unlink(missing_ok=True)
    return Report(
        exercise=chosen.name,
        passed=failure is None,
        seeds=len(chosen_seeds),
        seeds_run=tally.attempted,
        interleavings=len(tally.hashes),
        events=tally.recorded,
        cpu_s=round(time.process_time() - started + tally.child_cpu_s, 3),
        failure=failure,
        plan=None if plan_file is None else str(plan_file),
    )


@dataclasses.dataclass
class _Tally:
    """A check's count so far: its first failure, seeds run, distinct histories, events,
    the child's CPU seconds."""

    failure: Failure | None = None
    attempted: int = 0
    hashes: set[str] = dataclasses.field(default_factory=set)
    recorded: int = 0
    child_cpu_s: float = 0.0


def _run_seeds(
    chosen: Exercise,
    folder: Path,
    path: Path,
    facts: _Facts,
    child: _Child,
    seeds: list[int],
    budget: tuple[int, float],
    tally: _Tally,
    on_seed: Callable[[int], None] | None,
) -> None:
    """Ask the child for each seed's run (one ahead: it runs while the last is judged) and
    judge it here, until one fails; `budget`: a failure's shrink's most runs, and the
    `time.process_time()` of this process (the child's CPU added) its runs stop at."""
    ahead = iter(seeds)
    child.ask({"seed": next(ahead)})
    for number in seeds:
        if (following := next(ahead, None)) is not None:
            child.ask({"seed": following})
        reply = child.answer()
        tally.attempted += 1
        if "setup" in reply:  # (the student's setup raised: the tree did not start)
            tally.failure = _setup_failure(chosen, folder, number, reply["setup"])
            return
        run = _Run.of(reply)
        tally.hashes.add(run.hash)
        tally.recorded += run.events
        left = (budget[0], budget[1] - time.process_time() - child.cpu_s)
        failure = _judge(chosen, folder, run, facts, child, path, left)
        if reply["replaced"]:  # (whatever the verdict: the check runs their step, no other)
            said = reply["replaced"][0]
            failure = _raised(chosen, folder, number, said, failure, "step-replaced")
        elif reply["raised"]:  # (whatever the verdict: a step that raises is wrong)
            failure = _raised(chosen, folder, number, reply["raised"][0], failure)
        if on_seed is not None:
            on_seed(number)
        if failure is not None:
            tally.failure = failure
            return


@dataclasses.dataclass(frozen=True)
class _Facts:
    """What this process reads of a plan's TOML (it never imports the plan's modules):
    its managers' names, its rule 22 policy, its supervisors' intensities (name, most
    restarts, period in seconds), how many `[[faults]]` tables it has."""

    managers: tuple[str, ...]
    resolve: str
    supervisors: tuple[tuple[str, int, float], ...]
    faults: int

    @classmethod
    def read(cls, path: Path) -> _Facts:
        """Raises: SubmissionError: the file is missing, not a regular file, over
        `PLAN_LIMIT` or not TOML (the child says the rest)."""
        if not path.exists():  # (a pipe or a device is there: refused as such, not missing)
            raise SubmissionError(f"{path} is missing: the exercise's plan (start it again?)")
        try:
            data = tomllib.loads(files.read_text(path, PLAN_LIMIT, "a plan"))
        except files.RefusedFileError as exc:
            raise SubmissionError(str(exc)) from None
        except tomllib.TOMLDecodeError as exc:
            raise SubmissionError(f"{path}: is not valid TOML ({exc})") from None
        defaults = {f.name: f.default for f in msgspec.structs.fields(SupervisorPlan)}
        managers: list[str] = []
        supervisors: list[tuple[str, int, float]] = []

        def walk(node: Any, name: str) -> None:
            if not isinstance(node, dict):
                return
            supervisors.append(
                (
                    str(node.get("name", name)),
                    _number(node.get("max_restarts", defaults["max_restarts"])),
                    _number(node.get("period", defaults["period"])),
                )
            )
            for child in node.get("children", []):
                if isinstance(child, dict) and "children" in child:
                    walk(child, str(child.get("name")))
                elif isinstance(child, dict):
                    managers.append(str(child.get("name")))

        walk(data.get("tree", {}), "root")
        hosts = data.get("hosts")
        resolve = hosts.get("resolve", "first_served") if isinstance(hosts, dict) else None
        faults = data.get("faults", [])
        return cls(
            tuple(managers),
            str(resolve or "first_served"),
            tuple(supervisors),
            len(faults) if isinstance(faults, list) else 0,
        )


def _facts_of(plan: Plan) -> _Facts:
    """What `_Facts.read` reads of a plan's TOML, of a plan already read (a replay's)."""
    return _Facts(
        tuple(m.name for m in plan.managers()),
        plan.hosts.resolve if plan.hosts is not None else "first_served",
        tuple((s.name, s.max_restarts, s.period) for s in plan.tree.supervisors()),
        len(plan.faults),
    )


def _number(value: Any) -> Any:
    return value if isinstance(value, int | float) and not isinstance(value, bool) else 0


@dataclasses.dataclass(frozen=True)
class _Run:
    """A seed's run as the child told it: plain data, judged here."""

    seed: int
    history: str
    events: int
    hash: str

    @classmethod
    def of(cls, reply: dict[str, Any]) -> _Run:
        history = str(reply["history"])
        return cls(
            int(reply["seed"]), history, int(reply["events"]), simulate.history_hash(history)
        )


class _Child:
    """The check's child process (`_seeds.py`): the student's code runs there; requests
    and replies are JSON lines on its stdin and stdout (its prints go to stderr)."""

    def __init__(
        self,
        chosen: Exercise,
        folder: Path,
        path: Path,
        facts: _Facts,
        on_shrink: Callable[[int], None] | None = None,
    ) -> None:
        env = {**os.environ, "PYTHONHASHSEED": HASH_SEED}  # (the same seed, the same history)
        command = [sys.executable, "-m", "rr_actors_lab.teach._seeds"]
        self.process = subprocess.Popen(  # noqa: S603 - ours
            command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, text=True
        )
        self.pending = 0
        self.cpu_s = 0.0
        self.on_shrink = on_shrink
        spec = {
            "folder": str(folder),
            "plan": str(path),
            "step": chosen.step,
            "keep": list(chosen.yours.plan),
            "rules": list(chosen.rules),
            "options": chosen.options,
            "managers": list(facts.managers),
            "resolve": facts.resolve,
            "faults": facts.faults,
        }
        try:
            self.ask(spec)
            ready = self.answer()
        except BaseException:
            self.close()
            raise
        if "error" in ready:
            self.close()
            raise SubmissionError(str(ready["error"]))

    def __enter__(self) -> _Child:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def ask(self, request: dict[str, Any]) -> None:
        assert self.process.stdin is not None
        try:
            self.process.stdin.write(json.dumps(request) + "\n")
            self.process.stdin.flush()
        except BrokenPipeError:
            self.ended()
        self.pending += 1

    def answer(self) -> dict[str, Any]:
        """The next reply (its request's, in order)."""
        assert self.process.stdout is not None
        line = self.process.stdout.readline()
        if not line:
            self.ended()
        self.pending -= 1
        reply: dict[str, Any] = json.loads(line)
        self.cpu_s = float(reply.get("cpu_s", self.cpu_s))
        return reply

    def shrunk(self, seed: int, budget: int, cpu_s: float) -> dict[str, Any]:
        """The child's shrink of `seed` (the replies to seeds asked ahead dropped); each
        run it made so far, as it tells, to `on_shrink`."""
        while self.pending:
            self.answer()
        self.ask({"shrink": seed, "budget": budget, "cpu_s": cpu_s})
        if self.on_shrink is not None:
            self.on_shrink(0)
        while "shrinking" in (reply := self.answer()):
            self.pending += 1  # (a progress line: the shrink's own reply still to come)
            if self.on_shrink is not None:
                self.on_shrink(int(reply["shrinking"]))
        return reply

    def ended(self) -> None:
        code = self.process.wait(timeout=30)
        raise SubmissionError(
            f"the check's process that runs your code ended (exit code {code}) before it "
            "answered: did your code exit, or was it killed?"
        )

    def close(self) -> None:
        with contextlib.suppress(OSError):
            if self.process.stdin is not None:
                self.process.stdin.close()
        try:
            self.process.wait(timeout=0 if self.pending else 5)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        if self.process.stdout is not None:
            self.process.stdout.close()


def replay_story(folder: Path, seed: int, plan_file: Path | None = None) -> list[str]:
    """The whole story of one seed of `folder`'s check (`rr-actors teach check --seed
    S --story`): every step, the violations under the steps they point at.

    Raises:
        ConfigError: as `check_folder`; a setup that raised (its message).
    """
    _plan_of, run = seed_run(folder, seed, plan_file)
    return [s.plain() for s in story.story(run.history)]


def seed_run(
    folder: Path | None, seed: int, plan_file: Path | None = None
) -> tuple[Plan, simulate.SimulatedRun]:
    """One seed of a check run again: `folder`'s plan (or `plan_file`, alone without `folder`),
    a protocol exercise's `step.py` in place; the plan and the run.

    Raises:
        ConfigError: as `check_folder`; neither a folder nor a plan.
        SubmissionError: as `check_folder`; a setup that raised.
    """
    if folder is None and plan_file is None:
        raise ConfigError("a seed of what? give an exercise's folder or a plan (--plan)")
    if folder is None:
        assert plan_file is not None
        plan = _plan(plan_file)
    else:
        folder_exercise(folder)
        plan = _plan(folder / "plan.toml" if plan_file is None else plan_file)
    return plan, rerun(folder, seed)(plan)


def judge(folder: Path, plan: Plan, run: simulate.SimulatedRun) -> Failure | None:
    """What `folder`'s check says of `run`, a seed of `plan` run again (`seed_run`, `rerun`):
    the first rule it broke, the checker's or the exercise's own, told on the run itself
    (not shrunk); `None`: it held every rule (a replay's verdict).

    Raises:
        ConfigError: `folder` is not an exercise's folder.
    """
    chosen, _state = folder_exercise(folder)
    facts = _facts_of(plan)
    seen = _Run(run.seed, run.history, run.events, run.hash)
    return _intensity(chosen, facts, run.seed) or _judge(
        chosen, folder, seen, facts, None, Path(), (0, 0.0)
    )


def rerun(folder: Path | None, seed: int) -> Callable[[Plan], simulate.SimulatedRun]:
    """What runs seed `seed` of a plan as `folder`'s check does (a protocol exercise's
    `step.py` in place; `None`: no exercise): a replay's runs with a fault added."""

    def run(plan: Plan) -> simulate.SimulatedRun:
        if folder is None:
            with _quiet():
                return _seed(plan, seed)
        chosen, _state = folder_exercise(folder)
        with _quiet(), _seeds.student_step(chosen.step, folder):
            return _seed(plan, seed)

    return run


def _seed(plan: Plan, seed: int) -> simulate.SimulatedRun:
    try:
        return simulate.run_seed(plan, seed)
    except RrError as exc:
        raise SubmissionError(f"seed {seed}: the tree did not start: {exc}") from None


def _plan(path: Path) -> Plan:
    if not path.exists():  # (a pipe or a device is there: refused as such, not missing)
        raise SubmissionError(f"{path} is missing: the exercise's plan (start it again?)")
    _forget_modules(path.parent)
    try:
        plan = load_plan(path)
        simulate.check_simulable(plan)
    except ConfigError as exc:
        raise SubmissionError(str(exc)) from exc
    return plan


def _forget_modules(folder: Path) -> None:
    """Forget the modules imported from `folder` before: the student's code as it is now."""
    where = folder.resolve()
    for name, module in list(sys.modules.items()):
        file = getattr(module, "__file__", None)
        if file is not None and Path(file).resolve().parent == where:
            del sys.modules[name]
    for path in folder.glob("*.py"):  # (one of that name from another exercise's folder)
        sys.modules.pop(path.stem, None)


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """The framework's warnings (a child killed, restarted) kept out of a student's
    terminal: the story tells them."""
    logger = logging.getLogger("rr_actors")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        logger.setLevel(level)


def _judge(
    chosen: Exercise,
    folder: Path,
    run: _Run,
    facts: _Facts,
    child: _Child | None,
    path: Path,
    budget: tuple[int, float],
) -> Failure | None:
    """The first finding of `run` (the checker's, then the kit's), told on the run shrunk
    (by the child, within `budget`: runs and CPU seconds) if the shrink finds it again;
    `None`: held."""
    numbered, findings = _findings(chosen, run.history, facts)
    crashed = _crashed(run.history)
    if not findings and crashed is None:
        return None
    replay = f"rr-actors teach check {folder} --seed {run.seed} --story"
    if not findings:  # crashed, and no rule says why before it
        steps = story.story(run.history)
        crash = next(s for s in steps if s.who == "crashed")
        shown = _cut(steps, steps.index(crash), set())
        return Failure(
            run.seed,
            "crashed",
            chosen.rule,
            crash.text,
            None,
            tuple(s.plain() for s in shown),
            len(shown),
            run.events,
            replay,
        )
    first, told_run, shrunk_seed = findings[0], run, None
    if budget[0] > 0 and child is not None:  # (judged by the same rules: the kit's too)
        shrunk = _shrunk(chosen, run, folder, facts, child, path, budget)
        if shrunk is not None:
            told_run, numbered, first, shrunk_seed = shrunk
            replay = (
                f"rr-actors teach check {folder} --plan {folder / SHRUNK} "
                f"--seed {shrunk_seed} --story"
            )
    at = max(first.lines, default=0)
    event = dict(numbered).get(at)
    steps = story.story(told_run.history)
    index = next((i for i, s in enumerate(steps) if s.line == at), len(steps) - 1)
    cited = [e for n, e in numbered if n in first.lines]
    who = set(first.registrars) | {_who(e) for e in cited}
    who |= {str(getattr(e, "serving_rr", "")) for e in cited} - {""}
    shown = _cut(steps, index, who)
    told = [s.plain() for s in shown]
    told.append(f"{'':>17}^ [{first.rule}] {first.message}")
    return Failure(
        run.seed,
        first.rule,
        chosen.rule,
        first.message,
        f"#{at}: {describe(event)}" if event is not None else None,
        tuple(told),
        len(shown),
        run.events,
        replay,
        shrunk_seed,
        told_run.events if shrunk_seed is not None else None,
    )


def _findings(
    chosen: Exercise, history: str, facts: _Facts
) -> tuple[list[check.Line], list[check.Finding]]:
    """A run's numbered events and its violations (the checker's and the kit's), the
    first broken first."""
    return rules.judge(
        history, chosen.rules, chosen.options, facts.managers, facts.resolve, facts.faults
    )


def _crashed(history: str) -> str | None:
    """A crashed run's last line (`simulate.CRASH_LINE`); `None`: it did not crash."""
    last = history.rstrip("\n").rpartition("\n")[2]
    return last if f'"type": "{simulate.CRASH_LINE}"' in last else None


def _shrunk(
    chosen: Exercise,
    run: _Run,
    folder: Path,
    facts: _Facts,
    child: _Child,
    path: Path,
    budget: tuple[int, float],
) -> tuple[_Run, list[check.Line], check.Finding, int] | None:
    """`run` shrunk by the child to a smaller plan showing its first violation again,
    judged here again (its plan written to `folder / SHRUNK`): run, events, finding and
    seed; `None`: not found again."""
    runs, cpu_s = budget
    reply = child.shrunk(run.seed, runs, max(cpu_s, 0.0))
    if reply.get("shrunk", True) is None:
        return None
    shrunk = _Run.of(reply)
    numbered, findings = _findings(chosen, shrunk.history, facts)
    kind = str(reply["kind"])
    same = [f for f in findings if shrink.violation_kind(f.rule, f.message) == kind]
    if not same:
        return None
    header = (
        f"# {path.name}'s seed {run.seed} shrunk ({run.events} events to "
        f"{shrunk.events}): it shows {kind} at seed {shrunk.seed}.\n"
        f"# rr-actors teach check {folder} --plan {folder / SHRUNK} --seed {shrunk.seed} "
        "--story\n\n"
    )
    (folder / SHRUNK).write_text(header + str(reply["text"]), encoding="utf-8")
    return shrunk, numbered, same[0], shrunk.seed


def _who(event: Any) -> str:
    """Who a story names for `event` (its registrar, child or supervisor)."""
    who = getattr(event, "registrar", None) or getattr(event, "child", None)
    return str(who or getattr(event, "supervisor", None) or "-")


def _cut(steps: list[story.StoryLine], index: int, who: set[str]) -> list[story.StoryLine]:
    """At most `STORY` steps ending at `steps[index]`: the latest faults and steps of `who` (all
    steps if `who` names none)."""
    before = [s for s in steps[:index] if s.line > 0 and s.who != "violation"]
    kept = [s for s in before if s.who in who or s.who == "fault"] if who else before
    kept = kept or before
    return [*kept[-(STORY - 1) :], dataclasses.replace(steps[index], marked=True)]


def _intensity(chosen: Exercise, facts: _Facts, seed: int) -> Failure | None:
    """A supervisor of the plan whose intensity is above the exercise's bound (before any
    run: no intensity that high stops a crash loop in time), told; `None`: none."""
    bound = chosen.most_restarts_per_s
    if bound is None:
        return None
    for name, most, period in facts.supervisors:
        per_s = most / period if period > 0 else float("inf")
        if per_s > bound:
            message = (
                f"supervisor {name} allows {most} restarts within "
                f"{period:g} s ({per_s:g} a second): above {bound:g} a second, a child "
                "that crashes at every start is restarted on and on instead of stopped"
            )
            return Failure(seed, "intensity-bound", chosen.rule, message, None, (), 0, 0, "")
    return None


def _raised(
    chosen: Exercise,
    folder: Path,
    seed: int,
    said: str,
    failure: Failure | None,
    rule: str = "step-raised",
) -> Failure:
    """The failure of a seed in which the student's step raised (or was put out of its
    place: `rule` "step-replaced", `said` says it whole): said first, with the run's own
    failure's story if it has one."""
    message = f"your {chosen.step} raised {said}" if rule == "step-raised" else said
    if failure is None:
        replay = f"rr-actors teach check {folder} --seed {seed} --story"
        return Failure(seed, rule, chosen.rule, message, None, (), 0, 0, replay)
    also = f"{message}; and then [{failure.rule}] {failure.message}"
    return dataclasses.replace(failure, rule=rule, message=also)


def _setup_failure(chosen: Exercise, folder: Path, seed: int, error: str) -> Failure:
    lines = [line.strip() for line in error.splitlines() if line.strip()]
    text = lines[0] if len(lines) < 2 else f"{lines[0]} {lines[-1]}"  # (a traceback's end)
    return Failure(
        seed,
        "setup",
        chosen.rule,
        f"the tree did not start: {text}",
        None,
        (),
        0,
        0,
        f"rr-actors teach check {folder} --seed {seed} --story",
    )
