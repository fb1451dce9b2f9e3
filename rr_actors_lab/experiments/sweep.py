"""`rr-actors experiment PLAN --simulate --seeds A-B` and `rr-actors replay RUN --seed S`.

```
 experiment PLAN --simulate --seeds 1-500 --out DIR
   PYTHONHASHSEED is not 0? ─► the same command in a child process with it (`hash_fixed`)
   DIR/plan.toml (the plan's copy)
   simulate.run_seed per seed ─► a progress bar or lines; DIR/seeds.jsonl: a line per
   (here, or in --jobs workers:  seed; DIR/events-seed-S.jsonl: each seed that did not
   `_Workers`)                   hold; DIR/log.txt: the system's error lines, by seed
   ◄── a summary, the violating seeds, the lost ones (their worker died or hung); exit 0
       (1: a run failed, or a seed was lost; 2: bad input; 128 + the signal that stopped it)

 replay DIR --seed S
   DIR/plan.toml, DIR/seeds.jsonl's line of S ─► simulate.run_seed ─► its hash printed
   and compared with the recorded one; exit 0 same, 1 not; 2 bad input
```
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import multiprocessing
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent import futures
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import connection, resource_tracker
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from rr_actors.errors import ConfigError, RrError
from rr_actors_lab._tools.files import open_regular, read_text
from rr_actors_lab.experiments import experiment, shrink, simulate, story
from rr_actors_lab.experiments.plan import Plan
from rr_actors_lab.experiments.reading import PLAN_LIMIT, parse_plan

if TYPE_CHECKING:
    from rich.table import Table as RichTable

__all__ = [
    "LOG_FILE",
    "OUTPUT_FILES",
    "SEEDS_FILE",
    "SEED_TIMEOUT",
    "STOP_SIGNALS",
    "LostSeed",
    "hash_fixed",
    "lost_line",
    "parse_seeds",
    "prepare",
    "read_plan_text",
    "recorded_plan",
    "replay_arguments",
    "run_replay",
    "run_seeds",
    "run_shrink",
    "seed_bound",
    "seed_line",
    "shrink_arguments",
    "shrink_seed",
    "shrink_violations",
    "stopped_code",
    "stopped_line",
    "stopping_on_signals",
    "summary",
    "summary_rows",
]

PROGRESS_SECONDS = 5.0
"""Without a progress bar (stdout a pipe or a file), a line `seeds: 37/500 run, ...` after
the first seed, then after the first seed done at least this many seconds after the last
line: a long sweep through `| cat` or `| tee` shows that it is running."""

SEEDS_FILE = "seeds.jsonl"
"""A simulated experiment's results: a JSON line per seed."""

OUTPUT_FILES = ("plan.toml", SEEDS_FILE)
"""What a simulated experiment writes into `--out` (and `events-seed-S.jsonl` per seed
whose verdict was not "held", and `LOG_FILE` if the simulated system logged errors)."""

LOG_FILE = "log.txt"
"""The simulated system's log lines of ERROR and up, each with its seed (`_SystemLog`)."""

MAX_SEEDS = 10_000_000
"""The most seeds of one sweep."""

HASH_SEED = "0"
"""The `PYTHONHASHSEED` a sweep and a replay run with."""

LINE_LIMIT = 64 * 1024 * 1024
"""The most bytes of one line of a run directory's `seeds.jsonl` (a seed's line is its
counts and findings: a few kilobytes, a megabyte for thousands of findings)."""

