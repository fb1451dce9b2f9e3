"""`rr-actors experiment PLAN --simulate --seeds A-B` and `rr-actors replay RUN --seed S`.

```
 experiment PLAN --simulate --seeds 1-500 --out DIR
   PYTHONHASHSEED is not 0? ─► the same command again in a child process with it
                               (a hash then replays in any process), its output passed on
   DIR/plan.toml (the plan's copy)
   simulate.run_seed per seed ─► a progress bar (a terminal with rich) or a line per
                                 violating seed; DIR/seeds.jsonl: a line per seed (its
                                 hash, verdict, counts); DIR/events-seed-S.jsonl: the
                                 history of each seed that did not hold
   ◄── a summary table, the violating seeds; exit 0 (1: a run failed; 2: bad input)

 replay DIR --seed S
   DIR/plan.toml, DIR/seeds.jsonl's line of S ─► simulate.run_seed ─► its hash printed
   and compared with the recorded one; exit 0 same, 1 not (or no such seed recorded)
```
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import os
import re
import shutil
import statistics
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from rr_actors.errors import ConfigError, RrError
from rr_actors.experiments import experiment, simulate
from rr_actors.experiments.plan import Plan
from rr_actors.experiments.reading import parse_plan

if TYPE_CHECKING:
    from rich.table import Table as RichTable

__all__ = [
    "OUTPUT_FILES",
    "SEEDS_FILE",
    "hash_fixed",
    "parse_seeds",
    "prepare",
    "replay_arguments",
    "run_replay",
    "run_seeds",
    "summary",
    "summary_rows",
]

SEEDS_FILE = "seeds.jsonl"
"""A simulated experiment's results: a JSON line per seed."""

OUTPUT_FILES = ("plan.toml", SEEDS_FILE)
"""What a simulated experiment writes into `--out` (and `events-seed-S.jsonl` per seed
whose verdict was not "held")."""

MAX_SEEDS = 10_000_000
"""The most seeds of one sweep."""

HASH_SEED = "0"
"""The `PYTHONHASHSEED` a sweep and a replay run with."""

SUMMARY_HEADERS = (
    "seeds",
    "held",
    "violated",
    "unverifiable",
    "events",
    "faults",
    "calls ok",
    "calls failed",
    "virtual s",
    "seeds/CPU-min",
)


def parse_seeds(text: str) -> range:
    """`"A-B"` (both included) or `"S"` as a range of seeds.

    Raises:
        ConfigError: not that form, B below A, or more than `MAX_SEEDS` seeds.
    """
    found = re.fullmatch(r"\s*(-?\d+)\s*(?:-\s*(-?\d+)\s*)?", text)
    if found is None:
        raise ConfigError(f"--seeds must be A-B or S (whole numbers), got {text!r}")
    low = int(found[1])
    high = int(found[2]) if found[2] is not None else low
    if high < low:
        raise ConfigError(f"--seeds {text}: the last seed is below the first")
    if high - low + 1 > MAX_SEEDS:
        raise ConfigError(f"--seeds {text}: more than {MAX_SEEDS} seeds")
    return range(low, high + 1)


def prepare(plan: Plan, out: Path, *, force: bool) -> None:
    """Check that the simulation runs `plan`, and make `out` ready (`plan.toml` copied).

    Raises:
        ConfigError: what `simulate.check_simulable` refuses (a `PlanError`), or `out`
            is not usable (`experiment.prepare_out`).
    """
    simulate.check_simulable(plan)
    experiment.prepare_out(out, force=force, what="--out")
    for path in [out / SEEDS_FILE, *out.glob("events-seed-*.jsonl")]:
        path.unlink(missing_ok=True)
    if plan.source is not None:
        shutil.copyfile(plan.source, out / "plan.toml")


