"""Check a student's folder: its plan over the exercise's seeds on the simulation.

```
 check(folder) ─ the exercise (folder's .teach.json), its plan (folder/plan.toml, its
 │               setups imported fresh from the folder); a protocol exercise:
 │               folder/step.py's function in the registrar's place (`replaced_step`)
 ├─ seeds 1..N (or one: `seed`): simulate.run_seed ─► the checker's verdict + the kit's
 │  rules (`rules.py`); the first seed that breaks one ends it
 └─► Report: passed; seeds run; interleavings; CPU seconds; the first failure: the rule
     in words, the finding, its first violating event, a story of at most `STORY` steps
     of the run shrunk to a smaller plan breaking the same rule (`shrink.shrink`), the
     command that replays it
```
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import logging
import sys
import time
import traceback
from collections.abc import Callable, Collection, Iterator, Sequence
from pathlib import Path
from typing import Any

from rr_actors.errors import ConfigError, RrError
from rr_actors.events.text import describe
from rr_actors_lab.experiments import check, shrink, simulate, story
from rr_actors_lab.experiments.plan import Plan
from rr_actors_lab.experiments.reading import load_plan
from rr_actors_lab.teach import replaced_step
from rr_actors_lab.teach.kit import Exercise, folder_exercise
from rr_actors_lab.teach.rules import RULES

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
    """A folder's own files do not load, so no seed ran: its plan is missing, is not a
    regular file, is too big or is not a plan the simulation runs (its setups do not
    import, among others), or a protocol exercise's `step.py` is missing, does not import
    or lacks its step's function. The message names the file and why."""


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
        cpu_s: CPU seconds the check took (this process).
        failure: the first failure (`None`: passed).
    """

    exercise: str
    passed: bool
    seeds: int
    seeds_run: int
    interleavings: int
    events: int
    cpu_s: float
    failure: Failure | None

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

    Args:
        folder: the folder `start` wrote, as the student changed it.
        seed: one seed to run (a replay).
        seeds: run seeds 1 to this instead of the exercise's (at least 1).
        plan_file: run this plan instead of `folder/plan.toml` (a shrunk one, `SHRUNK`),
            its setups imported from its own folder.
        shrink_budget: the most runs a failure's shrink makes (0: no shrink).
        on_seed: called with each seed once it ran and was judged (progress), on this
            thread; a failing seed's shrink runs before.
        on_shrink: called on this thread with the runs a failing seed's shrink made so far
            (0 as it starts, then after each run).

    Raises:
        ConfigError: `folder` is not an exercise's folder; `seeds` below 1.
        SubmissionError: its `plan.toml` is missing or wrong (file, line, key); a protocol
            exercise's `step.py` is missing, does not import or lacks its step's function.
    """
    chosen, _state = folder_exercise(folder)
    count = chosen.seeds if seeds is None else seeds
    if count < 1:
        raise ConfigError(f"seeds must be at least 1, got {count}")
    chosen_seeds = [seed] if seed is not None else list(range(1, count + 1))
    path = folder / "plan.toml" if plan_file is None else plan_file
    plan = _plan(path)
    managers = {m.name for m in plan.managers()}
    resolve = plan.hosts.resolve if plan.hosts is not None else "first_served"
    started = time.process_time()
    shrink_to = (
        (plan, path, shrink_budget, started + CPU_S, on_shrink) if shrink_budget > 0 else None
    )
    hashes: set[str] = set()
    recorded = attempted = 0
    failure = _intensity(chosen, plan, chosen_seeds[0])
    raised: list[str] = []  # (what the student's step raised, said as it was)
    with _quiet(), _student_step(chosen, folder, raised):
        for number in chosen_seeds if failure is None else ():
            attempted += 1
            try:
                run = simulate.run_seed(plan, number)
            except RrError as exc:  # (the student's setup raised: the tree did not start)
                failure = _setup_failure(chosen, folder, number, exc)
                break
            hashes.add(run.hash)
            recorded += run.events
            failure = _judge(chosen, folder, run, (managers, resolve), shrink_to)
            if raised:  # (whatever the verdict: a step that raises is wrong)
                failure = _raised(chosen, folder, number, raised[0], failure)
            if on_seed is not None:
                on_seed(number)
            if failure is not None:
                break
    if failure is None and plan_file is None:  # (a shrunk plan of a failure fixed since)
        (folder / SHRUNK).unlink(missing_ok=True)
    return Report(
        exercise=chosen.name,
        passed=failure is None,
        seeds=len(chosen_seeds),
        seeds_run=attempted,
        interleavings=len(hashes),
        events=recorded,
        cpu_s=round(time.process_time() - started, 3),
        failure=failure,
    )


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
    managers = {m.name for m in plan.managers()}
    resolve = plan.hosts.resolve if plan.hosts is not None else "first_served"
    failure = _intensity(chosen, plan, run.seed)
    return failure or _judge(chosen, folder, run, (managers, resolve), None)


