"""What every benchmark here shares: options, alternated rounds, statistics, the table.

A figure means something only as a ratio to a floor measured in the same run, so a script
names its rows (the floor among them) and `alternate` measures them round by round (round
1 of every row, then round 2, ...), spreading other programs' noise over all rows. `table`
prints the Markdown table whose last column (the ratio) `alternate.py` sums up, under
`header`'s line (the CPUs this run may use: `taskset -c 0` pins it, and the load average).
`--quick` is the smallest run (`tests/test_benchmarks.py`): its figures mean nothing.
`cpu_seconds` and `memory_kib` read a process's CPU time and memory from /proc (Linux).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
QUICK_ROUNDS = 1
QUICK_BATCH = 5


def options(
    doc: str | None, *, rounds: int | None = None, batch: int | None = None
) -> argparse.ArgumentParser:
    """A parser with `--quick`, `--rounds` (when `rounds` is given; 0: the script chooses)
    and `--batch` (when `batch` is given); `parse` applies `--quick`. The description is
    `doc`'s first line."""
    parser = argparse.ArgumentParser(description=(doc or "").splitlines()[0])
    if rounds is not None:
        parser.add_argument("--rounds", type=int, default=rounds, help="alternated rounds")
    if batch is not None:
        parser.add_argument("--batch", type=int, default=batch, help="operations a round")
    parser.add_argument("--quick", action="store_true", help="the smallest run")
    return parser


def parse(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> argparse.Namespace:
    """`parser.parse_args(argv)`, with `--quick` setting the rounds and the batch."""
    args = parser.parse_args(argv)
    if args.quick:
        if hasattr(args, "rounds"):
            args.rounds = QUICK_ROUNDS
        if hasattr(args, "batch"):
            args.batch = QUICK_BATCH
    return args


def per_op(op: Callable[[], object], batch: int) -> float:
    """Seconds per call of `op`, called `batch` times back to back."""
    began = time.perf_counter()
    for _ in range(batch):
        op()
    return (time.perf_counter() - began) / batch


def each(op: Callable[[], object], batch: int) -> list[float]:
    """Seconds of each of `batch` calls of `op`, timed one by one."""
    clock = time.perf_counter_ns
    took: list[float] = []
    for _ in range(batch):
        began = clock()
        op()
        took.append((clock() - began) / 1e9)
    return took


def alternate(
    rows: Mapping[str, Callable[[], float | list[float]]],
    rounds: int,
    *,
    warm_up: bool = True,
    rotate: bool = False,
) -> dict[str, list[float]]:
    """Every row's samples over `rounds` alternated rounds (a row returns one sample or a
    list of them). `warm_up` runs each row once first, untimed; `rotate` starts round k
    at row k (modulo the rows)."""
    names = list(rows)
    if warm_up:
        for name in names:
            rows[name]()
    samples: dict[str, list[float]] = {name: [] for name in names}
    for k in range(rounds):
        start = k % len(names) if rotate else 0
        for name in names[start:] + names[:start]:
            got = rows[name]()
            samples[name].extend(got if isinstance(got, list) else [got])
    return samples


def percentile(values: Sequence[float], fraction: float) -> float:
    """The `fraction` quantile of `values` (nearest rank)."""
    ordered = sorted(values)
    index = min(len(ordered) - 1, max(0, round(fraction * len(ordered)) - 1))
    return float(ordered[index])


def median(values: Iterable[float]) -> float:
    """The median (`statistics.median`) as a float."""
    return float(statistics.median(values))


def header(what: str) -> str:
    """One line: Python, machine, the CPUs this run may use, the load average, `what`."""
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "?"
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (
        f"python {platform.python_version()} on {platform.machine()} ({sys.platform}), "
        f"CPUs {cpus}, load {load:.2f}; {what}"
    )


def table(columns: Sequence[str], rows: Iterable[Sequence[object]], *, right: int = 1) -> str:
    """A Markdown table: `columns`, then one line per row (each cell `str()`ed); the
    columns from index `right` on are right-aligned (numbers)."""
    rule = "|" + "|".join("---" if i < right else "---:" for i in range(len(columns))) + "|"
    return "\n".join([line(columns), rule, *(line(row) for row in rows)])


def line(cells: Sequence[object]) -> str:
    """One row of a Markdown table (each cell `str()`ed): for a row printed as measured."""
    return "| " + " | ".join(str(cell) for cell in cells) + " |"


def print_table(
    title: str, columns: Sequence[str], rows: Iterable[Sequence[object]], *, right: int = 1
) -> None:
    """Print `title` after a blank line, then `table(columns, rows, right=right)`."""
    print(f"\n{title}\n{table(columns, rows, right=right)}")


@contextlib.contextmanager
def busy(count: int) -> Iterator[None]:
    """`count` processes that only spin (each keeps a CPU busy), for as long as the block runs."""
    spinning = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]
    try:
        yield
    finally:
        for process in spinning:
            process.kill()
        for process in spinning:
            process.wait(10)


def commit() -> str:
    """The checkout's commit (`git describe --always --dirty`: `-dirty` with changes not
    committed), or "?" without git or a checkout."""
    git = shutil.which("git")
    if git is None:
        return "?"
    done = subprocess.run(
        [git, "-C", str(ROOT), "describe", "--always", "--dirty"],
        capture_output=True,
        text=True,
        check=False,
    )
    return done.stdout.strip() or "?"


def cpu_seconds(pids: Iterable[int]) -> float:
    """CPU seconds so far of every live thread of the processes `pids` (Linux schedstat;
    a thread or process that ended meanwhile is missed)."""
    total = 0
    for pid in pids:
        with contextlib.suppress(OSError):
            for task in os.listdir(f"/proc/{pid}/task"):
                with contextlib.suppress(OSError), open(f"/proc/{pid}/task/{task}/schedstat") as s:
                    total += int(s.read().split()[0])
    return total / 1e9


def memory_kib(pid: int | None = None, field: str = "VmRSS") -> int | None:
    """Process `pid`'s (this one's if `None`) `VmRSS` (from `status`) or `Pss` (from
    `smaps_rollup`) in KiB; `None` where it cannot be read (Linux only)."""
    where = f"/proc/{pid or 'self'}/{'status' if field == 'VmRSS' else 'smaps_rollup'}"
    with contextlib.suppress(OSError), open(where) as lines:
        for line in lines:
            if line.startswith(f"{field}:"):
                return int(line.split()[1])
    return None


def head(title: str | None, columns: Sequence[str], *, right: int = 1) -> None:
    """Print `title` (unless `None`), then the first two lines of `table(columns, ...)`:
    for a script that prints its rows (`| a | b |`) as it measures them."""
    if title is not None:
        print(title)
    print(table(columns, [], right=right))