def hash_fixed(argv: list[str], stream: TextIO) -> int | None:
    """Run `rr-actors ARGV` in a child with `PYTHONHASHSEED=0` unless this process has it;
    its exit code (`None`: this process has it, go on here)."""
    if os.environ.get("PYTHONHASHSEED") == HASH_SEED:
        return None
    env = {**os.environ, "PYTHONHASHSEED": HASH_SEED}
    command = [sys.executable, "-m", "rr_actors", *argv]
    if stream is sys.stdout:
        return subprocess.run(command, env=env, check=False).returncode  # noqa: S603
    done = subprocess.run(  # noqa: S603 - this program, its own arguments
        command, env=env, check=False, stdout=subprocess.PIPE, text=True
    )
    stream.write(done.stdout)
    return done.returncode


def _line(run: simulate.SimulatedRun, plan: Plan) -> dict[str, Any]:
    """A seed's line of `seeds.jsonl`: the run without its history, the plan's duration
    and file (a replay imports the setups from the file's folder, as the sweep did)."""
    fields = dataclasses.asdict(run)
    del fields["history"]
    return {
        **fields,
        "findings": list(run.findings),
        "duration": plan.duration,
        "plan": plan.source,
    }


def summary_rows(runs: list[simulate.SimulatedRun]) -> list[str]:
    """The summary's cells (`SUMMARY_HEADERS`): medians of events, faults, calls, time."""
    verdicts = [r.verdict for r in runs]
    cpu = sum(r.cpu_s for r in runs)

    def median(values: list[float]) -> str:
        return f"{statistics.median(values):g}" if values else "-"

    return [
        str(len(runs)),
        str(verdicts.count("held")),
        str(verdicts.count("violated")),
        str(verdicts.count("unverifiable")),
        median([r.events for r in runs]),
        median([r.faults for r in runs]),
        median([r.calls_ok for r in runs]),
        median([r.calls_failed for r in runs]),
        median([round(r.virtual_s, 2) for r in runs]),
        f"{60 * len(runs) / cpu:.0f}" if cpu > 0 else "-",
    ]


def _table(runs: list[simulate.SimulatedRun]) -> RichTable:
    from rich import box  # noqa: PLC0415 - rich is optional
    from rich.table import Table  # noqa: PLC0415

    table = Table(
        box=box.SIMPLE_HEAD,
        show_edge=False,
        pad_edge=False,
        collapse_padding=True,
        caption="events, faults, calls, virtual s: medians per seed",
        caption_justify="left",
    )
    for header in SUMMARY_HEADERS:
        table.add_column(header, justify="right", no_wrap=True)
    table.add_row(*summary_rows(runs))
    return table


def run_seeds(plan: Plan, seeds: range, out: Path, display: Any) -> list[simulate.SimulatedRun]:
    """Run each seed, a line of `out/seeds.jsonl` and a step of `display` (`cli.Display`)
    each, the history of each that did not hold in `out/events-seed-S.jsonl`.

    Raises:
        RrError: what `simulate.simulate` raises (with the seed in a note).
    """
    runs: list[simulate.SimulatedRun] = []
    bar = display.bar
    task = None if bar is None else bar.add_task("seeds", total=len(seeds))
    with (out / SEEDS_FILE).open("w", encoding="utf-8") as lines:

        def finished(run: simulate.SimulatedRun) -> None:
            runs.append(run)
            lines.write(json.dumps(_line(run, plan)) + "\n")
            lines.flush()
            if run.verdict != "held":
                name = f"events-seed-{run.seed}.jsonl"
                (out / name).write_text(run.history, encoding="utf-8")
                if not display.quiet:
                    display.say(f"seed {run.seed}: {run.verdict} ({name})")
            if bar is not None and task is not None:
                bar.update(task, completed=len(runs), description=f"seed {run.seed}")

        with _warnings_off():
            simulate.simulate(plan, seeds, on_run=finished)
    return runs


@contextlib.contextmanager
def _warnings_off() -> Iterator[None]:
    """rr_actors' warnings off while seeds run: each kill of a sweep is one ("child exited:
    killed by SIGKILL"), thousands a sweep; errors still show."""
    logger = logging.getLogger("rr_actors")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


