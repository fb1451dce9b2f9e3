"""`rr-actors experiment PLAN.toml --out DIR`: run an experiment from the command line.

    rr-actors experiment examples/experiments/strategies.toml --out results
    rr-actors experiment plan.toml --out results --repeat 5 --seed 42 --force

On a terminal with `rich` installed (`pip install 'rr-actors[experiments]'`) a progress
bar shows the runs; elsewhere one line per finished run. At the end: a summary per
compared value and the files written. Exit codes: 0 done; 1 a run failed; 2 bad input
(the plan, an option, the output directory, the platform), found before anything
started; 130 interrupted (Ctrl-C), with the finished runs kept.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from rr_actors.errors import ConfigError
from rr_actors.experiments import experiment
from rr_actors.experiments.experiment import (
    ExperimentError,
    ExperimentInterruptedError,
    Progress,
)
from rr_actors.experiments.metrics import percentile
from rr_actors.experiments.reading import load_plan
from rr_actors.experiments.results import Results, RunResult, show_value
from rr_actors.observe import require_extra

if TYPE_CHECKING:
    from rich.progress import Progress as RichProgress
    from rich.progress import TaskID

__all__ = ["INTERRUPTED_EXIT", "add_arguments", "main", "summary_lines"]

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
    parser.add_argument("plan", help="the plan file (TOML; see docs/reference/plan.md)")
    parser.add_argument(
        "--out",
        required=True,
        help="output directory: events.jsonl, runs.csv, faults.csv, recovery.png, "
        "timeline.png, plan.toml (must be empty or new, unless --force)",
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
        "--force",
        action="store_true",
        help="replace the experiment files in a non-empty --out",
    )
    parser.add_argument(
        "--quiet", action="store_true", help="no progress: print only the summary and the files"
    )


def _value(progress: Progress | RunResult) -> str:
    if progress.value is None:
        return ""
    return f"{progress.setting}={show_value(progress.value)} "


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value * 1e3:.0f} ms"


def run_line(result: RunResult, runs: int) -> str:
    """One line about a finished run."""
    return (
        f"run {result.run}/{runs} {_value(result)}seed {result.seed}: "
        f"{result.calls_ok} calls ok, {result.calls_failed} failed, "
        f"{result.restarts} restarts, recovery median {_ms(result.recovery_median_s)}"
        + (", the supervisor gave up" if result.gave_up else "")
    )


def summary_lines(results: Results) -> list[str]:
    """The summary per compared value: recovery, calls, unavailability, leftovers."""
    label = results.plan.setting_label() or "strategy"
    lines = [
        f"{label:<20} {'runs':>4} {'faults':>6} {'recovery p50':>12} {'p90':>8} "
        f"{'calls failed':>12} {'down s':>7} {'left':>5}"
    ]
    for value, runs in results.by_value():
        if not runs:
            continue
        shown = results.plan.tree.strategy if value is None else show_value(value)
        recoveries = [r for run in runs for r in run.recoveries()]
        faults = sum(1 for run in runs for f in run.faults if not f.skipped)
        failed = statistics.mean(run.calls_failed for run in runs)
        down = statistics.mean(sum(run.unavailable_s.values()) for run in runs)
        left = sum(max(0, run.catalog_entries_left) + run.leaked_processes for run in runs)
        lines.append(
            f"{shown[:20]:<20} {len(runs):>4} {faults:>6} "
            f"{_ms(percentile(recoveries, 50)):>12} {_ms(percentile(recoveries, 90)):>8} "
            f"{failed:>12.1f} {down:>7.2f} {left:>5}"
        )
    lines.append(
        "recovery: per fault, from the injection until the system served again; "
        "calls failed and down s (all managers): mean per run; left: catalog entries and "
        "processes left, all runs"
    )
    return lines


class _Display:
    """Progress on a terminal (rich) or as plain lines."""

    def __init__(self, stream: TextIO, *, quiet: bool) -> None:
        self.stream = stream
        self.quiet = quiet
        self.bar: RichProgress | None = None
        self.task: TaskID | None = None
        self.done = 0.0
        if not quiet and stream.isatty():
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
            self.bar = RichProgress(
                TextColumn("{task.description}"),
                BarColumn(),
                TimeRemainingColumn(),
                console=Console(file=stream),
                transient=True,
            )

    def __enter__(self) -> _Display:
        if self.bar is not None:
            self.bar.start()
        return self

    def __exit__(self, *_: object) -> None:
        if self.bar is not None:
            self.bar.stop()

    def say(self, line: str) -> None:
        if self.bar is not None:
            self.bar.console.print(line, highlight=False, markup=False, soft_wrap=True)
        else:
            self.stream.write(line + "\n")
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


def _error(message: str) -> None:
    sys.stderr.write(f"rr-actors experiment: {message}\n")
    sys.stderr.flush()


def main(args: argparse.Namespace, stream: TextIO) -> int:
    """Run the experiment the parsed `args` ask for; return the exit code.

    Args:
        args: parsed by a parser that `add_arguments` set up.
        stream: where progress and the summary go (errors go to standard error).

    Returns:
        0 done; 1 a run failed; 2 bad input (nothing was started); 130 interrupted.
    """
    display = _Display(stream, quiet=args.quiet)
    interrupted = False
    try:
        plan = load_plan(args.plan)
        if args.observe:
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
                progress=display,
                on_observe=lambda run, url: display.say(f"run {run}: observer at {url}"),
            )
    except ConfigError as exc:
        _error(str(exc))
        return 2
    except ExperimentError as exc:
        _error(str(exc))
        return 1
    except ExperimentInterruptedError as exc:
        results = exc.results
        interrupted = True
    _summary(stream, results, interrupted=interrupted)
    return INTERRUPTED_EXIT if interrupted else 0


def _summary(stream: TextIO, results: Results, *, interrupted: bool) -> None:
    out: list[str] = []
    if interrupted:
        out.append(
            f"interrupted: {len(results.runs)} run(s) finished and kept; every process "
            "the experiment started was stopped"
        )
    if results.runs:
        out.extend(summary_lines(results))
    if results.out is not None:
        written = [name for name in experiment.OUTPUT_FILES if (results.out / name).exists()]
        out.append(f"written to {results.out}/: {', '.join(written)}")
        if "recovery.png" not in written and results.runs:
            out.append(
                "plots not drawn: matplotlib is not installed "
                "(pip install 'rr-actors[experiments]')"
            )
    stream.write("\n".join(out) + "\n")
    stream.flush()
