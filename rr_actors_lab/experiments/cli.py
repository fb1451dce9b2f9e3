"""`rr-actors experiment PLAN --out DIR`: run an experiment from the command line.

    rr-actors experiment --list                  # the shipped plans
    rr-actors experiment strategies --out results
    rr-actors experiment plan.toml --out results --repeat 5 --seed 42 --force

A progress bar with `rich` (`pip install 'rr-actors[experiments]'`), else a line per run;
at the end a summary per compared value, the faults' lateness and skips, the verdicts and
the files written. Exit codes: `main`'s. A full disk under `--out` is exit 1 in one line,
the files then agreeing with each other.
"""

from __future__ import annotations

import argparse
import contextlib
import re
import signal
import statistics
import sys
import textwrap
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from rr_actors._extras import install_command, needs
from rr_actors.errors import ConfigError, RrError, _known_names
from rr_actors_lab.experiments import experiment, plans, shrink, simulate, sweep
from rr_actors_lab.experiments.experiment import (
    ExperimentError,
    ExperimentInterruptedError,
    Progress,
)
from rr_actors_lab.experiments.metrics import percentile
from rr_actors_lab.experiments.reading import load_plan
from rr_actors_lab.experiments.results import Results, RunResult, show_value
from rr_actors_lab.observe import require_extra

if TYPE_CHECKING:
    from rich.console import Console
    from rich.progress import Progress as RichProgress
    from rich.progress import TaskID
    from rich.table import Table as RichTable

    from rr_actors_lab.experiments.plan import Plan

__all__ = [
    "INTERRUPTED_EXIT",
    "Display",
    "add_arguments",
    "error",
    "fault_line",
    "main",
    "plan_file",
    "summary_lines",
]

INTERRUPTED_EXIT = 130
"""Exit code after Ctrl-C (128 + SIGINT), as shells use."""


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text}")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be a positive number of seconds, got {text}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the `experiment` subcommand's arguments to `parser`."""
    parser.add_argument(
        "plan",
        nargs="?",
        help="a plan file (TOML), or the name of a plan shipped with rr_actors (--list); "
        "the format: docs/reference/plan.md (and plan-reference.md beside the shipped plans)",
    )
    parser.add_argument("--list", action="store_true", help="name the shipped plans and exit")
    parser.add_argument(
        "--out",
        help="output directory (required to run): events.jsonl, runs.csv, faults.csv, "
        "recovery.png, timeline.png, plan.toml (must be empty or new, unless --force)",
    )
    parser.add_argument(
        "--repeat",
        type=_positive_int,
        default=None,
        help="runs per compared value (default: the plan's)",
    )
    parser.add_argument(
        "--seed", type=int, default=None, help="seed of the first repeat (default: the plan's)"
    )
    parser.add_argument(
        "--duration",
        type=_positive_float,
        default=None,
        help="seconds per run (default: the plan's; later faults are dropped)",
    )
    parser.add_argument(
        "--observe",
        action="store_true",
        help="serve each run's live observer page (Supervisor.observe) and print its URL",
    )
    parser.add_argument(
        "--trace",
        action="store_true",
        help="make OpenTelemetry spans of each run's steps (a client's call, unload, a "
        "fault), calls, loads and restarts, exported where the OTEL_* environment variables "
        "say (OTEL_TRACES_EXPORTER: default otlp, to a collector; the run processes' output "
        "is not shown); needs the otel extra",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="replace the experiment files in a non-empty --out",
    )
    parser.add_argument(
        "--quiet", action="store_true", help="no progress: print only the summary and the files"
    )
    parser.add_argument(
        "--simulate",
        action="store_true",
        help="run the plan on the simulation (virtual time, one seed a run, each replayable: "
        "rr-actors replay): a verdict per seed, the violating seeds, seeds.jsonl",
    )
    parser.add_argument(
        "--seeds",
        metavar="A-B",
        help="with --simulate: the seeds to run, A to B included, or one seed (default: 1)",
    )
    parser.add_argument(
        "--jobs",
        type=_positive_int,
        default=None,
        metavar="N",
        help="with --simulate: run the seeds in N processes (default: the cores available, "
        "at most one per seed); the same hashes, verdicts and seeds.jsonl as one process",
    )
    parser.add_argument(
        "--seed-timeout",
        type=_positive_float,
        default=None,
        metavar="S",
        help="with --simulate: the wall seconds a worker process may run one seed before it "
        f"is killed as hung and the seed named lost (default: {sweep.SEED_TIMEOUT:g}, or "
        f"{sweep.SLOWEST_TIMES} times the slowest seed so far if longer; given, the seeds run "
        "in worker processes even with --jobs 1)",
    )
    parser.add_argument(
        "--shrink",
        nargs="?",
        type=_positive_int,
        const=shrink.BUDGET,
        metavar="RUNS",
        help="with --simulate: shrink the first violating seed of each violation kind to a "
        "small plan that violates the same way, in at most RUNS simulated runs each "
        f"(default {shrink.BUDGET}; DIR/shrunk-seed-S: rr-actors replay reads it)",
    )