def summary(display: Any, runs: list[simulate.SimulatedRun], out: Path) -> None:
    """The sweep's summary: a table (rich) or lines, the seeds that did not hold."""
    if display.console is not None:
        display.say(_table(runs))
    else:
        for header, cell in zip(SUMMARY_HEADERS, summary_rows(runs), strict=True):
            display.say(f"{header:>14}  {cell}")
    violated = [r.seed for r in runs if r.verdict == "violated"]
    unverifiable = [r.seed for r in runs if r.verdict == "unverifiable"]
    display.say(
        f"violated: seeds {', '.join(map(str, violated))}" if violated else "violated: none"
    )
    if unverifiable:
        display.say(f"unverifiable: seeds {', '.join(map(str, unverifiable))}")
    if violated or unverifiable:
        seed = (violated or unverifiable)[0]
        display.say(f"replay one: rr-actors replay {out} --seed {seed}")
    kept = len(violated) + len(unverifiable)
    histories = [f"{kept} histories (events-seed-S.jsonl)"] if kept else []
    display.say(f"written to {out}/: {', '.join([*OUTPUT_FILES, *histories])}")


def replay_arguments(parser: argparse.ArgumentParser) -> None:
    """The `replay` subcommand's arguments."""
    parser.add_argument(
        "run_dir", metavar="RUN", help="the --out directory of `rr-actors experiment --simulate`"
    )
    parser.add_argument("--seed", type=int, required=True, help="the seed to run again")
    parser.add_argument(
        "--events", metavar="FILE", help="write the replayed history (events.jsonl) to FILE"
    )


def run_replay(args: argparse.Namespace, stream: TextIO) -> int:
    """`rr-actors replay RUN --seed S`: 0 the same hash as recorded, 1 not, 2 bad input."""

    def error(message: str) -> None:
        sys.stderr.write(f"rr-actors replay: {message}\n")

    run_dir = Path(args.run_dir)
    try:
        recorded = _recorded(run_dir, args.seed)
        text = (run_dir / "plan.toml").read_text(encoding="utf-8")
        source = recorded.get("plan") or str(run_dir / "plan.toml")  # (its setups' folder)
        plan = parse_plan(text, source=source, name=Path(source).stem)
        plan = plan.with_changes(duration=recorded["duration"])
        simulate.check_simulable(plan)
    except (ConfigError, OSError) as exc:
        error(str(exc))
        return 2
    argv = ["replay", args.run_dir, "--seed", str(args.seed)]
    argv += ["--events", args.events] if args.events else []
    code = hash_fixed(argv, stream)
    if code is not None:
        return code
    try:
        with _warnings_off():
            run = simulate.run_seed(plan, args.seed)
    except RrError as exc:
        error(str(exc))
        return 1
    if args.events:
        Path(args.events).write_text(run.history, encoding="utf-8")
    same = run.hash == recorded["hash"]
    stream.write(
        f"seed {run.seed}: {run.verdict}, hash {run.hash}\n"
        f"recorded:        hash {recorded['hash']}: "
        f"{'the same history' if same else 'a different history'}\n"
    )
    for finding in run.findings:
        stream.write(f"{finding}\n")
    return 0 if same else 1


def _recorded(run_dir: Path, seed: int) -> dict[str, Any]:
    """The line of `seed` in `RUN/seeds.jsonl`.

    Raises:
        ConfigError: no such file, or no line of that seed.
    """
    path = run_dir / SEEDS_FILE
    if not path.is_file():
        raise ConfigError(f"{run_dir}: no {SEEDS_FILE} (not an `experiment --simulate` output)")
    with path.open(encoding="utf-8") as lines:
        for text in lines:
            line = json.loads(text)
            if line.get("seed") == seed:
                found: dict[str, Any] = line
                return found
    raise ConfigError(f"{path}: seed {seed} was not run")