def rerun(folder: Path | None, seed: int) -> Callable[[Plan], simulate.SimulatedRun]:
    """What runs seed `seed` of a plan as `folder`'s check does (a protocol exercise's
    `step.py` in place; `None`: no exercise): a replay's runs with a fault added."""

    def run(plan: Plan) -> simulate.SimulatedRun:
        if folder is None:
            with _quiet():
                return _seed(plan, seed)
        chosen, _state = folder_exercise(folder)
        with _quiet(), _student_step(chosen, folder):
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


_RETURNS: dict[str, tuple[Callable[[Any, tuple[Any, ...]], bool], str]] = {
    "climb": (
        lambda r, _args: (
            isinstance(r, list | tuple | set | frozenset) and all(isinstance(i, str) for i in r)
        ),
        "a list of resource ids (str)",
    ),
    "shares": (lambda r, _args: isinstance(r, bool), "True or False"),
    "unloads": (lambda r, _args: isinstance(r, bool), "True or False"),
    "in_doubt": (lambda r, _args: isinstance(r, bool), "True or False"),
    "recent": (
        lambda r, _args: isinstance(r, int) and not isinstance(r, bool) and r >= 0,
        "a count of restarts (an int >= 0)",
    ),
    "reconcile": (
        lambda r, _args: (
            isinstance(r, tuple)
            and len(r) == 2
            and all(
                isinstance(part, list | tuple | set | frozenset)
                and all(isinstance(i, str) for i in part)
                for part in r
            )
        ),
        "two sets of query ids (str): (release, unknown)",
    ),
    "release_order": (
        lambda r, args: isinstance(r, list | tuple) and sorted(r) == sorted([*args[0], UNLOAD]),
        'a list of every dependency id and "unload", each once',
    ),
    "group": (
        lambda r, _args: (
            isinstance(r, list | tuple | set | frozenset) and all(isinstance(i, str) for i in r)
        ),
        "a list of child names (str)",
    ),
}
"""What each step must return, as a test (of the result and the step's arguments) and in
words (a student's step is held to it)."""

UNLOAD = "unload"
"""In `release_order`'s answer: where the resource's own unload runs."""


@contextlib.contextmanager
def _student_step(
    chosen: Exercise, folder: Path, raised: list[str] | None = None
) -> Iterator[None]:
    """A protocol exercise: `folder/step.py`'s function in the registrar's place; what
    it raises is added to `raised` (`Type: message (step.py, line N)`), then raised on."""
    if chosen.step is None:
        yield
        return
    path = folder / "step.py"
    if not path.is_file():
        raise SubmissionError(f"{folder} has no step.py: the step you fix (start it again?)")
    spec = importlib.util.spec_from_file_location(f"rr_teach_step_{chosen.name}", path)
    if spec is None or spec.loader is None:
        raise SubmissionError(f"{path} cannot be imported")
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except Exception as exc:  # noqa: BLE001 - the student's code: said, not raised
        raise SubmissionError(f"{path} does not import: {type(exc).__name__}: {exc}") from None
    step = getattr(module, chosen.step, None)
    if not callable(step):
        raise SubmissionError(f"{path} has no function {chosen.step!r}: the step you fix")

    returns = _RETURNS.get(chosen.step)

    def watched(*args: Any) -> Any:
        try:
            result = step(*args)
            if returns is not None and not returns[0](result, args):
                raise TypeError(f"it must return {returns[1]}, not {result!r}")  # noqa: TRY301
        except Exception as exc:
            if raised is not None:
                line = next(
                    (f.lineno for f in reversed(traceback.extract_tb(exc.__traceback__))
                     if Path(f.filename) == path),
                    None,
                )  # fmt: skip
                where = f" (step.py, line {line})" if line is not None else ""
                raised.append(f"{type(exc).__name__}: {exc}{where}")
            raise
        return result

    with replaced_step(chosen.step, watched):
        yield


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
    run: simulate.SimulatedRun,
    known: tuple[set[str], str],
    shrink_to: tuple[Plan, Path, int, float, Callable[[int], None] | None] | None,
) -> Failure | None:
    """The first finding of `run` (the checker's, then the kit's), told on the run shrunk
    (`shrink_to`) if the shrink finds it again; `None`: held. `known`: the plan's managers and
    its rule 22 policy."""
    kit_rules = [RULES[name] for name in chosen.rules]
    if run.verdict == "held" and not kit_rules:
        return None
    numbered, findings = _findings(run, kit_rules, *known)
    if not findings and run.verdict != "crashed":
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
    if shrink_to is not None:  # (judged by the same rules: the kit's too)
        shrunk = _shrunk(run, folder, shrink_to, lambda r: _findings(r, kit_rules, *known)[1])
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
    run: simulate.SimulatedRun,
    kit_rules: list[Callable[[Sequence[check.Line], Collection[str]], list[check.Finding]]],
    managers: set[str],
    resolve: str,
) -> tuple[list[check.Line], list[check.Finding]]:
    """A run's numbered events and its violations (the checker's and the kit's), the
    first broken first."""
    numbered = check.read_runs(run.history.splitlines()).get(simulate.RUN, [])
    findings: list[check.Finding] = []
    if run.verdict == "violated":
        findings += [f for f in check.check(numbered, resolve).findings if f.kind == "violation"]
    for rule in kit_rules:
        findings += rule(numbered, managers)
    findings.sort(key=lambda f: max(f.lines, default=0))  # (broken at its last event)
    return numbered, findings