def _value(progress: Progress | RunResult) -> str:
    if progress.value is None:
        return ""
    return f"{progress.setting}={show_value(progress.value)} "


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value * 1e3:.0f} ms"


RUN_LINE_WIDTH = 80
"""The widest a plain line is (a pipe, a file): longer ones wrap at words, indented."""


def wrap(text: str, width: int = RUN_LINE_WIDTH, indent: str = "    ") -> list[str]:
    """`text` in lines of at most `width` columns, broken between words (a word longer
    than a line, a path or a URL, stays whole on a line of its own), never cut."""
    return textwrap.wrap(
        text, width, subsequent_indent=indent, break_long_words=False, break_on_hyphens=False
    ) or [""]


def run_line(result: RunResult, runs: int) -> str:
    """One finished run in lines of at most `RUN_LINE_WIDTH` columns (wrapped at words, never
    cut): `run 2/4 rest_for_one seed 1: 46 calls ok, 0 failed, 4 restarts, rec. p50 172 ms`,
    then its verdict, and each finding on lines of their own."""
    value = "" if result.value is None else show_value(result.value)
    rest = (
        f"seed {result.seed}: {result.calls_ok} calls ok, {result.calls_failed} failed, "
        f"{result.restarts} restarts, rec. p50 {_ms(result.recovery_median_s)}"
        + (", gave up" if result.gave_up else "")
        + (f", {result.verdict}" if result.verdict else "")
    )
    line = " ".join(part for part in (f"run {result.run}/{runs}", value, rest) if part)
    return "\n".join(wrapped for text in (line, *result.findings) for wrapped in wrap(text))


SUMMARY_HEADERS = ("runs", "faults", "rec. p50", "p90", "failed", "retried", "down s", "left")
SUMMARY_WIDTHS = (18, 4, 6, 8, 7, 6, 7, 6, 4)  # with the spaces between: 74 columns
SUMMARY_NOTE = (
    "rec. p50, p90: recovery per fault, from the injection until the system served again; "
    "failed, retried (calls) and down s (not serving, all managers): mean per run; "
    "left: catalog entries and processes left, all runs"
)


def summary_rows(results: Results) -> list[list[str]]:
    """The summary's cells per compared value (the first: the value, or the strategy)."""
    rows = []
    for value, runs in results.by_value():
        if not runs:
            continue
        recoveries = [r for run in runs for r in run.recoveries()]
        rows.append(
            [
                results.plan.tree.strategy if value is None else show_value(value),
                str(len(runs)),
                str(sum(1 for run in runs for f in run.faults if not f.skipped)),
                _ms(percentile(recoveries, 50)),
                _ms(percentile(recoveries, 90)),
                f"{statistics.mean(run.calls_failed for run in runs):.1f}",
                f"{statistics.mean(run.calls_retried for run in runs):.1f}",
                f"{statistics.mean(sum(run.unavailable_s.values()) for run in runs):.2f}",
                str(sum(max(0, run.catalog_entries_left) + run.leaked_processes for run in runs)),
            ]
        )
    return rows


def verdict_line(results: Results) -> str:
    """The runs' verdicts (`rr_actors_lab.experiments.check`), counted, under the summary."""
    runs = results.runs
    counts = {
        v: sum(1 for r in runs if r.verdict == v) for v in ("held", "violated", "unverifiable")
    }
    findings = sum(r.violations for r in runs), sum(r.unverifiable for r in runs)
    return (
        f"verdicts: {counts['held']} held, {counts['violated']} violated, "
        f"{counts['unverifiable']} unverifiable ({findings[0]} violations, {findings[1]} "
        f"unverifiable findings; rr-actors check OUT shows each)"
    )


FAULT_REASONS_SHOWN = 3
"""Distinct reasons for skipped faults the fault line names; faults.csv has every one."""


