"""`rr-actors teach`: list, start, check, hint, solution, replay (`rr_actors_lab.teach`)."""

from __future__ import annotations

import argparse
import contextlib
import json
import threading
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from rr_actors._extras import needs
from rr_actors.errors import ConfigError
from rr_actors_lab.teach import kit

if TYPE_CHECKING:
    from rr_actors_lab.teach import grade

__all__ = ["HELP", "add_arguments", "main"]

HELP = "a classroom kit: exercises checked by the verdict of simulated runs"

CHECK_FAILED = 1
"""The exit code of a check that failed (0: it passed; 1 also for bad input, said)."""


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
    replay.add_argument("--plan", type=Path, help="this plan (a shrunk one, or any simulable plan)")
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
    """Run `rr-actors teach SUBCOMMAND`; its exit code (0; 1: a check failed).

    Raises:
        ConfigError: bad input (an unknown exercise, a folder that is not one, a plan
            or step that does not load, `--story` without `--seed`).
    """
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
    observer, shown = replay.open_replay(plan, run, port=args.port, rerun=rerun)
    with observer:
        out.write(
            f"replay of {plan.name}, seed {run.seed} ({len(shown)} steps; the checker: "
            f"{run.verdict}): "
            f"{observer.url} (Ctrl-C stops)\n"
        )
        out.flush()
        with contextlib.suppress(KeyboardInterrupt):
            threading.Event().wait(args.duration)
    return 0


def _solution(args: argparse.Namespace, out: TextIO) -> int:
    folder = Path(args.target)
    if (folder / kit.STATE).is_file():
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
    folder: Path = args.folder
    kit.folder_exercise(folder)  # (said before a child process starts)
    argv = ["teach", "check", str(folder)]
    for flag in ("seed", "seeds", "json", "plan"):
        if getattr(args, flag) is not None:
            argv += [f"--{flag}", str(getattr(args, flag))]
    argv += ["--story"] if args.story else []
    code = sweep.hash_fixed(argv, out)  # (the same seed, the same history: PYTHONHASHSEED)
    if code is not None:
        return code
    if args.story:
        out.write("".join(f"{line}\n" for line in grade.replay_story(folder, args.seed, args.plan)))
        return 0
    report = grade.check_folder(folder, seed=args.seed, seeds=args.seeds, plan_file=args.plan)
    if args.json is not None:
        args.json.write_text(json.dumps(report.as_dict(), indent=2) + "\n", encoding="utf-8")
    out.write(_told(report))
    return 0 if report.passed else CHECK_FAILED


def _told(report: grade.Report) -> str:
    from rr_actors_lab.teach.grade import SHRUNK, STORY  # noqa: PLC0415 - imported by the check

    failure = report.failure
    if failure is None:
        return (
            f"{report.exercise}: PASSED: {report.seeds} seeds, {report.interleavings} "
            f"interleavings, {report.events} events checked, every rule held "
            f"({report.cpu_s:.1f} CPU s)\n"
        )
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