def _shrunk(
    run: simulate.SimulatedRun,
    folder: Path,
    shrink_to: tuple[Plan, Path, int, float, Callable[[int], None] | None],
    judge: shrink.Judge,
) -> tuple[simulate.SimulatedRun, list[check.Line], check.Finding, int] | None:
    """`run` shrunk to a smaller plan showing its first violation again (its plan written to
    `folder / SHRUNK`): run, events, finding and seed; `None`: not found again."""
    plan, path, budget, cpu_until, on_run = shrink_to
    text = path.read_text(encoding="utf-8")
    if on_run is not None:
        on_run(0)
    try:
        shrunk = shrink.shrink(
            plan, run.seed, budget=budget, text=text, judge=judge, cpu_until=cpu_until,
            on_run=on_run,
        )  # fmt: skip
    except (ConfigError, RrError):
        return None
    numbered = check.read_runs(shrunk.run.history.splitlines()).get(simulate.RUN, [])
    same = [f for f in judge(shrunk.run) if shrink.violation_kind(f.rule, f.message) == shrunk.kind]
    if not same:
        return None
    header = (
        f"# {path.name}'s seed {run.seed} shrunk ({run.events} events to "
        f"{shrunk.run.events}): it shows {shrunk.kind} at seed {shrunk.seed}.\n"
        f"# rr-actors teach check {folder} --plan {folder / SHRUNK} --seed {shrunk.seed} "
        "--story\n\n"
    )
    (folder / SHRUNK).write_text(header + shrunk.text, encoding="utf-8")
    return shrunk.run, numbered, same[0], shrunk.seed


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


def _intensity(chosen: Exercise, plan: Plan, seed: int) -> Failure | None:
    """A supervisor of `plan` whose intensity is above the exercise's bound (before any
    run: no intensity that high stops a crash loop in time), told; `None`: none."""
    bound = chosen.most_restarts_per_s
    if bound is None:
        return None
    for sup in plan.tree.supervisors():
        per_s = sup.max_restarts / sup.period if sup.period > 0 else float("inf")
        if per_s > bound:
            message = (
                f"supervisor {sup.name} allows {sup.max_restarts} restarts within "
                f"{sup.period:g} s ({per_s:g} a second): above {bound:g} a second, a child "
                "that crashes at every start is restarted on and on instead of stopped"
            )
            return Failure(seed, "intensity-bound", chosen.rule, message, None, (), 0, 0, "")
    return None


def _raised(
    chosen: Exercise, folder: Path, seed: int, said: str, failure: Failure | None
) -> Failure:
    """The failure of a seed in which the student's step raised: said first, with the
    run's own failure's story if it has one."""
    message = f"your {chosen.step} raised {said}"
    if failure is None:
        replay = f"rr-actors teach check {folder} --seed {seed} --story"
        return Failure(seed, "step-raised", chosen.rule, message, None, (), 0, 0, replay)
    also = f"{message}; and then [{failure.rule}] {failure.message}"
    return dataclasses.replace(failure, rule="step-raised", message=also)


def _setup_failure(chosen: Exercise, folder: Path, seed: int, exc: RrError) -> Failure:
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
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