def fault_line(results: Results) -> str | None:
    """How late the injections were and why any was skipped (first run; alike reasons counted
    `+2 like it`), under the summary: `faults: 12 injected, 0.6-1.0 s late; 1 skipped (...)`;
    `None`: no fault."""
    faults = list(results.faults())
    if not faults:
        return None
    late = [f.late_s for _, f in faults if f.late_s is not None]
    injected = sum(1 for _, f in faults if not f.skipped)
    line = f"faults: {injected} injected" + (
        f", {_span(min(late), max(late))} late" if late else ""
    )
    reasons: dict[str, tuple[str, int]] = {}  # the reason, its pids masked -> (shown, count)
    for run, fault in faults:
        if fault.skipped:
            key = re.sub(r"\d+", "N", fault.detail)
            shown, count = reasons.get(key, (f"run {run.run}: {fault.detail}", 0))
            reasons[key] = (shown, count + 1)
    if not reasons:
        return line + "; none skipped"
    named = [
        shown + (f" (+{count - 1} like it)" if count > 1 else "")
        for shown, count in list(reasons.values())[:FAULT_REASONS_SHOWN]
    ]
    more = len(reasons) - FAULT_REASONS_SHOWN
    if more > 0:
        named.append(f"{more} other reason(s) in faults.csv")
    skipped = sum(count for _, count in reasons.values())
    return f"{line}; {skipped} skipped ({'; '.join(named)})"


def _span(low: float, high: float) -> str:
    """`low`-`high` seconds in one unit, with the digits that matter: `0.6-1.0 s`,
    `20-310 ms`, `0.02-0.06 ms`; one value if both show the same."""
    scale, unit = (1.0, "s") if abs(high) >= 1.0 else (1e3, "ms")

    def shown(value: float) -> str:
        size = abs(high * scale)
        return f"{value * scale:.{0 if size >= 10 else 1 if size >= 1 else 2}f}"

    low_text, high_text = shown(low), shown(high)
    if low_text == high_text:
        return f"{high_text} {unit}"
    return f"{low_text}{'-' if low >= 0 else ' to '}{high_text} {unit}"


def summary_lines(results: Results) -> list[str]:
    """The summary per compared value as plain lines of at most 80 columns."""
    label = results.plan.setting_label() or "strategy"

    def lines(cells: list[str]) -> list[str]:
        """The row; a first cell too long for its column on a line of its own, whole."""
        rest = (f"{c:>{w}}" for c, w in zip(cells[1:], SUMMARY_WIDTHS[1:], strict=True))
        if len(cells[0]) <= SUMMARY_WIDTHS[0]:
            return [" ".join([f"{cells[0]:<{SUMMARY_WIDTHS[0]}}", *rest])]
        return [*wrap(cells[0], indent=""), " ".join([" " * SUMMARY_WIDTHS[0], *rest])]

    rows = [*lines([label, *SUMMARY_HEADERS])]
    for row in summary_rows(results):
        rows.extend(lines(row))
    return [*rows, *wrap(SUMMARY_NOTE, indent="")]


def summary_table(results: Results) -> RichTable:
    """The summary as a `rich` table: it fits the terminal, its note wraps under it."""
    from rich import box  # noqa: PLC0415 - rich is optional
    from rich.table import Table  # noqa: PLC0415

    table = Table(
        box=box.SIMPLE_HEAD,
        show_edge=False,
        pad_edge=False,
        collapse_padding=True,
        caption=SUMMARY_NOTE,
        caption_justify="left",
    )
    table.add_column(results.plan.setting_label() or "strategy", overflow="fold")
    for header in SUMMARY_HEADERS:
        table.add_column(header, justify="right", no_wrap=True)
    for row in summary_rows(results):
        table.add_row(*row)
    return table


class Display:
    """Progress on a terminal (rich) or as plain lines."""

    def __init__(self, stream: TextIO, *, quiet: bool) -> None:
        self.stream = stream
        self.quiet = quiet
        self.bar: RichProgress | None = None
        self.console: Console | None = None  # on a terminal with rich: it fits the width
        self.task: TaskID | None = None
        self.done = 0.0
        if stream.isatty():
            try:
                from rich.console import Console  # noqa: PLC0415
                from rich.progress import (  # noqa: PLC0415
                    BarColumn,
                    TextColumn,
                    TimeRemainingColumn,
                )
                from rich.progress import Progress as RichProgress  # noqa: PLC0415
            except ImportError:
                return
            self.console = Console(file=stream)
            if quiet:
                return
            self.bar = RichProgress(
                TextColumn("{task.description}"),
                BarColumn(),
                TimeRemainingColumn(),
                console=self.console,
                transient=True,
            )

    def __enter__(self) -> Display:
        if self.bar is not None:
            self.bar.start()
        return self

    def __exit__(self, *_: object) -> None:
        if self.bar is not None:
            self.bar.stop()

    def say(self, line: Any) -> None:
        """Print a line (or, on a terminal, a `rich` renderable) that fits the width:
        `rich` wraps at words to the terminal's; plain text wraps at words to 80."""
        if self.console is not None:
            self.console.print(line, highlight=False, markup=False, emoji=False)
        else:
            text = "\n".join(w for part in str(line).split("\n") for w in wrap(part))
            self.stream.write(f"{text}\n")
            self.stream.flush()

    def __call__(self, progress: Progress) -> None:
        if progress.finished is not None:
            self.done += 1
            if not self.quiet:
                self.say(run_line(progress.finished, progress.runs))
        if self.bar is None:
            return
        part = min(1.0, progress.elapsed_s / max(progress.duration_s, 1e-9))
        completed = self.done if progress.finished is not None else self.done + part
        description = f"run {progress.run}/{progress.runs} {_value(progress)}seed {progress.seed}"
        if self.task is None:
            self.task = self.bar.add_task(description, total=progress.runs)
        self.bar.update(self.task, completed=completed, description=description)


