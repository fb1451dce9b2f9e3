"""Scale benchmark: how costs grow with the number of process managers, beside their floor.

Section "start": a `Supervisor` of N process managers is started (`start()` returns once
every one serves, in order: OTP's ordered start) and stopped; beside it, in the same run
and alternated with it round by round, its floor: N plain `multiprocessing` children
started the same way, one after the other, each telling its parent "ready" over a pipe
before the next is started (the forkserver context, as rr_actors uses; its forkserver is
started before the clock runs, as the supervisor's is). Also the memory of one process
manager (PSS, from `/proc/<pid>/smaps_rollup`, Linux) beside a plain child's.

Target (issue 34 item 1): 50 process managers start within 3x the time of the floor.

Section "serve": kill to serving with N catalog entries. A manager process whose backup
holds N served resources (one consumer id each) is SIGKILLed; the time runs from the kill
until a call answered by its new incarnation returned (`bench_supervisor.measure`:
respawned, restored, setup run, serving, one call), with the supervisor subscribed (as
an experiment is: the restored registrar publishes `CatalogRestored`). Beside it, in
the same run and alternated round by round, its floor: a plain forkserver child (of a
Python of its own, importing nothing) SIGKILLed, its exit waited on and a new one
started until it says "ready".
Target (issue 34 item 3): at 100k entries within 2x of the figure at 1k.

Run: `python benchmarks/bench_scale.py [--sections start serve] [--counts 1 10 50]
[--sizes 1000 10000 100000] [--rounds 5] [--kills 5] [--pin]`
(`--pin`: under `taskset -c 0`, one CPU, as `benchmarks/alternate.py --pin` runs).
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
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


RESPAWN = """
import multiprocessing, os, signal, sys, time
from multiprocessing import forkserver
context = multiprocessing.get_context("forkserver")
context.set_forkserver_preload([])
forkserver.ensure_running()
CHILD = "import os\\nready.send(os.getpid())\\n"
CHILD += "try:\\n    ready.recv()\\nexcept EOFError:\\n    pass"
def spawn():
    ours, theirs = context.Pipe()
    process = context.Process(target=exec, args=(CHILD, {"ready": theirs}), daemon=True)
    process.start()
    theirs.close()
    ours.recv()
    return process, ours
process, ours = spawn()
for line in sys.stdin:
    times = []
    for _ in range(int(line)):
        began = time.perf_counter()
        os.kill(process.pid, signal.SIGKILL)
        process.join()
        ours.close()
        process, ours = spawn()
        times.append((time.perf_counter() - began) * 1000)
    print(*times, flush=True)
os.kill(process.pid, signal.SIGKILL)
process.join()
"""
"""The respawn floor, run by a Python of its own (as `FLOOR`): it keeps one plain child;
each line it reads is a count k: k times it SIGKILLs the child, waits for its exit and
starts a new one until it says "ready", and prints the k times in ms."""


class Respawn:
    """The respawn floor's process: `kill(k)` times k respawns of a plain child."""

    def __init__(self) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-c", RESPAWN],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )

    def kill(self, count: int) -> list[float]:
        assert self.process.stdin is not None
        assert self.process.stdout is not None
        self.process.stdin.write(f"{count}\n")
        self.process.stdin.flush()
        return [float(ms) for ms in self.process.stdout.readline().split()]

    def close(self) -> None:
        assert self.process.stdin is not None
        self.process.stdin.close()
        self.process.wait(30)


class Served:
    """A supervisor of one manager process whose backup holds `size` entries."""

    def __init__(self, size: int, *, listen: bool) -> None:
        from bench_supervisor import fill_backup  # noqa: PLC0415 - a sibling script

        self.state = tempfile.TemporaryDirectory()
        self.name = f"serve{size}"
        fill_backup(Path(self.state.name) / f"{self.name}.db", size)
        spec = rr.ManagerSpec(self.name, setup, isolation="process", start_timeout=120.0)
        self.supervisor = rr.Supervisor(
            [spec], max_restarts=10_000, period=3600.0, state_dir=self.state.name
        )
        self.listening = self.supervisor.subscribe(lambda _event: None) if listen else None
        self.supervisor.start()
        self.app = self.supervisor.registrar(f"app{size}")
        self.app.call(self.name, "res", "warm-up", timeout=120.0)
        self.calls = 0

    def kill(self) -> float:
        """SIGKILL the manager; ms until a call answered by its next incarnation returned."""
        time.sleep(0.2)  # the last restart settled (its spare process warmed up)
        pid = self.supervisor.child(self.name).pid
        assert pid is not None
        killed = time.perf_counter()
        os.kill(pid, signal.SIGKILL)
        self.supervisor.wait_restarted(self.name, timeout=120.0)
        self.calls += 1
        self.app.call(self.name, "res", f"after-{self.calls}", timeout=120.0)
        return (time.perf_counter() - killed) * 1000

    def close(self) -> None:
        self.supervisor.stop()
        if self.listening is not None:
            self.listening.close()
        self.state.cleanup()


def section_serve(sizes: list[int], rounds: int, kills: int, *, listen: bool) -> None:
    start_forkserver()
    floor = Respawn()
    floor.kill(1)  # warm its forkserver's first fork
    served = [Served(size, listen=listen) for size in sizes]
    heard = "subscribed (events on)" if listen else "nobody subscribed"
    print(f"## serve: kill to serving with N catalog entries (ms; {heard})")
    print()
    print("| N | rr_actors med | rr_actors min-max | floor med | floor min-max | to 1k |")
    print("|---|---|---|---|---|---|")
    ours: dict[int, list[float]] = {size: [] for size in sizes}
    plain: dict[int, list[float]] = {size: [] for size in sizes}
    for _ in range(rounds):  # alternated: every size and the floor meet the same noise
        for tree in served:
            size = int(tree.name.removeprefix("serve"))
            ours[size].extend(tree.kill() for _ in range(kills))
            plain[size].extend(floor.kill(kills))
    for tree in served:
        tree.close()
    floor.close()
    base = statistics.median(ours[sizes[0]])
    for size in sizes:
        median = statistics.median(ours[size])
        print(
            f"| serve {size} | {median:.1f} | {spread(ours[size])} "
            f"| {statistics.median(plain[size]):.1f} | {spread(plain[size])} "
            f"| {median / base:.2f}x |"
        )
    print()
    print(f"(to 1k: the median over that of N = {sizes[0]})")
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sections", nargs="+", choices=["start", "serve"], default=["start"])
    parser.add_argument("--counts", type=int, nargs="+", default=[1, 10, 50])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1_000, 10_000, 100_000])
    parser.add_argument("--kills", type=int, default=5, help="kills per size and round (serve)")
    parser.add_argument("--listen", action="store_true", help="serve: subscribe to the tree")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--pin", action="store_true", help="run under taskset -c 0")
    args = parser.parse_args()
    if args.pin and not os.environ.get("RR_BENCH_PINNED"):
        command = ["taskset", "-c", "0", sys.executable, *sys.argv]
        env = {**os.environ, "RR_BENCH_PINNED": "1"}
        raise SystemExit(subprocess.run(command, env=env, check=False).returncode)
    if "start" in args.sections:
        section_start(args.counts, args.rounds)
    if "serve" in args.sections:
        section_serve(args.sizes, args.rounds, args.kills, listen=args.listen)


if __name__ == "__main__":
    main()
