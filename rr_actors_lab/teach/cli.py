"""`rr-actors teach`: list, start, check, hint, solution, replay (`rr_actors_lab.teach`).

```
 teach check DIR ─ DIR/.teach.json (`kit.folder_exercise`: not an exercise's? exit 2)
   PYTHONHASHSEED is not 0? ─► the same command in a child process with it
   grade.check_folder ─ on_seed, on_shrink ─► progress on standard error: a bar on a
   │                                          terminal, else a line every PROGRESS_EVERY
   └─► the report on standard output; the exit code (`EXIT_CODES`)
```

A grading script tells the outcomes apart by the exit code alone (as pytest's):
`EXIT_CODES` lists them. Every error is one line on standard error naming the file and
what is wrong with it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import threading
import time
import traceback
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from rr_actors._extras import needs
from rr_actors._log import terminal_width, wrap
from rr_actors.errors import ConfigError, MissingExtraError
from rr_actors_lab.teach import kit

if TYPE_CHECKING:
    from rich.progress import Progress as RichProgress
    from rich.progress import TaskID

    from rr_actors_lab.teach import grade, replay

__all__ = [
    "BAD_INPUT",
    "CHECK_FAILED",
    "EXIT_CODES",
    "HELP",
    "KIT_ERROR",
    "NOT_LOADED",
    "PASSED",
    "PROGRESS_EVERY",
    "add_arguments",
    "main",
]

HELP = "a classroom kit: exercises checked by the verdict of simulated runs"

PASSED = 0
"""`teach check`: every seed held every rule (other subcommands: done)."""
CHECK_FAILED = 1
"""`teach check`: a seed broke a rule (the report names it)."""
BAD_INPUT = 2
"""Usage: bad arguments, a folder that is not an exercise's (no `.teach.json`, or one
refused), an unknown exercise, a missing extra; nothing was checked."""
NOT_LOADED = 3
"""The folder's files cannot be checked: its `plan.toml` is missing, refused (not a
regular file, too big) or not a plan, its `step.py` does not import or lacks its
function, a file that is not the student's changed, the student's code ended the check's
process, or its setup raised (the tree did not start); no seed was judged."""
KIT_ERROR = 4
"""The check itself raised (a traceback on standard error): neither passed nor failed."""

EXIT_CODES = {
    PASSED: "passed",
    CHECK_FAILED: "failed: a seed broke a rule",
    BAD_INPUT: "bad input: not an exercise's folder, bad arguments",
    NOT_LOADED: "the folder's files cannot be checked (do not load, or changed what is not yours)",
    KIT_ERROR: "the check itself raised (a traceback)",
    130: "stopped by Ctrl-C (128 + the signal: 143 SIGTERM, 129 SIGHUP)",
}
"""`rr-actors teach`'s exit codes, in words (`docs/reference/cli.md`)."""

PROGRESS_EVERY = 20
"""Without a terminal, a check's progress is a line after the first seed, then after every
this many seeds (and shrink runs), and after the last."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add `teach`'s subcommands to `parser`."""
    sub = parser.add_subparsers(dest="teach_command", metavar="SUBCOMMAND", required=True)
    sub.add_parser("list", help="the exercises, one a line: name, kind, level, topic")
    start = sub.add_parser("start", help="write an exercise's README and starter files")
    start.add_argument("name", help="the exercise (`rr-actors teach list`)")
    start.add_argument("folder", nargs="?", type=Path, help="where (default: ./NAME)")
    check = sub.add_parser(
        "check", help="run the exercise's plan over its seeds in simulation: the verdict"
    )
    check.add_argument("folder", nargs="?", type=Path, default=Path(), help="(default: .)")
    check.add_argument("--seed", type=int, help="run this seed alone (a failure's replay)")
    check.add_argument("--seeds", type=int, help="run seeds 1 to this (default: the exercise's)")
    check.add_argument("--story", action="store_true", help="with --seed: its whole story")
    check.add_argument(
        "--plan", type=Path, help="run this plan instead of FOLDER/plan.toml (a shrunk one)"
    )
    check.add_argument("--json", type=Path, metavar="FILE", help="write the report as JSON")
    check.add_argument(
        "--quiet", "-q", action="store_true", help="no progress on standard error (the report)"
    )
    replay = sub.add_parser(
        "replay", help="a seed of a check step by step in the browser (the observer's page)"
    )
    replay.add_argument(
        "folder",
        nargs="?",
        type=Path,
        help="an exercise's folder (default: .; none with --plan)",
    )
    replay.add_argument("--seed", type=int, default=1, help="the seed (default: 1)")
    replay.add_argument(
        "--plan",
        type=Path,
        help="this plan (a shrunk one: judged by its folder's exercise; or any simulable plan)",
    )
    replay.add_argument("--port", type=int, default=0, help="the page's port (default: a free one)")
    replay.add_argument(
        "--for", dest="duration", type=float, metavar="SECONDS", help="serve this long (Ctrl-C)"
    )
    hint = sub.add_parser("hint", help="the next hint (the folder remembers those shown)")
    hint.add_argument("folder", nargs="?", type=Path, default=Path(), help="(default: .)")
    solution = sub.add_parser("solution", help="the solution's files (for a teacher)")
    solution.add_argument("target", nargs="?", default=".", help="an exercise or its folder")
    solution.add_argument("--teacher", action="store_true", help="yes, show the solution")