def error(message: str) -> None:
    sys.stderr.write(f"rr-actors experiment: {message}\n")
    sys.stderr.flush()


def main(args: argparse.Namespace, stream: TextIO) -> int:
    """Run the experiment the parsed `args` ask for; return the exit code.

    Args:
        args: parsed by a parser that `add_arguments` set up.
        stream: where progress and the summary go (errors go to standard error).

    Returns:
        0 done; 1 a run failed (a simulated seed lost, or `--out` could not be written); 2
        bad input (nothing was started); 130 interrupted (Ctrl-C); 143 stopped (SIGTERM);
        129 hung up (SIGHUP).
    """
    if args.list:
        return _list(stream)
    if args.plan is None or args.out is None:
        error(f"give {'a PLAN and ' if args.plan is None else ''}--out DIR (or --list)")
        return 2
    if args.simulate:
        with _one_ctrl_c():
            return _simulated(args, stream)
    needs = [
        name
        for name in ("seeds", "jobs", "seed_timeout", "shrink")
        if getattr(args, name) is not None
    ]
    if needs:
        error(f"--{needs[0].replace('_', '-')} needs --simulate")
        return 2
    with _one_ctrl_c():
        return _run(args, stream)


@contextlib.contextmanager
def _one_ctrl_c() -> Iterator[None]:
    """The first Ctrl-C stops the experiment; the ones after it are ignored (it is stopping:
    they would cut its cleanup, its plots or its summary short)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def first(_signum: int, _frame: object) -> None:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, first)
    try:
        yield
    finally:
        if signal.getsignal(signal.SIGINT) is first:  # after a Ctrl-C, ignored to the end
            signal.signal(signal.SIGINT, previous)


def _run(args: argparse.Namespace, stream: TextIO) -> int:
    display = Display(stream, quiet=args.quiet)
    interrupted = 0
    try:
        plan = load_plan(plan_file(args.plan))
        if args.observe:
            with needs("observe", "--observe"):
                require_extra()  # before --out is made
        experiment.prepare_out(Path(args.out), force=args.force, what="--out")
        with display:
            results = experiment.run(
                plan,
                out=args.out,
                repeat=args.repeat,
                seed=args.seed,
                duration=args.duration,
                force=args.force,
                observe=args.observe,
                trace=args.trace,
                progress=display,
                on_observe=lambda run, url: display.say(f"run {run}: observer at {url}"),
            )
    except ConfigError as exc:
        error(str(exc))
        return 2
    except ExperimentError as exc:
        error(str(exc))
        return 1
    except ExperimentInterruptedError as exc:
        results = exc.results
        interrupted = 128 + exc.signum  # 130 after Ctrl-C, 143 after SIGTERM, 129 SIGHUP
    _summary(display, results, interrupted=bool(interrupted))
    return interrupted or 0


def _simulated(args: argparse.Namespace, stream: TextIO) -> int:
    """`--simulate`: the plan's seeds on the simulation (`sweep.py`); the exit code."""
    if args.observe or args.trace or args.repeat is not None or args.seed is not None:
        error("--simulate runs --seeds: not --repeat, --seed, --observe or --trace")
        return 2
    try:
        seeds = sweep.parse_seeds(args.seeds or "1")
        plan = load_plan(plan_file(args.plan))
        if args.duration is not None:
            plan = plan.with_changes(duration=args.duration)
        out = Path(args.out)
        sweep.prepare(plan, out, force=args.force)
    except ConfigError as exc:
        error(str(exc))
        return 2
    argv = ["experiment", args.plan, "--simulate", "--seeds", f"{seeds[0]}-{seeds[-1]}"]
    argv += ["--out", args.out, "--force"]  # (the directory is prepared)
    argv += [*(["--duration", str(args.duration)] if args.duration is not None else [])]
    argv += ["--quiet"] if args.quiet else []
    argv += ["--jobs", str(args.jobs)] if args.jobs is not None else []
    argv += ["--seed-timeout", repr(args.seed_timeout)] if args.seed_timeout is not None else []
    argv += ["--shrink", str(args.shrink)] if args.shrink is not None else []
    code = sweep.hash_fixed(argv, stream)
    return code if code is not None else _sweep(plan, seeds, out, args, stream)


