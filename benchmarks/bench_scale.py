"""Scale benchmark: how costs grow with the number of process managers, beside their floor.

Section "start": a `Supervisor` of N process managers is started (`start()` returns once
every one serves, in order: OTP's ordered start) and stopped; beside it, in the same run
and alternated with it round by round, its floor: N plain `multiprocessing` children
started the same way, one after the other, each telling its parent "ready" over a pipe
before the next is started (the forkserver context, as rr_actors uses; its forkserver is
started before the clock runs, as the supervisor's is). Also the memory of one process
manager (PSS, from `/proc/<pid>/smaps_rollup`, Linux) beside a plain child's.

Target (issue 34 item 1): 50 process managers start within 3x the time of the floor.

Run: `python benchmarks/bench_scale.py [--counts 1 10 50] [--rounds 5] [--pin]`
(`--pin`: under `taskset -c 0`, one CPU, as `benchmarks/alternate.py --pin` runs).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import rr_actors as rr
from rr_actors.testing import start_forkserver


def setup(registrar: rr.ResourceRegistrar) -> None:
    """Each manager's setup: one server (what a small experiment's manager has)."""
    registrar.register_server("res", load=lambda r: r, unload=lambda r, s: None)


FLOOR = """
import multiprocessing, os, sys, time
from multiprocessing import forkserver
context = multiprocessing.get_context("forkserver")
context.set_forkserver_preload([])
forkserver.ensure_running()
CHILD = "import os\\nready.send(os.getpid())\\n"
CHILD += "try:\\n    ready.recv()\\nexcept EOFError:\\n    pass"
for line in sys.stdin:
    children = []
    began = time.perf_counter()
    for _ in range(int(line)):
        ours, theirs = context.Pipe()
        names = {"ready": theirs}
        process = context.Process(target=exec, args=(CHILD, names), daemon=True)
        process.start()
        theirs.close()
        ours.recv()
        children.append((process, ours))
    elapsed = (time.perf_counter() - began) * 1000
    pss = open(f"/proc/{children[-1][0].pid}/smaps_rollup").read().split("Pss:")[1].split()[0]
    for process, ours in children:
        ours.close()
    for process, _ in children:
        process.join(10)
    print(elapsed, pss, flush=True)
"""
"""The floor, run by a Python of its own (`python -c`): its children have no main module
to re-import and import nothing of rr_actors or of this script. Each line it reads is a
count N; it starts N children in order (each runs `exec` of a few lines: say "ready",
then wait for EOF), and prints the milliseconds and the last child's PSS (KiB)."""


class Floor:
    """The floor's process: `start(n)` times n plain children there."""

    def __init__(self) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-c", FLOOR], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )

    def start(self, count: int) -> tuple[float, int | None]:
        assert self.process.stdin is not None
        assert self.process.stdout is not None
        self.process.stdin.write(f"{count}\n")
        self.process.stdin.flush()
        elapsed, pss = self.process.stdout.readline().split()
        return float(elapsed), int(pss)

    def close(self) -> None:
        assert self.process.stdin is not None
        self.process.stdin.close()
        self.process.wait(30)


def pss_kib(pid: int) -> int | None:
    """The proportional set size of process `pid` in KiB (`None` where it cannot be read)."""
    try:
        text = Path(f"/proc/{pid}/smaps_rollup").read_text()
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith("Pss:"):
            return int(line.split()[1])
    return None


def start_managers(count: int) -> tuple[float, int | None]:
    """Start (and stop) a supervisor of `count` process managers; ms to start, a PSS."""
    specs = [rr.ManagerSpec(f"m{n}", setup, isolation="process") for n in range(count)]
    supervisor = rr.Supervisor(specs, name=f"scale-{count}")
    began = time.perf_counter()
    supervisor.start()
    elapsed = (time.perf_counter() - began) * 1000
    pid = supervisor.child(f"m{count - 1}").pid
    memory = pss_kib(pid) if pid is not None else None
    supervisor.stop()
    return elapsed, memory


def spread(values: list[float]) -> str:
    return f"{min(values):.0f}-{max(values):.0f}"


def section_start(counts: list[int], rounds: int) -> None:
    start_forkserver()  # rr_actors' forkserver (preloaded), before the clocks run
    floor = Floor()
    start_managers(1)  # warm both sides (imports, the forkservers' first forks)
    floor.start(1)
    print("## start: N process managers vs N plain multiprocessing children (ms)")
    print()
    print("| N | rr_actors med | rr_actors min-max | floor med | floor min-max | ratio |")
    print("|---|---|---|---|---|---|")
    memory: dict[str, int | None] = {}
    for count in counts:
        ours: list[float] = []
        plain: list[float] = []
        for _ in range(rounds):  # alternated: both meet the same noise
            elapsed, memory["rr_actors"] = start_managers(count)
            ours.append(elapsed)
            elapsed, memory["plain"] = floor.start(count)
            plain.append(elapsed)
        ratio = statistics.median(ours) / statistics.median(plain)
        print(
            f"| start {count} | {statistics.median(ours):.0f} | {spread(ours)} "
            f"| {statistics.median(plain):.0f} | {spread(plain)} | {ratio:.1f}x |"
        )
    floor.close()
    print()
    mine, theirs = memory.get("rr_actors"), memory.get("plain")
    if mine is not None and theirs is not None:
        print(
            f"memory (PSS) of one process manager: {mine / 1024:.1f} MiB; "
            f"of one plain child: {theirs / 1024:.1f} MiB"
        )
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[1, 10, 50])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--pin", action="store_true", help="run under taskset -c 0")
    args = parser.parse_args()
    if args.pin and not os.environ.get("RR_BENCH_PINNED"):
        command = ["taskset", "-c", "0", sys.executable, *sys.argv]
        env = {**os.environ, "RR_BENCH_PINNED": "1"}
        raise SystemExit(subprocess.run(command, env=env, check=False).returncode)
    section_start(args.counts, args.rounds)


if __name__ == "__main__":
    main()