def main(args: argparse.Namespace, out: TextIO) -> int:
    """Run `rr-actors teach SUBCOMMAND`; its exit code (`EXIT_CODES`): bad input and
    files that do not load are said in one line on standard error.

    Raises:
        MissingExtraError: the subcommand needs an extra that is missing.
    """
    try:
        return _main(args, out)
    except MissingExtraError:
        raise
    except ConfigError as exc:
        _error(f"rr-actors teach {args.teach_command}: {exc}")
        graded = sys.modules.get("rr_actors_lab.teach.grade")  # (none imported: none raised)
        return NOT_LOADED if graded and isinstance(exc, graded.SubmissionError) else BAD_INPUT


def _error(line: str) -> None:
    """`line` on standard error, wrapped at words on a terminal it does not fit."""
    width = terminal_width(sys.stderr)
    sys.stderr.write(f"{line if width is None else wrap(line, width)}\n")
    sys.stderr.flush()


def _main(args: argparse.Namespace, out: TextIO) -> int:
    command = args.teach_command
    if command == "list":
        for e in kit.exercises():
            out.write(f"{e.name:<14} {e.kind:<9} level {e.level}  {e.topic}: {e.title}\n")
        return 0
    if command == "start":
        chosen, folder = kit.start(args.name, args.folder)
        out.write(
            f"{chosen.name}: {chosen.title}\nwritten to {folder}/: README.md, "
            f"{', '.join(chosen.starter())}\nread {folder}/README.md, then: "
            f"rr-actors teach check {folder}\n"
        )
        return 0
    if command == "hint":
        chosen, number, text = kit.next_hint(args.folder)
        if text is None:
            out.write(f"{chosen.name}: no more hints (all {number} shown)\n")
        else:
            out.write(f"hint {number} of {len(chosen.hints)}: {text}\n")
        return 0
    if command == "solution":
        return _solution(args, out)
    if command == "replay":
        return _replay(args, out)
    return _check(args, out)


def _replay(args: argparse.Namespace, out: TextIO) -> int:
    with needs("teach", "rr-actors teach replay"):
        from rr_actors_lab.experiments import sweep  # noqa: PLC0415 - the run's (hash seed)
        from rr_actors_lab.teach import grade, replay  # noqa: PLC0415 - the simulation
    with needs("observe", "rr-actors teach replay"):
        from rr_actors_lab.observe import require_extra  # noqa: PLC0415

        require_extra()
    folder: Path | None = args.folder
    if folder is None and args.plan is None:
        folder = Path()
    elif folder is None and os.path.lexists(args.plan.parent / kit.STATE):
        folder = args.plan.parent  # (a plan in an exercise's folder, shrunk.toml: its rules)
    if folder is not None:
        kit.folder_exercise(folder)  # (said before a child process starts)
    argv = ["teach", "replay", *([str(folder)] if folder is not None else [])]
    argv += ["--seed", str(args.seed), "--port", str(args.port)]
    argv += ["--plan", str(args.plan)] if args.plan is not None else []
    argv += ["--for", str(args.duration)] if args.duration is not None else []
    code = sweep.hash_fixed(argv, out)  # (the seed's history as its check saw it)
    if code is not None:
        return code
    plan, run = grade.seed_run(folder, args.seed, args.plan)
    rerun = grade.rerun(folder, args.seed)
    judge = None if folder is None else replay.exercise_verdict(folder)
    observer, shown = replay.open_replay(plan, run, port=args.port, rerun=rerun, judge=judge)
    with observer:
        out.write(
            f"replay of {plan.name}, seed {run.seed} ({len(shown)} steps; the check: "
            f"{_verdict_words(shown)}): {observer.url} (Ctrl-C stops)\n"
        )
        out.flush()
        with contextlib.suppress(KeyboardInterrupt):
            threading.Event().wait(args.duration)
    return 0