def _sweep(plan: Plan, seeds: range, out: Path, args: argparse.Namespace, stream: TextIO) -> int:
    """The seeds run (here: `PYTHONHASHSEED=0`), then the summary, then `--shrink`."""
    jobs = args.jobs if args.jobs is not None else sweep.default_jobs(seeds)
    runs: list[simulate.SimulatedRun] = []
    lost: list[sweep.LostSeed] = []
    try:
        with sweep.stopping_on_signals(), Display(stream, quiet=args.quiet) as display:
            sweep.run_seeds(
                plan, seeds, out, display, jobs=jobs, seed_timeout=args.seed_timeout,
                runs=runs, lost=lost,
            )  # fmt: skip
    except RrError as exc:
        error(str(exc))
        return 1
    except KeyboardInterrupt as exc:  # (the seeds running removed their folders)
        error(f"{sweep.stopped_line(exc)}: the seeds that ran are in {out / sweep.SEEDS_FILE}")
        if runs or lost:
            sweep.summary(display, runs, _shown(out), lost)
        return sweep.stopped_code(exc)
    sweep.summary(display, runs, _shown(out), lost)
    if args.shrink is not None:
        try:
            with sweep.stopping_on_signals():
                sweep.shrink_violations(plan, runs, _shown(out), display, budget=args.shrink)
        except RrError as exc:
            error(str(exc))
            return 1
        except KeyboardInterrupt as exc:
            error(sweep.stopped_line(exc))
            return sweep.stopped_code(exc)
    return 1 if lost else 0  # (a seed lost: a run failed)


LIST_FOOTER = (
    "(shipped in rr_actors_lab/experiments/plans/; run one with rr-actors experiment NAME "
    "--out DIR; the plan format: docs/reference/plan.md, also plan-reference.md there)"
)


def _list(stream: TextIO) -> int:
    """Each shipped plan and what it shows, wrapped at words to 80 columns."""
    for name, path in plans.shipped().items():
        description = load_plan(path).description
        lines = textwrap.wrap(
            f"{name:<12} {description}",
            RUN_LINE_WIDTH,
            subsequent_indent=" " * 13,
            break_long_words=False,
            break_on_hyphens=False,
        )
        stream.write("".join(f"{line}\n" for line in lines))
    stream.write("".join(f"{line}\n" for line in wrap(LIST_FOOTER, indent="")))
    return 0


def plan_file(plan: str) -> Path:
    """The file `plan` names (see `plans.find`), or a `ConfigError` naming the shipped ones."""
    path = plans.find(plan)
    if not path.exists() and path.parent == Path():
        shipped = plans.shipped()
        raise ConfigError(
            f"{plan}: no such file, and no shipped plan of that name"
            + _known_names(plan, shipped, shown=len(shipped)).replace("(known:", "(shipped:")
        )
    return path


def _shown(path: Path) -> Path:
    """`path` relative to the working directory when it is under it (as the user typed
    `--out`), else whole."""
    try:
        return path.resolve().relative_to(Path.cwd().resolve())
    except (ValueError, OSError):
        return path


def _summary(display: Display, results: Results, *, interrupted: bool) -> None:
    if interrupted:
        display.say(
            f"interrupted: {len(results.runs)} run(s) finished and kept; every process "
            "the experiment started was stopped"
        )
    if results.runs and display.console is not None:
        display.say(summary_table(results))
    elif results.runs:
        for line in summary_lines(results):
            display.say(line)
    faults = fault_line(results)
    if faults is not None:
        display.say(faults)
    if results.runs:
        display.say(verdict_line(results))
    if results.out is not None:
        written = [name for name in experiment.OUTPUT_FILES if (results.out / name).exists()]
        display.say(f"written to {_shown(results.out)}/: {', '.join(written)}")
        if "recovery.png" not in written and results.runs:
            display.say(
                "plots not drawn: matplotlib is missing, in an extra: "
                + install_command("experiments")
            )
