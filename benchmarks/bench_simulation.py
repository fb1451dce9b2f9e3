"""How fast a plan runs on the simulation: runs per CPU-minute, virtual seconds per CPU
second, next to a real run of the same plan and to the floors (issue 42 section 3).

The plan is the shipped `killheavy` without its `cut_connections` fault (not simulated
yet): a chain edge -> api -> db of manager processes, 4 clients, about 600 calls and 20
SIGKILLs in 6 virtual seconds. Rows:

    greenlet switch (floor)   two bare greenlets switching back and forth: switches/s
    scheduler step (floor)    two simulated threads handing an `Event` to each other
                              (`simulation.run`): steps/s of the scheduler with no work
    pykka ask (floor)         a raw pykka `ask` to a `ThreadingActor`, on real threads
    simulated run, per seed   `simulate.run_seed` (what `rr-actors experiment --simulate`
                              runs per seed): CPU s of the simulation, of the history and
                              its verdict (`check`), steps, virtual s
    real run                  `rr-actors experiment PLAN --repeat 1`: wall s of the
                              command (one run, fresh processes, plots), its workload's
                              duration, and the CPU s of all its processes (the same
                              protocol work on real threads: what a simulated run's CPU
                              cannot go much below)

and the figures the issue sets targets for: simulated runs per CPU-minute (200), and how
many times faster a simulated run is than a real one of the same plan (20: the real
run's wall time over the simulated run's CPU time), with the simulated clock's speed
(virtual s per CPU s) beside them. Seeds run under `PYTHONHASHSEED=0` (as the sweep's:
the script starts itself again under it) so their hashes are those of a sweep.

Pin it to one CPU for the figures the docs state (the real run's manager processes share
that CPU then too):

    taskset -c 0 python benchmarks/bench_simulation.py --seeds 1-20
    python benchmarks/bench_simulation.py --seeds 1-3 --no-real --profile /tmp/sim.prof
    python benchmarks/bench_simulation.py --seeds 1-3 --no-real --sample /tmp/sim.folded
    python benchmarks/bench_simulation.py --jobs --plan killheavy --seeds 1-40   # every core

`--sample` records where the seeds' CPU time goes (the simulation, its history and its
verdict), one sample a tick of the process's CPU time (`SIGPROF`; 1-4 ms), so the waits
of a loaded machine count for nothing, unlike a sampler of wall time (py-spy, whose
shares they blur). Its file has one folded stack a line with its count (`a;b;c 12`, as
`py-spy record -f raw`: flamegraph.pl reads it); the script prints the functions with
the most samples, the files, and the parts of a seed (`part`): the simulation's own
machinery, and the rest, the protocol's floor (what a seed would cost if the machinery
cost nothing).
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import csv
import functools
import json
import logging
import os
import platform
import resource
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import types
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from types import FrameType
from typing import Any

import _harness
import greenlet
import pykka

import rr_actors_lab
from rr_actors import simulation
from rr_actors._core import runtime
from rr_actors.simulation import _run
from rr_actors_lab.experiments import simulate
from rr_actors_lab.experiments.reading import load_plan

PLANS = Path(rr_actors_lab.__file__).parent / "experiments" / "plans"


def killheavy_without_cut(folder: Path) -> Path:
    """The shipped killheavy plan without its `cut_connections` fault, written to `folder`."""
    text = (PLANS / "killheavy.toml").read_text(encoding="utf-8")
    head, *faults = text.split("[[faults]]")
    kept = [f for f in faults if 'kind = "cut_connections"' not in f]
    path = folder / "killheavy-nocut.toml"
    path.write_text(head + "".join("[[faults]]" + f for f in kept), encoding="utf-8")
    return path


def greenlet_switches(n: int) -> float:
    """Switches per second of two bare greenlets (the floor of any greenlet scheduler)."""

    def other() -> None:
        while True:
            main.switch()

    main = greenlet.getcurrent()
    peer = greenlet.greenlet(other)
    start = time.process_time()
    for _ in range(n):
        peer.switch()
    return 2 * n / (time.process_time() - start)


def scheduler_steps(n: int) -> float:
    """Steps per second of CPU of the simulation's scheduler with nothing else to do: two
    simulated threads handing a turn to each other through simulated `Event`s."""

    def world() -> None:
        ping, pong = runtime.Event(), runtime.Event()

        def player(mine: Any, theirs: Any) -> None:
            for _ in range(n):
                mine.wait()
                mine.clear()
                theirs.set()

        threads = [
            runtime.Thread(target=player, args=(ping, pong), name="ping"),
            runtime.Thread(target=player, args=(pong, ping), name="pong"),
        ]
        for thread in threads:
            thread.start()
        ping.set()
        for thread in threads:
            thread.join()

    start = time.process_time()
    ran = simulation.run(world, seed=1, preempt=simulate.PREEMPT)
    return ran.steps / (time.process_time() - start)


class _Echo(pykka.ThreadingActor):
    def on_receive(self, message: Any) -> Any:
        return message


def pykka_asks(n: int) -> float:
    """Asks per second of CPU of a raw pykka `ask` on real threads."""
    ref = _Echo.start()
    try:
        start = time.process_time()
        for i in range(n):
            ref.ask(i)
        return n / (time.process_time() - start)
    finally:
        ref.stop()


@contextlib.contextmanager
def split_simulation(seen: list[tuple[float, int]]) -> Iterator[None]:
    """Meanwhile, each `simulation.run` adds its CPU seconds and steps to `seen` (the rest
    of a seed's CPU is its history and verdict). The caller waits in a join meanwhile, so
    the process's CPU time is the simulation thread's."""
    real = simulation.run

    def timed(*args: Any, **kwargs: Any) -> Any:
        start = time.process_time()
        ran = real(*args, **kwargs)
        seen.append((time.process_time() - start, ran.steps))
        return ran

    simulation.run = timed  # type: ignore[assignment] - (read at each call by run_seed)
    try:
        yield
    finally:
        simulation.run = real  # type: ignore[assignment]


class _Inline:
    """A `threading.Thread` that runs its target in `start`, in the calling thread."""

    def __init__(self, target: Callable[..., None], args: tuple[Any, ...], **_: Any) -> None:
        self._run = functools.partial(target, *args)

    def start(self) -> None:
        self._run()

    def join(self, timeout: float | None = None) -> None:
        pass

    def is_alive(self) -> bool:
        return False


@contextlib.contextmanager
def cpu_samples(stacks: Counter[str], every: float = 0.001) -> Iterator[None]:
    """Meanwhile, each `every` seconds of the process's CPU time (`SIGPROF`), where the
    simulation is (its running greenlet's frames) is counted in `stacks`, folded
    (`outer;...;inner`). Python runs a signal's handler in the main thread, at its next
    instruction, so the simulation runs in the calling (main) thread meanwhile, not in a
    thread of its own (`simulation.run`'s `threading.Thread` made `_Inline`): a sampler
    thread would get the GIL only where the simulation lets it go (its system calls)."""

    def sample(_signum: int, frame: FrameType | None) -> None:
        stacks[_folded(frame)] += 1

    if threading.current_thread() is not threading.main_thread():
        raise RuntimeError("CPU samples are taken in the main thread only")
    threads = _run.threading
    _run.threading = types.SimpleNamespace(  # type: ignore[assignment]
        Thread=_Inline, Event=threading.Event, get_ident=threading.get_ident
    )
    previous = signal.signal(signal.SIGPROF, sample)
    signal.setitimer(signal.ITIMER_PROF, every, every)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0, 0)
        signal.signal(signal.SIGPROF, previous)
        _run.threading = threads  # type: ignore[assignment]


def _folded(frame: FrameType | None) -> str:
    names = []
    while frame is not None:
        code = frame.f_code
        where = code.co_filename.rpartition("site-packages/")[2]
        where = where.rpartition("rr_actors/")[2] if "rr_actors/" in where else where
        names.append(f"{code.co_qualname} ({where}:{frame.f_lineno})")
        frame = frame.f_back
    return ";".join(reversed(names))


MACHINERY = {
    "simulation/_network.py": "the simulated carrier and manager processes",
    "simulation/_manager.py": "the simulated carrier and manager processes",
    "testing/": "the simulated carrier and manager processes",  # (the hub under it)
    "experiments/_simulated_faults.py": "the simulated carrier and manager processes",
    "simulation/_processes.py": "switching a simulated process's singletons",
    "simulation/": "the scheduler, the simulated primitives and the seams",
}
"""The simulation's own machinery, by where its code is (the first prefix that fits)."""

FLOOR = {
    "cloudpickle/": "pickling across simulated processes",
    "_transport/codec.py": "pickling across simulated processes",
    "_store/": "the SQLite backups",
    "experiments/simulate.py": "the history's JSON and its verdict",
    "experiments/_history.py": "the history's JSON and its verdict",
    "experiments/check.py": "the history's JSON and its verdict",
    "experiments/_consumer_rules.py": "the history's JSON and its verdict",
    "experiments/_provider_rules.py": "the history's JSON and its verdict",
    "experiments/_status_rules.py": "the history's JSON and its verdict",
    "events/lines.py": "the history's JSON and its verdict",
}
"""The protocol's own work, where it is not the protocol's logic (every other file of
rr_actors, the workload's included, and pykka)."""


ELSEWHERE = "elsewhere (the benchmark, the sampler)"


def part(stack: str) -> str:
    """Which part of a seed a sample is in: its innermost frame of rr_actors, pykka or
    cloudpickle (one of the standard library, or a dataclass's generated `__init__`,
    counted for its caller), by `MACHINERY`, then `FLOOR`; else the protocol."""
    for frame in reversed(stack.split(";")):
        where = frame.rpartition(" (")[2].rpartition(":")[0]
        if where.startswith(("/", "<")) or "/" not in where:
            continue  # (the standard library, generated code, rr_actors' top modules)
        for table in (MACHINERY, FLOOR):
            for prefix, name in table.items():
                if where.startswith(prefix):
                    return name
        return "the protocol: registrars, messenger, supervisor, catalog, events, workload"
    return ELSEWHERE


def print_samples(stacks: Counter[str], path: str) -> None:
    """Write `stacks` to `path` (folded); print the top functions and files by samples,
    and the parts of a seed (`part`)."""
    with open(path, "w", encoding="utf-8") as file:
        file.writelines(f"{stack} {count}\n" for stack, count in stacks.items())
    total = sum(stacks.values()) or 1
    functions: Counter[str] = Counter()
    files: Counter[str] = Counter()
    for stack, count in stacks.items():
        inner = stack.rpartition(";")[2]
        name, _, where = inner.partition(" (")
        file = where.rpartition(":")[0]
        functions[f"{file}: {name}"] += count
        files[file] += count
    print(f"\nCPU samples of the simulation: {total:,} (a tick of CPU each: 1 to 4 ms), in {path}")
    for title, counter in (("functions", functions), ("files", files)):
        print(f"| {title} (the innermost frame) | share |\n|---|---:|")
        for key, count in counter.most_common(25):
            print(f"| {key} | {100 * count / total:.1f}% |")
    parts: Counter[str] = Counter()
    for stack, count in stacks.items():
        parts[part(stack)] += count
    machinery = set(MACHINERY.values())
    print("| parts of a seed (`part`) | share |\n|---|---:|")
    for key, count in parts.most_common():
        print(f"| {key}{' (machinery)' if key in machinery else ''} | {100 * count / total:.1f}% |")
    floor = sum(count for key, count in parts.items() if key not in machinery | {ELSEWHERE})
    print(f"| **the protocol's floor (all but the machinery)** | **{100 * floor / total:.1f}%** |")


def simulated(
    plan_path: Path, seeds: range, profile: str | None, stacks: Counter[str] | None = None
) -> list[dict[str, Any]]:
    """One row per seed: CPU s (whole, simulation), steps, virtual s, hash, verdict;
    `stacks`: the simulation thread's CPU samples added there (`cpu_samples`)."""
    plan = load_plan(plan_path)
    rows = []
    profiler = cProfile.Profile() if profile else None
    logging.getLogger("rr_actors").setLevel(logging.ERROR)  # (as the sweep: a kill is one)
    for seed in seeds:
        seen: list[tuple[float, int]] = []
        with (
            split_simulation(seen),
            cpu_samples(stacks) if stacks is not None else contextlib.nullcontext(),
        ):
            if profiler is not None:
                profiler.enable()
            start = time.process_time()
            run = simulate.run_seed(plan, seed)
            cpu = time.process_time() - start
            if profiler is not None:
                profiler.disable()
        (sim_cpu, steps), *_ = seen
        rows.append(
            {
                "seed": seed,
                "cpu": cpu,
                "sim": sim_cpu,
                "steps": steps,
                "virtual": run.virtual_s,
                "events": run.events,
                "faults": run.faults,
                "calls": run.calls_ok + run.calls_failed,
                "hash": run.hash[:12],
                "verdict": run.verdict,
            }
        )
        print(
            f"  seed {seed}: {cpu:.2f} s CPU ({sim_cpu:.2f} simulation), {steps:,} steps, "
            f"{run.virtual_s:.2f} virtual s, {run.events:,} events, {run.faults} kills, "
            f"{run.calls_ok + run.calls_failed} calls, {run.verdict}, {run.hash[:12]}",
            flush=True,
        )
    if profiler is not None and profile is not None:
        profiler.dump_stats(profile)  # (the caller's thread: history, verdict; py-spy sees all)
    return rows


def real_run(plan_path: Path) -> tuple[float, float, float]:
    """Wall s of `rr-actors experiment PLAN --repeat 1`, its workload's duration s (from
    runs.csv), and the CPU s of all its processes (those reaped: every one of a run)."""
    with tempfile.TemporaryDirectory(prefix="rr-bench-sim-") as tmp:
        out = Path(tmp) / "out"
        command = [sys.executable, "-m", "rr_actors_lab", "experiment", str(plan_path)]
        command += ["--repeat", "1", "--out", str(out), "--quiet"]
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.perf_counter()
        subprocess.run(command, check=True, capture_output=True)
        wall = time.perf_counter() - start
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
        with (out / "runs.csv").open() as file:
            (row,) = list(csv.DictReader(file))
        return wall, float(row["duration_s"]), cpu


def rate(fn: Callable[[int], float], n: int, rounds: int) -> float:
    """The best of `rounds` rates (the least disturbed by other programs)."""
    return max(fn(n) for _ in range(rounds))


def report(
    rows: list[dict[str, Any]],
    real: tuple[float, float, float] | None,
    floors: tuple[float, ...],
) -> float:
    """Print the table of figures; the simulated runs per CPU-minute."""
    switch, step, ask = floors
    cpu = statistics.mean(r["cpu"] for r in rows)
    sim = statistics.mean(r["sim"] for r in rows)
    steps = statistics.mean(r["steps"] for r in rows)
    virtual = statistics.mean(r["virtual"] for r in rows)
    runs_per_minute = 60 / cpu
    print()
    print("| figure | value | target |")
    print("|---|---:|---:|")
    median = statistics.median(r["cpu"] for r in rows)
    print(f"| CPU s per run (mean of {len(rows)}; median {median:.2f}) | {cpu:.2f} | 0.30 |")
    print(f"| of which the simulation | {sim:.2f} | |")
    print(f"| of which the history and its verdict | {cpu - sim:.2f} | |")
    print(f"| **simulated runs per CPU-minute** | **{runs_per_minute:.0f}** | 200 |")
    print(f"| virtual s per run | {virtual:.2f} | |")
    print(f"| virtual s per CPU s (the simulated clock's speed) | {virtual / cpu:.1f} | |")
    print(f"| scheduler steps per run | {steps:,.0f} | |")
    print(f"| CPU us per step (all the work) | {1e6 * sim / steps:.1f} | |")
    print(f"| ... the floor: a bare scheduler step | {1e6 / step:.1f} | |")
    print(f"| ... the floor: a bare greenlet switch | {1e6 / switch:.2f} | |")
    print(f"| a run's steps at the bare scheduler's speed, s | {steps / step:.2f} | |")
    print(f"| a run as raw pykka asks (CPU s per run x asks/s) | {sim * ask:,.0f} | |")
    if real is not None:
        wall, duration, real_cpu = real
        print(f"| real run: `rr-actors experiment --repeat 1` wall s | {wall:.2f} | |")
        print(f"| real run: its workload's duration s | {duration:.2f} | |")
        print(f"| real run: CPU s of all its processes (imports, plots too) | {real_cpu:.2f} | |")
        faster = wall / cpu
        print(
            f"| **x faster than the real run (its wall / a run's CPU)** | **{faster:.1f}** | 20 |"
        )
    return runs_per_minute


def sweep(plan: str, seeds: str, jobs: int, out: Path) -> float:
    """Wall seconds of one sweep of `plan` over `seeds` with `jobs` workers."""
    env = {**os.environ, "PYTHONHASHSEED": "0"}
    command = [sys.executable, "-m", "rr_actors_lab", "experiment", plan, "--simulate"]
    command += ["--seeds", seeds, "--jobs", str(jobs), "--out", str(out), "--quiet"]
    started = time.perf_counter()
    subprocess.run(command, env=env, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - started


def lines(out: Path) -> list[dict[str, object]]:
    """The seeds' lines without their CPU seconds (the one field that is not the run's)."""
    text = (out / "seeds.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(line).items() if k != "cpu_s"} for line in text]


def on_every_core(plan: str, seeds: str) -> None:
    """`--jobs`: `rr-actors experiment PLAN --simulate --seeds A-B --jobs N` for N = 1 to
    the cores: wall s, seeds per wall-minute, speed-up, whether `seeds.jsonl` is the
    serial one's; then a bound for 10,000 seeds on 16 cores (from this run's CPU a seed).
    Run it on an idle machine, unpinned (a process beside it takes a core from N = 2)."""
    first, _, last = seeds.partition("-")
    count = int(last or first) - int(first) + 1
    cores = len(os.sched_getaffinity(0))
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-jobs-") as folder:
        serial: list[dict[str, object]] = []
        cpu = 0.0
        for jobs in range(1, cores + 1):
            out = Path(folder) / f"jobs-{jobs}"
            wall = sweep(plan, seeds, jobs, out)
            if jobs == 1:
                serial = lines(out)
                text = (out / "seeds.jsonl").read_text().splitlines()
                cpu = sum(float(json.loads(line)["cpu_s"]) for line in text)
            rows.append((jobs, wall, lines(out) == serial))
    base = rows[0][1]
    print(_harness.header(f"{plan}, seeds {seeds} ({count}), on 1 to {cores} cores"))
    columns = ["jobs", "wall s", "seeds/wall-min", "speed-up", "same as --jobs 1"]
    print(
        _harness.table(
            columns,
            [
                (n, f"{w:.1f}", f"{60 * count / w:.1f}", f"{base / w:.2f}x", same)
                for n, w, same in rows
            ],
        )
    )
    per_seed = cpu / count
    print(
        f"CPU per seed (--jobs 1): {per_seed:.2f} s; 10,000 seeds on 16 such cores: "
        f"about {10_000 * per_seed / 16 / 60:.0f} min (at best)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="1-10", help="the seeds to run, A-B (default 1-10)")
    parser.add_argument("--no-real", action="store_true", help="skip the real run")
    parser.add_argument("--profile", help="write a cProfile of the seeds' calling thread here")
    parser.add_argument(
        "--sample", help="write CPU-time samples of the simulation's thread here (folded)"
    )
    parser.add_argument(
        "--min-runs", type=float, default=0.0, help="exit 1 below this many runs per CPU-minute"
    )
    parser.add_argument("--jobs", action="store_true", help="--plan's seeds on 1 to all cores")
    parser.add_argument("--plan", default="killheavy", help="--jobs: the plan (default killheavy)")
    args = parser.parse_args()
    if args.jobs:
        on_every_core(args.plan, args.seeds)
        return
    if os.environ.get("PYTHONHASHSEED") != "0":  # (a sweep's hashes: start again under it)
        env = {**os.environ, "PYTHONHASHSEED": "0"}
        os.execve(sys.executable, [sys.executable, *sys.argv], env)  # noqa: S606
    first, _, last = args.seeds.partition("-")
    seeds = range(int(first), int(last or first) + 1)
    pinned = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "?"
    print(
        f"# simulation speed: Python {platform.python_version()}, greenlet "
        f"{greenlet.__version__}, {pinned} CPU(s) usable, load average "
        f"{os.getloadavg()[0]:.1f}; killheavy without its cut, seeds {args.seeds}"
    )
    switch = rate(greenlet_switches, 200_000, 3)
    step = rate(scheduler_steps, 20_000, 3)
    ask = rate(pykka_asks, 5_000, 3)
    print(f"floors: {switch:,.0f} greenlet switches/s, {step:,.0f} scheduler steps/s, ")
    print(f"        {ask:,.0f} pykka asks/s (real threads, of CPU)")
    with tempfile.TemporaryDirectory(prefix="rr-bench-sim-") as tmp:
        plan_path = killheavy_without_cut(Path(tmp))
        stacks: Counter[str] | None = Counter() if args.sample else None
        rows = simulated(plan_path, seeds, args.profile, stacks)
        real = None if args.no_real else real_run(plan_path)
    runs_per_minute = report(rows, real, (switch, step, ask))
    if stacks is not None and args.sample:
        print_samples(stacks, args.sample)
    if runs_per_minute < args.min_runs:
        sys.exit(f"below {args.min_runs:g} runs per CPU-minute: {runs_per_minute:.0f}")


if __name__ == "__main__":
    main()