def _verdict_words(shown: replay.Replay) -> str:
    verdict = shown.verdict
    if verdict.passed:
        return "passed"
    at = f" at step {shown.violating}" if shown.violating is not None else ""
    return f"FAILED, [{verdict.rule}]{at}"


def _solution(args: argparse.Namespace, out: TextIO) -> int:
    folder = Path(args.target)
    if os.path.lexists(folder / kit.STATE):  # (one that is not a file: refused as such)
        chosen, _state = kit.folder_exercise(folder)
    else:
        chosen = kit.exercise(args.target)
    if not args.teacher:
        raise ConfigError("the solution is for a teacher: add --teacher")
    for name, text in kit.solution_files(chosen).items():
        out.write(f"# ---- {name} ----\n{text}")
    return 0


def _check(args: argparse.Namespace, out: TextIO) -> int:
    with needs("teach", "rr-actors teach check"):  # (greenlet, msgspec: one line if missing)
        from rr_actors import simulation  # noqa: F401, PLC0415 - a check's runs
        from rr_actors_lab.experiments import sweep  # noqa: PLC0415 - a check's own (hash seed)
        from rr_actors_lab.teach import grade  # noqa: PLC0415 - the simulation: only a check

    if args.story and args.seed is None:
        raise ConfigError("--story tells one seed: add --seed S")
    if args.seeds is not None and args.seeds < 1:
        raise ConfigError(f"--seeds must be at least 1, got {args.seeds}")
    folder: Path = args.folder
    chosen, _state = kit.folder_exercise(folder)  # (said before a child process starts)
    argv = ["teach", "check", str(folder)]
    for flag in ("seed", "seeds", "json", "plan"):
        if getattr(args, flag) is not None:
            argv += [f"--{flag}", str(getattr(args, flag))]
    argv += ["--story"] if args.story else []
    argv += ["--quiet"] if args.quiet else []
    code = sweep.hash_fixed(argv, out)  # (the same seed, the same history: PYTHONHASHSEED)
    if code is not None:
        return code
    try:
        with sweep.stopping_on_signals():
            if args.story:
                lines = grade.replay_story(folder, args.seed, args.plan)
                out.write("".join(f"{line}\n" for line in lines))
                return PASSED
            total = 1 if args.seed is not None else (args.seeds or chosen.seeds)
            with _Progress(sys.stderr, chosen.name, total, quiet=args.quiet) as progress:
                report = grade.check_folder(
                    folder,
                    seed=args.seed,
                    seeds=args.seeds,
                    plan_file=args.plan,
                    on_seed=progress.seed,
                    on_shrink=progress.shrink,
                )
    except KeyboardInterrupt as exc:
        _error(f"rr-actors teach check: {sweep.stopped_line(exc)}")
        return sweep.stopped_code(exc)
    except ConfigError:
        raise  # (bad input, files that do not load: one line, `main`)
    except (Exception, SystemExit):  # noqa: BLE001 - told: not a pass, not a failure
        traceback.print_exc()
        _error(
            "rr-actors teach check: the check itself raised (above): neither passed nor "
            f"failed (exit {KIT_ERROR})"
        )
        return KIT_ERROR
    out.write(_told(report))
    if args.json is not None:
        try:
            args.json.write_text(json.dumps(report.as_dict(), indent=2) + "\n", encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"--json {args.json}: cannot be written ({exc.strerror})") from None
    return {"passed": PASSED, "failed": CHECK_FAILED}.get(report.outcome, NOT_LOADED)