SUMMARY_HEADERS = (
    "seeds",
    "held",
    "violated",
    "unverifiable",
    "crashed",
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
    its exit code (`None`: this process has it, go on here).

    A Ctrl-C, SIGTERM or SIGHUP meanwhile is passed on to the child, which stops as it would
    alone; this process waits for it (a killed child would leave its folder).
    """
    if os.environ.get("PYTHONHASHSEED") == HASH_SEED:
        return None
    env = {**os.environ, "PYTHONHASHSEED": HASH_SEED}
    command = [sys.executable, "-m", "rr_actors_lab", *argv]
    pipe = None if stream is sys.stdout else subprocess.PIPE
    child = subprocess.Popen(command, env=env, stdout=pipe, text=True)  # noqa: S603 - ours
    with _passed_on(child):
        out, _ = child.communicate()
    if out is not None:
        stream.write(out)
    return child.returncode


def _passed_on(child: subprocess.Popen[str]) -> contextlib.AbstractContextManager[None]:
    """Each of `STOP_SIGNALS` this process gets passed on to `child` (main thread only)."""

    def pass_on(signum: int, _frame: object) -> None:
        with contextlib.suppress(ProcessLookupError):  # (it ended meanwhile)
            child.send_signal(signum)

    return experiment.handling_signals(STOP_SIGNALS, pass_on)


STOP_SIGNALS = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)
"""The signals that stop a sweep, a replay or a shrink (as a Ctrl-C stops an experiment)."""


class _Stopped(KeyboardInterrupt):
    """One of `STOP_SIGNALS`, raised in the main thread (`stopping_on_signals`)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def stopping_on_signals() -> contextlib.AbstractContextManager[None]:
    """The first of `STOP_SIGNALS` raises `KeyboardInterrupt` in the main thread, later ones are
    ignored until the block ends (`stopped_code` gives the exit code); off the main thread,
    nothing."""

    def first(signum: int, _frame: object) -> None:
        for number in STOP_SIGNALS:
            signal.signal(number, signal.SIG_IGN)
        raise _Stopped(signum)

    return experiment.handling_signals(STOP_SIGNALS, first)


def stopped_code(exc: KeyboardInterrupt) -> int:
    """The exit code of a command stopped by `exc`: 128 + its signal (130 after a
    Ctrl-C, 143 after a SIGTERM, 129 after a SIGHUP)."""
    return 128 + int(getattr(exc, "signum", signal.SIGINT))


def stopped_line(exc: KeyboardInterrupt) -> str:
    """What a stopped command says: by which signal."""
    return f"stopped by {signal.Signals(stopped_code(exc) - 128).name}"


def seed_line(run: simulate.SimulatedRun, plan: Plan) -> dict[str, Any]:
    """A seed's line of `seeds.jsonl`: the run without its history, the plan's duration
    and file (a replay imports the setups from the file's folder, as the sweep did)."""
    fields = dataclasses.asdict(run)
    del fields["history"]
    return {
        **fields,
        "findings": list(run.findings),
        "duration": plan.duration,
        "plan": None if plan.source is None else os.path.abspath(plan.source),
    }


def lost_line(lost: LostSeed, plan: Plan) -> dict[str, Any]:
    """A lost seed's line of `seeds.jsonl`: its seed, `"verdict": "lost"`, no hash (`None`),
    how its worker ended (`"worker"`), the plan's duration and file (as `seed_line`)."""
    return {
        "seed": lost.seed,
        "verdict": "lost",
        "hash": None,
        "worker": lost.worker,
        "duration": plan.duration,
        "plan": None if plan.source is None else os.path.abspath(plan.source),
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
        str(verdicts.count("crashed")),
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


def run_seeds(
    plan: Plan,
    seeds: range,
    out: Path,
    display: Any,
    *,
    jobs: int = 1,
    seed_timeout: float | None = None,
    runs: list[simulate.SimulatedRun] | None = None,
    lost: list[LostSeed] | None = None,
) -> list[simulate.SimulatedRun]:
    """Run each seed: a line of `out/seeds.jsonl`, a step of `display`, the history of each that
    did not hold in `out/events-seed-S.jsonl`, the system's error lines in `out/log.txt`.

    With `jobs` above 1 (or a `seed_timeout`) the seeds run in that many worker processes
    (`_Workers`); what is written is the same, in seed order. A seed whose worker died or
    hung is lost: its line says how (`lost_line`), the sweep goes on in new workers.

    Args:
        plan: the plan (`simulate.check_simulable` must accept it).
        seeds: the seeds, in order.
        out: the run directory (`prepare`d).
        display: the progress (`cli.Display`).
        jobs: processes to run seeds in (1: this one, unless `seed_timeout` is given).
        seed_timeout: the wall seconds a worker may run one seed before it is killed as
            hung (`None`: `seed_bound`'s default).
        runs: the list to append each finished run to (a stop leaves the seeds that ran);
            a new one if `None`.
        lost: the list to append each lost seed to; a new one if `None`.

    Returns:
        `runs`; those that held without their history (`""`).

    Raises:
        RrError: what `simulate.simulate` raises (with the seed in a note); the workers died
            `BREAKS_IN_A_ROW` times before they finished a seed.
        KeyboardInterrupt: one of `STOP_SIGNALS`: the seeds running are cancelled and
            their folders removed, in every worker too.
    """
    runs = [] if runs is None else runs
    lost = [] if lost is None else lost
    bar = display.bar
    task = None if bar is None else bar.add_task("seeds", total=len(seeds))
    simulate.check_simulable(plan)
    started = said = time.monotonic()
    with (
        (out / SEEDS_FILE).open("w", encoding="utf-8") as lines,
        _SystemLog(out / LOG_FILE) as log,
    ):
        for outcome in _seed_runs(plan, seeds, jobs, seed_timeout):
            if isinstance(outcome, LostSeed):
                lost.append(outcome)
                lines.write(json.dumps(lost_line(outcome, plan)) + "\n")
                if not display.quiet:
                    display.say(f"seed {outcome.seed}: lost, worker {outcome.worker}")
                seed = outcome.seed
            else:
                run, errors = outcome
                log.write(run.seed, errors)
                runs.append(run)
                lines.write(json.dumps(seed_line(run, plan)) + "\n")
                if run.verdict != "held":
                    name = f"events-seed-{run.seed}.jsonl"
                    (out / name).write_text(run.history, encoding="utf-8")
                    if not display.quiet:
                        display.say(f"seed {run.seed}: {run.verdict} ({name})")
                seed = run.seed
            lines.flush()
            done = len(runs) + len(lost)
            if bar is not None and task is not None:
                bar.update(task, completed=done, description=f"seed {seed}")
            now = time.monotonic()
            if bar is None and not display.quiet and (done == 1 or now - said >= PROGRESS_SECONDS):
                said = now
                failed = sum(r.verdict != "held" for r in runs)
                display.say(
                    f"seeds: {done}/{len(seeds)} run, {failed} did not hold"
                    f"{f', {len(lost)} lost' if lost else ''} ({now - started:.0f} s)"
                )
    return runs


def default_jobs(seeds: range) -> int:
    """`--jobs`' default: the cores this process may run on, at most one per seed."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # (not Linux)
        cores = os.cpu_count() or 1
    return max(1, min(cores, len(seeds)))


def _seed_runs(
    plan: Plan, seeds: range, jobs: int, seed_timeout: float | None
) -> Iterator[_Result | LostSeed]:
    """Each seed's run and the error lines its system logged, or that it was lost, in seed
    order (in this process with one job and no `seed_timeout`: a timeout needs a worker).

    Raises:
        RrError: what a seed's run raised (at its turn), or `_Workers.run`'s.
    """
    if seed_timeout is None and (jobs <= 1 or len(seeds) <= 1):
        for seed in seeds:
            yield _run_one(plan, seed)
        return
    with _Workers(min(jobs, len(seeds)), seed_timeout=seed_timeout) as workers:
        for outcome in workers.run(plan, seeds):
            if isinstance(outcome, BaseException):
                raise outcome
            yield outcome


def _run_one(plan: Plan, seed: int) -> tuple[simulate.SimulatedRun, list[str]]:
    """Run one seed (in this process, or a worker's): its run (without its history if it
    held) and the lines of ERROR and up that rr_actors logged meanwhile (warnings off:
    each kill is one, thousands a sweep)."""
    global _SEED_RUNNING  # (a worker's one flag: `_worker_stop`)
    caught = _Caught()
    logger = logging.getLogger("rr_actors")
    saved = (logger.level, logger.propagate)
    logger.setLevel(logging.ERROR)
    logger.propagate = False
    logger.addHandler(caught)
    _SEED_RUNNING = True
    try:
        run = simulate.run_seed(plan, seed)
    finally:
        _SEED_RUNNING = False
        logger.removeHandler(caught)
        logger.setLevel(saved[0])
        logger.propagate = saved[1]
    return (run if run.verdict != "held" else dataclasses.replace(run, history="")), caught.lines


class _Caught(logging.Handler):
    """The lines of ERROR and up of one seed's run (`_run_one`)."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(self.format(record))


@dataclasses.dataclass(frozen=True)
class LostSeed:
    """A seed without a result: the worker process running it died or hung (`--jobs`).

    Attributes:
        seed: the seed.
        worker: how its worker ended, in words: `"killed by SIGKILL"`, `"exited with code
            3"`, `"hung: no answer in 300 s, killed"`.
    """

    seed: int
    worker: str


SEED_TIMEOUT = 300.0
"""`--seed-timeout`'s default floor: the wall seconds a worker may run one seed before it
is killed as hung (`seed_bound`)."""

SLOWEST_TIMES = 10
"""`--seed-timeout`'s default is also at least this many times the slowest seed the sweep
finished so far (a plan whose seeds take minutes)."""

STOP_SECONDS = 60.0
"""How long the workers of a pool that ends, is stopped or broke get after their SIGTERM
(to cancel their seeds and remove their folders) before they are killed (a stopped one)."""

BREAKS_IN_A_ROW = 3
"""A sweep whose pool broke this many times with no seed finished or lost in between gives
up (an `RrError`): its workers die before they run a seed, and a new pool's would too."""

AHEAD = 4
"""Seeds submitted per worker ahead of the one written next (a slow seed holds the ones
after it back, in memory, until its turn)."""

POLL_SECONDS = 1.0
"""How often the sweep reads which worker runs which seed while it waits for results (a
seed's bound is counted from then: at most this much late)."""


def seed_bound(seed_timeout: float | None, slowest: float) -> float:
    """The wall seconds a worker may run one seed: `seed_timeout` if given, otherwise
    `SEED_TIMEOUT` or `SLOWEST_TIMES` times `slowest` (the slowest seed finished so far, in
    seconds), whichever is longer."""
    if seed_timeout is not None:
        return seed_timeout
    return max(SEED_TIMEOUT, SLOWEST_TIMES * slowest)


_Result = tuple[simulate.SimulatedRun, list[str]]
"""A seed's run and the error lines its system logged (`_run_one`)."""

_Outcome = _Result | LostSeed | BaseException
"""What became of a seed a worker ran: its result, lost, or what it raised."""


class _Workers:
    """`jobs` spawned worker processes running seeds (`--jobs`): a process pool
    (`concurrent.futures.ProcessPoolExecutor`), replaced by a new one when a worker dies.

    ```
     run(plan, seeds): a future per seed, AHEAD * jobs ahead at most ─► _Pool
        worker: (its pid, the seed) on the pool's report pipe, then _run_one ─► the future
     ◄── each seed's outcome in seed order: its result, a LostSeed, or what it raised
        a seed running past `seed_bound` ─► its worker killed (hung); no word from a pool
            with seeds in flight and none running for as long ─► its workers killed
        BrokenProcessPool ─► every worker ended (_Pool.end): the seed that a worker which
            died reported and did not finish is lost (how the worker ended); the other
            seeds in flight run again in a new pool
    ```

    Spawned, not forked: a fork would copy this process's threads' locks and the simulation's
    patches. A worker ignores SIGINT (this process decides) and takes SIGTERM as a stop; it
    starts with `STOP_SIGNALS` blocked until its handlers are set, so the resource tracker
    (whose start unblocks them, CPython 3.11-3.13) is started before any worker.
    """

    def __init__(self, jobs: int, *, seed_timeout: float | None = None) -> None:
        self.jobs = jobs
        self.seed_timeout = seed_timeout
        self.pool: _Pool | None = None
        self.slowest = 0.0
        self.finished = 0  # (seeds finished or lost: a break after none counts to the limit)

    def __enter__(self) -> _Workers:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.pool is not None:  # (stopped, or a seed failed: the seeds running cancelled)
            self.pool.end()
            self.pool = None

    def run(self, plan: Plan, seeds: range) -> Iterator[_Outcome]:
        """Each seed's outcome, in seed order, as the workers finish them.

        Raises:
            RrError: the pool broke `BREAKS_IN_A_ROW` times with no seed finished or lost.
        """
        fresh = iter(seeds)  # (not submitted yet)
        again: list[int] = []  # (their pool broke: they run again, before the fresh ones)
        kept: dict[int, _Outcome] = {}  # (finished, until their turn)
        flights: dict[Future[_Result], int] = {}
        breaks = 0
        for seed in seeds:
            while seed not in kept:
                if self.pool is None:
                    self.pool = _Pool(self.jobs)
                while not flights or len(flights) + len(kept) < AHEAD * self.jobs:
                    following = again.pop(0) if again else next(fresh, None)
                    if following is None:
                        break
                    flights[self.pool.submit(_run_in_worker, plan, following)] = following
                finished = self.finished
                failed = self._wait(self.pool, flights, kept)
                if failed is None:
                    continue
                again = sorted([*again, *self._broke(self.pool, failed, kept)])
                breaks = 0 if self.finished > finished else breaks + 1
                if breaks >= BREAKS_IN_A_ROW:
                    raise RrError(
                        f"--jobs: the pool of worker processes broke {breaks} times in a row "
                        "with no seed finished (its workers die before they run one)"
                    )
            yield kept.pop(seed)

    def _wait(
        self, pool: _Pool, flights: dict[Future[_Result], int], kept: dict[int, _Outcome]
    ) -> list[int] | None:
        """Wait for a result (`POLL_SECONDS` at most), keep what finished, kill what hung;
        the seeds that were in flight if the pool broke (`None`: it did not)."""
        done, _ = futures.wait(flights, POLL_SECONDS, futures.FIRST_COMPLETED)
        now = time.monotonic()
        pool.read_reports(now)
        broke = any(map(_broken, done))
        if broke:
            futures.wait(flights, STOP_SECONDS)  # (a broken pool fails them all at once)
            done = set(flights)
        failed = []
        for future in done:
            seed = flights.pop(future)
            if not future.done() or _broken(future):
                failed.append(seed)
                continue
            kept[seed] = future.exception() or future.result()
            self.finished += 1
            pool.heard = now
            self.slowest = max(self.slowest, now - pool.started.get(seed, now))
        if broke:
            return failed
        pool.kill_hung(set(flights.values()), seed_bound(self.seed_timeout, self.slowest), now)
        return None

    def _broke(self, pool: _Pool, failed: list[int], kept: dict[int, _Outcome]) -> list[int]:
        """The pool broke: it ends; each of the `failed` seeds that a worker which died
        reported is lost; the others, to run again."""
        died = pool.end()
        self.pool = None
        lost = _lost(pool.running, died, failed)
        for seed in lost:
            kept[seed.seed] = seed
            self.finished += 1
        return [seed for seed in failed if seed not in kept]


def _broken(future: Future[_Result]) -> bool:
    """Whether `future` failed because its pool broke (a worker died, or was killed)."""
    return future.done() and isinstance(future.exception(), BrokenProcessPool)


class _Pool:
    """One `ProcessPoolExecutor` of spawned workers, and what the sweep knows of it: each
    worker's process, the seed each last said it runs and since when, whom it killed.

    Its workers make their seeds' folders in one folder of the pool's own (their `TMPDIR`),
    removed when the pool ended: a worker killed in a seed leaves nothing behind.
    """

    def __init__(self, jobs: int) -> None:
        context = multiprocessing.get_context("spawn")
        resource_tracker.ensure_running()
        self.folder = tempfile.mkdtemp(prefix="rr-sim-workers-", dir=simulate.scratch_parent())
        # (a pipe, not a queue: a report is one write of a few bytes, atomic, with no lock
        # that a worker killed while it writes would keep)
        self.reports, self.writer = context.Pipe(duplex=False)
        self.executor = ProcessPoolExecutor(
            jobs,
            mp_context=context,
            initializer=_worker_started,
            initargs=(self.writer, self.folder),
        )
        self.processes: dict[int, BaseProcess] = {}
        self.running: dict[int, int] = {}  # (pid -> the seed it last said it runs)
        self.started: dict[int, float] = {}  # (seed -> when that was read, monotonic)
        self.heard = time.monotonic()  # (a report or a result came)
        self.killed: dict[int, str] = {}  # (pid -> why this process killed it)

    def submit(self, fn: Callable[..., _Result], *args: object) -> Future[_Result]:
        """`fn(*args)` in a worker (one started now if fewer than `jobs` run); a future
        failed with `BrokenProcessPool` if the pool broke before."""
        try:
            with _stop_signals_blocked():  # (a worker started here begins with them blocked)
                future = self.executor.submit(fn, *args)
        except BrokenProcessPool as exc:
            future = Future()
            future.set_exception(exc)
        # CPython's ProcessPoolExecutor keeps its workers in `_processes` (pid -> Process,
        # 3.8 to 3.14; the one private name used here): how a worker ended is its exit code.
        # Without it (a later CPython) no worker is known: a broken pool's seeds run again in
        # a new one, `BREAKS_IN_A_ROW` breaks end the sweep; a hung worker is not killed.
        self.processes.update(getattr(self.executor, "_processes", None) or {})
        return future

    def read_reports(self, now: float) -> None:
        """Read which worker runs which seed, since `now` (the reports that came)."""
        while self.reports.poll():
            pid, seed = self.reports.recv()
            self.running[pid] = seed
            self.started[seed] = self.heard = now

    def kill_hung(self, flying: set[int], bound: float, now: float) -> None:
        """Kill each worker that has run one of the `flying` seeds for more than `bound`
        seconds; and every worker if none runs one and none said a word for as long, and
        `SEED_TIMEOUT` at least (one stopped while idle holds the pool's queue; a pool's
        start under load is not a seed's time)."""
        running = {pid: seed for pid, seed in self.running.items() if seed in flying}
        for pid, seed in running.items():
            if now - self.started[seed] > bound and pid not in self.killed:
                self.killed[pid] = f"hung: no answer in {bound:g} s, killed"
                self.processes[pid].kill()
        if flying and not running and now - self.heard > max(bound, SEED_TIMEOUT):
            for pid, process in self.processes.items():
                self.killed.setdefault(pid, "")  # (stuck, no seed of its own: not lost)
                process.kill()

    def end(self) -> dict[int, str]:
        """End the pool: each worker told to stop (SIGTERM: the seed it runs is cancelled)
        and given `STOP_SECONDS`, then killed; the pool's thread joined, its folder removed.

        Returns:
            How each worker that died (not one the pool or this process ended) ended, by pid.
        """
        # (an idle worker exits at once too: the executor's own shutdown would wait forever
        # for one stopped by a SIGSTOP)
        for process in self.processes.values():
            process.terminate()
        waiting = {process.sentinel: pid for pid, process in self.processes.items()}
        deadline = time.monotonic() + STOP_SECONDS
        while waiting and (left := deadline - time.monotonic()) > 0:
            ended = connection.wait(list(waiting), left)
            waiting = {sentinel: pid for sentinel, pid in waiting.items() if sentinel not in ended}
        for pid in waiting.values():
            self.killed.setdefault(pid, "")
            self.processes[pid].kill()
        self.executor.shutdown(wait=True, cancel_futures=True)
        self.reports.close()
        self.writer.close()
        shutil.rmtree(self.folder, ignore_errors=True)
        exits = {pid: process.exitcode for pid, process in self.processes.items()}
        return _died(exits, self.killed)


def _died(exits: dict[int, int | None], killed: dict[int, str]) -> dict[int, str]:
    """Of a pool's workers (`exits`: pid -> exit code), how each that died ended: `killed`'s
    reason (a hung one), or its exit in words; not one the pool ended (SIGTERM: `_Pool.end`,
    and CPython's executor once a worker died, 3.8 to 3.14), nor one this process killed
    without a reason (stuck, or left after `STOP_SECONDS`)."""
    stopped = {-signal.SIGTERM, 128 + signal.SIGTERM}
    died: dict[int, str] = {}
    for pid, code in exits.items():
        if killed.get(pid):
            died[pid] = killed[pid]
        elif pid not in killed and code is not None and code not in stopped:
            died[pid] = _exit_words(code)
    return died


def _exit_words(code: int) -> str:
    """A process's exit code in words: `"killed by SIGKILL"`, `"exited with code 3"`."""
    if code < 0:
        with contextlib.suppress(ValueError):
            return f"killed by {signal.Signals(-code).name}"
        return f"killed by signal {-code}"
    return f"exited with code {code}"


def _lost(running: dict[int, int], died: dict[int, str], failed: list[int]) -> list[LostSeed]:
    """The seeds lost when a pool broke: each of the `failed` ones (in flight) that a worker
    which `died` said it runs (`running`: pid -> seed). A worker that died before it said so
    loses nothing: its seed runs again."""
    return sorted(
        (
            LostSeed(seed, died[pid])
            for pid, seed in running.items()
            if pid in died and seed in failed
        ),
        key=lambda lost: lost.seed,
    )


def _run_in_worker(plan: Plan, seed: int) -> _Result:
    """`_run_one` in a worker, said to the sweep first; a stop cancels the seed (its folder
    removed), then the worker exits quietly (a traceback of each worker would bury the
    summary)."""
    assert _REPORTS is not None  # (`_worker_started` set it)
    _REPORTS.send((os.getpid(), seed))
    try:
        return _run_one(plan, seed)
    except KeyboardInterrupt as exc:
        os._exit(stopped_code(exc))


_SEED_RUNNING = False
"""Whether a seed runs in this process now (a worker's stop cancels it; an idle worker
just exits)."""

_REPORTS: Connection | None = None
"""A worker's end of its pool's report pipe (`_worker_started`)."""


@contextlib.contextmanager
def _stop_signals_blocked() -> Iterator[None]:
    """`STOP_SIGNALS` blocked in this thread for the block (held pending, then delivered
    as it ends); threads and processes started inside it begin with them blocked. Where
    the OS has no signal masks (Windows): nothing changes."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _worker_started(reports: Connection, folder: str) -> None:
    """A worker's start: its report pipe kept, its seeds' folders in the pool's `folder`;
    SIGINT ignored, the other `STOP_SIGNALS` stop it; then they are unblocked (`_Pool`:
    one that came while the worker started is taken now)."""
    global _REPORTS  # (a worker's one pipe)
    _REPORTS = reports
    os.environ["TMPDIR"] = folder
    tempfile.tempdir = None  # (read again from TMPDIR)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for number in STOP_SIGNALS:
        if number != signal.SIGINT:
            signal.signal(number, _worker_stop)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)


def _worker_stop(signum: int, _frame: object) -> None:
    """A worker told to stop: the seed running is cancelled (`simulate.run_seed` removes
    its folder), then the worker exits; an idle one exits at once."""
    for number in STOP_SIGNALS:
        signal.signal(number, signal.SIG_IGN)
    if _SEED_RUNNING:
        raise _Stopped(signum)
    os._exit(128 + signum)


@contextlib.contextmanager
def _warnings_off() -> Iterator[None]:
    """rr_actors' warnings off while a seed runs (a replay, a shrink): each kill is one
    ("child exited: killed by SIGKILL"); errors still show."""
    logger = logging.getLogger("rr_actors")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


class _SystemLog:
    """The simulated system's ERROR lines, each with its seed, in `path` (made at the first
    line)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.lines = 0
        self._file: TextIO | None = None

    def __enter__(self) -> _SystemLog:
        return self

    def __exit__(self, *_: object) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def write(self, seed: int, lines: list[str]) -> None:
        """Seed `seed`'s lines."""
        if not lines:
            return
        if self._file is None:
            self._file = self.path.open("a", encoding="utf-8")
        self._file.write("".join(f"seed {seed}: {line}\n" for line in lines))
        self._file.flush()
        self.lines += len(lines)


def summary(
    display: Any, runs: list[simulate.SimulatedRun], out: Path, lost: Sequence[LostSeed] = ()
) -> None:
    """The sweep's summary: a table (rich) or lines, the seeds that did not hold, a line per
    lost seed (how its worker ended)."""
    if display.console is not None:
        display.say(_table(runs))
    else:
        for header, cell in zip(SUMMARY_HEADERS, summary_rows(runs), strict=True):
            display.say(f"{header:>14}  {cell}")
    violated = [r.seed for r in runs if r.verdict == "violated"]
    unverifiable = [r.seed for r in runs if r.verdict == "unverifiable"]
    crashed = [r.seed for r in runs if r.verdict == "crashed"]
    display.say(
        f"violated: seeds {', '.join(map(str, violated))}" if violated else "violated: none"
    )
    if crashed:
        display.say(f"crashed: seeds {', '.join(map(str, crashed))}")
    if unverifiable:
        display.say(f"unverifiable: seeds {', '.join(map(str, unverifiable))}")
    for each in lost:
        display.say(f"lost: seed {each.seed}, worker {each.worker}")
    if violated or crashed or unverifiable:
        seed = (violated or crashed or unverifiable)[0]
        display.say(f"replay one: rr-actors replay {out} --seed {seed}")
    kept = len(violated) + len(crashed) + len(unverifiable)
    histories = [f"{kept} histories (events-seed-S.jsonl)"] if kept else []
    logged = []
    if (out / LOG_FILE).exists():
        count = len((out / LOG_FILE).read_text(encoding="utf-8").splitlines())
        logged = [f"{LOG_FILE} (the simulated system's {count} log lines of ERROR, by seed)"]
    display.say(f"written to {out}/: {', '.join([*OUTPUT_FILES, *histories, *logged])}")


def replay_arguments(parser: argparse.ArgumentParser) -> None:
    """The `replay` subcommand's arguments."""
    parser.add_argument(
        "run_dir", metavar="RUN", help="the --out directory of `rr-actors experiment --simulate`"
    )
    parser.add_argument(
        "--seed",
        type=int,
        help="the seed to run again (default: the only one RUN recorded, as in a shrunk run)",
    )
    parser.add_argument(
        "--events", metavar="FILE", help="write the replayed history (events.jsonl) to FILE"
    )
    parser.add_argument(
        "--story",
        action="store_true",
        help="tell the run step by step: each event's virtual time, process and what "
        "happened, in words; the checker's violations marked",
    )


def run_replay(args: argparse.Namespace, stream: TextIO) -> int:
    """`rr-actors replay RUN --seed S [--story]`: 0 the same hash as recorded, 1 not, 2 bad
    input."""
    try:
        if args.seed is None:
            args.seed = _only_seed(Path(args.run_dir))
        plan, recorded = recorded_plan(Path(args.run_dir), args.seed)
    except ConfigError as exc:
        _error("replay", str(exc))
        return 2
    argv = ["replay", args.run_dir, "--seed", str(args.seed)]
    argv += ["--events", args.events] if args.events else []
    argv += ["--story"] if args.story else []
    code = hash_fixed(argv, stream)
    if code is not None:
        return code
    try:
        with stopping_on_signals(), _warnings_off():
            run = simulate.run_seed(plan, args.seed)
    except RrError as exc:
        _error("replay", str(exc))
        return 1
    except KeyboardInterrupt as exc:
        _error("replay", stopped_line(exc))
        return stopped_code(exc)
    if args.events:
        Path(args.events).write_text(run.history, encoding="utf-8")
    if args.story:
        story.tell(run.history, stream)
    same = run.hash == recorded["hash"]
    stream.write(
        f"seed {run.seed}: {run.verdict}, hash {run.hash}\n"
        f"recorded:        hash {recorded['hash']}: "
        f"{'the same history' if same else 'a different history'}\n"
    )
    for finding in run.findings:
        stream.write(f"{finding}\n")
    return 0 if same else 1


def _error(command: str, message: str) -> None:
    sys.stderr.write(f"rr-actors {command}: {message}\n")


def recorded_plan(run_dir: Path, seed: int) -> tuple[Plan, dict[str, Any]]:
    """The plan of a run directory (its setups from the original's folder) and the line of `seed`.

    Raises:
        ConfigError: no such file or line; a file not regular, too big (`PLAN_LIMIT`,
            `LINE_LIMIT`) or not UTF-8; a line not a seed's; the plan invalid or not
            simulable (`PlanError` naming `RUN/plan.toml`).
    """
    recorded = _recorded(run_dir, seed)
    path = run_dir / "plan.toml"
    text = read_plan_text(path)
    original = recorded["plan"] or None  # (its setups' folder: the sweep's imports')
    base_dir = None if original is None else os.path.dirname(os.path.abspath(original))
    plan = parse_plan(text, source=str(path), name=Path(original or path).stem, base_dir=base_dir)
    try:
        plan = plan.with_changes(duration=recorded["duration"])
    except ConfigError as exc:
        raise ConfigError(f"{run_dir / SEEDS_FILE}: seed {seed}: {exc}") from None
    simulate.check_simulable(plan)
    if original is None:
        return plan, recorded
    # (from here on the plan is the original file's, as in the sweep: a shrink reads its
    # candidates with its folder, and names it in the shrunk run's seeds.jsonl)
    return _read_from(plan, original), recorded


def read_plan_text(path: Path) -> str:
    """The text of a run directory's `plan.toml`, read within `PLAN_LIMIT` bytes.

    Raises:
        ConfigError: it cannot be opened, is not a regular file, is too big or not UTF-8.
    """
    return read_text(path, PLAN_LIMIT, "a plan")


def _read_from(plan: Plan, source: str) -> Plan:
    """`plan` (and each of its variants) as read from `source`."""
    variants = tuple((v, dataclasses.replace(p, source=source)) for v, p in plan.variants)
    return dataclasses.replace(plan, source=source, variants=variants)


def shrink_arguments(parser: argparse.ArgumentParser) -> None:
    """The `shrink` subcommand's arguments."""
    parser.add_argument(
        "run_dir", metavar="RUN", help="the --out directory of `rr-actors experiment --simulate`"
    )
    parser.add_argument("--seed", type=int, required=True, help="a seed that violated a rule")
    parser.add_argument(
        "--out", metavar="DIR", help="where the shrunk run goes (default: RUN/shrunk-seed-S)"
    )
    parser.add_argument(
        "--budget",
        type=int,
        default=shrink.BUDGET,
        help=f"the most simulated runs to make (default: {shrink.BUDGET})",
    )
    parser.add_argument(
        "--tries",
        type=int,
        default=shrink.TRIES,
        help="seeds per candidate at first: the current one, then 1, 2, ...; four times as "
        f"many after each round that kept nothing (default: {shrink.TRIES})",
    )


def run_shrink(args: argparse.Namespace, stream: TextIO) -> int:
    """`rr-actors shrink RUN --seed S`: 0 shrunk, 1 a run failed, 2 bad input (the seed
    did not violate, among others)."""
    run_dir = Path(args.run_dir)
    out = Path(args.out) if args.out else run_dir / f"shrunk-seed-{args.seed}"
    if args.budget < 1 or args.tries < 1:
        _error("shrink", "--budget and --tries must be at least 1")
        return 2
    try:
        plan, _ = recorded_plan(run_dir, args.seed)
        text = read_plan_text(run_dir / "plan.toml")  # (read and checked: recorded_plan)
    except ConfigError as exc:
        _error("shrink", str(exc))
        return 2
    argv = ["shrink", args.run_dir, "--seed", str(args.seed), "--out", str(out)]
    argv += ["--budget", str(args.budget), "--tries", str(args.tries)]
    code = hash_fixed(argv, stream)
    if code is not None:
        return code
    try:
        with stopping_on_signals():
            shrink_seed(
                plan, args.seed, out, _Say(stream), budget=args.budget, tries=args.tries, text=text
            )
    except (RrError, KeyboardInterrupt) as exc:
        return _failed("shrink", exc)
    return 0


def _failed(command: str, exc: RrError | KeyboardInterrupt) -> int:
    """Say why `command` ended early; its exit code: 2 bad input (`ConfigError`), 1 a
    run failed, 128 + the signal that stopped it (`stopped_code`)."""
    if isinstance(exc, KeyboardInterrupt):
        _error(command, stopped_line(exc))
        return stopped_code(exc)
    _error(command, str(exc))
    return 2 if isinstance(exc, ConfigError) else 1


class _Say(contextlib.nullcontext["_Say"]):
    """A display of plain lines (`cli.Display`'s `say`, no bar)."""

    def __init__(self, stream: TextIO) -> None:
        super().__init__(self)
        self.stream = stream

    def say(self, line: object) -> None:
        self.stream.write(f"{line}\n")
        self.stream.flush()


def shrink_seed(
    plan: Plan,
    seed: int,
    out: Path,
    display: Any,
    *,
    budget: int = shrink.BUDGET,
    tries: int = shrink.TRIES,
    text: str | None = None,
) -> shrink.Shrunk:
    """Shrink one violating seed (`shrink.shrink`) and write the shrunk run into `out`.

    Raises:
        ConfigError: the seed does not violate (or the plan has no file).
        RrError: a run failed.
    """
    bar = getattr(display, "bar", None)
    task = None
    if bar is not None:
        for shown in bar.task_ids:  # (the sweep's, done)
            bar.update(shown, visible=False)
        task = bar.add_task(f"shrink seed {seed}", total=budget)

    def ran(runs: int) -> None:
        if bar is not None and task is not None:
            bar.update(task, completed=runs)

    with _warnings_off(), display:
        shrunk = shrink.shrink(
            plan, seed, budget=budget, tries=tries, on_step=display.say, on_run=ran, text=text
        )
    if bar is not None and task is not None:
        bar.remove_task(task)
    shrink.write(shrunk, out, seed_line(shrunk.run, shrunk.plan))
    run = shrunk.run
    told = f" (its story {shrunk.story})" if 0 < shrunk.story < run.events else ""
    display.say(
        f"shrunk seed {seed} ({shrunk.original_events} events) to seed {shrunk.seed}: "
        f"{run.events} events{told}, {run.faults} faults, {shrunk.plan.workload.clients} "
        f"clients, {shrunk.plan.duration:g} s ({shrunk.runs} runs)"
    )
    display.say(f"  {shrunk.kind}")
    display.say(f"written to {out}/: plan.toml, {SEEDS_FILE}, events-seed-{shrunk.seed}.jsonl")
    display.say(f"replay it: rr-actors replay {out} --story")
    return shrunk


def shrink_violations(
    plan: Plan,
    runs: list[simulate.SimulatedRun],
    out: Path,
    display: Any,
    *,
    budget: int = shrink.BUDGET,
) -> list[shrink.Shrunk]:
    """`--shrink`: the first violating seed of each kind, shrunk into `out/shrunk-seed-S`.

    Raises:
        RrError: a run failed.
    """
    firsts: dict[str, int] = {}
    for run in runs:
        for kind in shrink.violation_kinds(run)[:1]:
            firsts.setdefault(kind, run.seed)
    return [
        shrink_seed(plan, seed, out / f"shrunk-seed-{seed}", display, budget=budget)
        for seed in dict.fromkeys(firsts.values())
    ]


def _only_seed(run_dir: Path) -> int:
    """The seed of a run directory that recorded one (`ConfigError` if it has more)."""
    path = run_dir / SEEDS_FILE
    seeds = [line["seed"] for _, line in _seed_lines(run_dir)]
    if len(seeds) != 1:
        raise ConfigError(f"{path}: {len(seeds)} seeds recorded: give --seed S")
    return int(seeds[0])


def _recorded(run_dir: Path, seed: int) -> dict[str, Any]:
    """The line of `seed` in `RUN/seeds.jsonl`.

    Raises:
        ConfigError: no such file, a line not a seed's, or no line of that seed.
    """
    run: list[int] = []
    for number, line in _seed_lines(run_dir):
        if line["seed"] == seed:
            if line.get("verdict") == "lost":
                raise ConfigError(
                    f"{run_dir / SEEDS_FILE}:{number}: seed {seed} was lost (its worker "
                    f"{_words(line.get('worker'))}): no history to replay; `rr-actors "
                    f"experiment PLAN --simulate --seeds {seed}` runs it again"
                )
            _check_fields(line, f"{run_dir / SEEDS_FILE}:{number}")
            return line
        run.append(line["seed"])
    raise ConfigError(
        f"{run_dir / SEEDS_FILE}: seed {seed} was not run (seeds run: {_seed_ranges(run)})"
    )


def _seed_ranges(seeds: list[int]) -> str:
    """`seeds` as ranges, the way `--seeds` takes them: `[1, 2, 3, 7]` -> `"1-3,7"`."""
    if not seeds:
        return "none"
    parts: list[str] = []
    ordered = sorted(set(seeds))
    start = previous = ordered[0]
    for seed in [*ordered[1:], None]:
        if seed is not None and seed == previous + 1:
            previous = seed
            continue
        parts.append(f"{start}" if start == previous else f"{start}-{previous}")
        if seed is not None:
            start = previous = seed
    return ",".join(parts)


_FIELDS: tuple[tuple[str, tuple[type, ...], str], ...] = (
    ("seed", (int,), "a whole number"),
    ("hash", (str,), "a string"),
    ("duration", (int, float), "a number of seconds"),
    ("plan", (str, type(None)), "a file name or null"),
)
"""What `replay` reads of a line of `seeds.jsonl`: each field, its types, in words."""


def _seed_lines(run_dir: Path) -> Iterator[tuple[int, dict[str, Any]]]:
    """Each line of `RUN/seeds.jsonl` with its number (1-based), blank ones skipped.

    Raises:
        ConfigError: no such file or not regular; a line too long (`LINE_LIMIT`), not UTF-8,
            not a JSON object with a whole-number `seed` (the message names file and line).
    """
    path = run_dir / SEEDS_FILE
    if not run_dir.exists():
        raise ConfigError(
            f"{run_dir}: no such folder (give the --out folder of an `experiment --simulate` run)"
        )
    if not path.exists():
        raise ConfigError(f"{run_dir}: no {SEEDS_FILE} (not an `experiment --simulate` output)")
    with open_regular(path) as lines:
        number = 0
        while raw := lines.readline(LINE_LIMIT + 1):
            number += 1
            if len(raw) > LINE_LIMIT and not raw.endswith(b"\n"):
                raise ConfigError(f"{path}:{number}: longer than {LINE_LIMIT} bytes")
            if raw.strip():
                yield number, _seed_line(raw, f"{path}:{number}")


def _seed_line(raw: bytes, where: str) -> dict[str, Any]:
    """One line of `seeds.jsonl`, read and checked (`_seed_lines`)."""
    try:
        line = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{where}: not UTF-8 text ({exc.reason})") from None
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{where}: not a JSON line ({exc.msg}, column {exc.colno})") from None
    except RecursionError:
        raise ConfigError(f"{where}: not a seed's line: nested too deeply to read") from None
    except ValueError:  # (an integer past Python's limit of digits)
        digits = sys.get_int_max_str_digits()
        raise ConfigError(f"{where}: not a seed's line: a number of over {digits} digits") from None
    if not isinstance(line, dict):
        raise ConfigError(f"{where}: not a seed's line: {_short(line)}")
    _check_fields(line, where, _FIELDS[:1])
    return line


def _check_fields(
    line: dict[str, Any],
    where: str,
    fields: tuple[tuple[str, tuple[type, ...], str], ...] = _FIELDS,
) -> None:
    """Refuse a line without one of `fields` of its type (`plan` missing: `None`).

    Raises:
        ConfigError: the message names the line (`where`) and the field.
    """
    for key, types, what in fields:
        if key not in line and key != "plan":  # (no plan: the run directory's copy's)
            raise ConfigError(f"{where}: not a seed's line: no {key}")
        line.setdefault(key, None)
        value = line[key]
        if not isinstance(value, types) or isinstance(value, bool):
            raise ConfigError(f"{where}: {key} must be {what}, got {_short(value)}")


def _words(value: object) -> str:
    """A line's text as it is if it is a short printable string, or `_short`'s words."""
    if isinstance(value, str) and len(value) <= 80 and value.isprintable():
        return value
    return _short(value)


def _short(value: object) -> str:
    """A JSON value in words: a scalar's `repr` (cut to 60 characters), or its type."""
    if isinstance(value, list | dict):
        return f"a JSON {'array' if isinstance(value, list) else 'object'}"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