class _Progress:
    """A check's progress on `stream`: a bar (rich) on a terminal, else a line after the
    first seed, every `PROGRESS_EVERY` seeds and the last; a failing seed's shrink the same
    way. Nothing with `quiet`. Its methods run on the check's thread."""

    def __init__(self, stream: TextIO, name: str, total: int, *, quiet: bool) -> None:
        self.stream, self.name, self.total, self.quiet = stream, name, total, quiet
        self.done = 0
        self.started = time.monotonic()
        self.bar: RichProgress | None = None
        self.seeds_task: TaskID | None = None
        self.shrink_task: TaskID | None = None
        if quiet or not stream.isatty():
            return
        try:
            from rich.console import Console  # noqa: PLC0415 - rich is optional
            from rich.progress import (  # noqa: PLC0415
                BarColumn,
                MofNCompleteColumn,
                TextColumn,
                TimeElapsedColumn,
            )
            from rich.progress import Progress as RichProgress  # noqa: PLC0415
        except ImportError:  # (lines, then)
            return
        self.bar = RichProgress(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=Console(file=stream),
            transient=True,
        )
        self.seeds_task = self.bar.add_task(f"{name}: seeds", total=total)

    def __enter__(self) -> _Progress:
        if self.bar is not None:
            self.bar.start()
        return self

    def __exit__(self, *_: object) -> None:
        if self.bar is not None:
            self.bar.stop()

    def seed(self, number: int) -> None:
        """Seed `number` ran and was judged."""
        self.done += 1
        if self.bar is not None and self.seeds_task is not None:
            description = f"{self.name}: seed {number}"
            self.bar.update(self.seeds_task, completed=self.done, description=description)
        elif self._due(self.done, self.total):
            self._say(f"seeds: {self.done}/{self.total} run")

    def shrink(self, runs: int) -> None:
        """A failing seed's shrink made `runs` runs (0: it starts)."""
        from rr_actors_lab.teach.grade import SHRINK_BUDGET  # noqa: PLC0415 - a check's

        if runs == 0:
            self._say(
                f"seed {self.done + 1} broke a rule: shrinking its run to a shorter story "
                f"(at most {SHRINK_BUDGET} runs)"
            )
            if self.bar is not None:
                self.shrink_task = self.bar.add_task(f"{self.name}: shrink", total=SHRINK_BUDGET)
        elif self.bar is not None and self.shrink_task is not None:
            self.bar.update(self.shrink_task, completed=runs)
        elif runs % PROGRESS_EVERY == 0:
            self._say(f"shrink: {runs}/{SHRINK_BUDGET} runs")

    def _due(self, done: int, total: int) -> bool:
        return not self.quiet and (done in (1, total) or done % PROGRESS_EVERY == 0)

    def _say(self, line: str) -> None:
        if self.quiet:
            return
        if self.bar is not None:
            self.bar.console.print(line, highlight=False, markup=False, emoji=False)
            return
        self.stream.write(f"{line} ({time.monotonic() - self.started:.0f} s)\n")
        self.stream.flush()


def _told(report: grade.Report) -> str:
    from rr_actors_lab.teach.grade import SHRUNK, STORY  # noqa: PLC0415 - imported by the check

    failure = report.failure
    if failure is None:
        return (
            f"{report.exercise}: PASSED: {report.seeds} seeds, {report.interleavings} "
            f"interleavings, {report.events} events checked, every rule held "
            f"({report.cpu_s:.1f} CPU s)\n"
        )
    if report.outcome == "not-loaded":  # (exit NOT_LOADED: nothing was judged)
        return f"{report.exercise}: NOT CHECKED: seed {failure.seed}: {failure.message}\n"
    lines = [
        f"{report.exercise}: FAILED on seed {failure.seed} ({report.seeds_run - 1} seeds "
        f"held before it)"
        if report.seeds_run
        else f"{report.exercise}: FAILED before any seed ran: its plan breaks the rule",
        f"the rule: {failure.words}",
        f"broken: [{failure.rule}] {failure.message}",
    ]
    if failure.first_event is not None:
        lines.append(f"first violating event: {failure.first_event}")
    if failure.story:
        of = f"the run's {failure.run_events} events"
        if failure.shrunk_events is not None:
            of = (
                f"the {failure.shrunk_events} events of the run shrunk from "
                f"{failure.run_events} (plan {SHRUNK}, seed {failure.shrunk_seed})"
            )
        lines.append(
            f"the story ({failure.story_events} steps of {of}: the faults and the "
            "registrars concerned, up to the violation):"
        )
        if failure.shrunk_events is None and failure.run_events > STORY:
            lines.append("  (not shrunk: no smaller plan found that breaks it: the run's own)")
        elif (failure.shrunk_events or 0) > STORY:
            lines.append(
                f"  (the shrink stopped at {failure.shrunk_events} events, not {STORY}: "
                "the steps below are those of its run that concern the violation)"
            )
        lines += [f"  {line}" for line in failure.story]
    if failure.replay:
        lines.append(f"replay it whole: {failure.replay}")
    return "".join(f"{line}\n" for line in lines)
