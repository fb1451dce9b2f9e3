"""In-process dedup hits counted, not timed: CPU, instructions and Python bytecodes per operation.

Wall-clock timings on a shared machine are noise; what an operation costs is steadier.
A consumer registrar calls a provider registrar in the same process. Each operation is
counted on its own, between two marks:

    hit      a dedup-hit `call` (the request is loaded: a consumer id is added)
    unload   `unload` of one of those ids (not the last consumer: nothing is unloaded)
    pykka    a raw pykka ask to an echoing `ThreadingActor` (the floor)
    actor    the same ask to rr_actors' own actor type (the registrars are built on it)

`--count commits` counts SQLite commits instead, per hit, miss, unload and last unload,
on each side, with a durable consumer and provider, then with a plain consumer (`commits`).

How (`--count`):

* `cpu` (the default): the CPU time of every thread of the process and its context
  switches per operation (`getrusage`), in `--rounds` rounds of `--calls` of each
  operation in turn; the medians, and each over the pykka ask's (pin it for steadier
  figures: `taskset -c 0 python benchmarks/count_dedup.py`).
* `callgrind`: the script runs itself under `valgrind --tool=callgrind`, which dumps
  (and zeroes) its counters at each mark (`--dump-before=getsid`: a mark calls
  `os.getsid`); every operation runs `--calls` times, then three times as many, and
  the difference over the difference of the calls is what one costs, every thread,
  the same to a tenth of a percent run after run.
* `protocol`: durable registrars (`save_on_modify`, a backup each, in a temporary
  folder): the SQLite transactions (`SqliteStore.write`) and the messages the
  registrar actors handle (`RegistrarActor.on_receive`, by type; "inline": run in
  the actor's turn on the thread that brought it, no hand-off) per `hit`, per `miss`
  (a request not loaded: a load) and per `unload`, each `--calls` times.
* `bytecodes`: Python bytecodes executed per operation, every thread: `sys.settrace`
  and `threading.settrace` (installed before any actor starts) with each frame's
  `f_trace_opcodes` set count every `opcode` event; also the Python function calls per
  operation, and the distinct functions the operation ran (over its 3x phase). With
  `--profile`, each function run at least once per operation, by bytecodes (where the
  work is). Tracing slows the run some 20x; the counts do not depend on it.

Both counted modes run each operation `--calls` and three times `--calls` times and
print the difference over the difference (fixed costs cancel: the marks, the sync). A
hit's answer is recorded by the consumer's actor before its next message: every phase
ends with a message to that actor (`server_queries` of an empty server), so the hit's
record counts in the hit's phase. `--durable` (with `cpu`, `callgrind`, `bytecodes`)
gives both registrars a backup with `save_on_modify` (a temporary folder). `--user`
makes the request an instance of a user class (its `repr`, `==` and `hash` are user
code, run off the actor thread).

`--cross`: the consumer in this process calls a provider in a process of its own (the
AF_UNIX carrier, as `bench_transport.py` sets it up); rows `hit` and `unload`, counted in
each process: `cpu`, the CPU of every thread of both processes and their voluntary
context switches (thread wake-ups, from `/proc`); `callgrind`, followed into the
provider's process (it calls `getsid` at each mark when the control pipe asks it);
`bytecodes` (`--profile`), each process's.

Usage:
    python benchmarks/count_dedup.py [--calls 1000]
        [--count cpu|callgrind|bytecodes|protocol|commits] [--rounds 5] [--user] [--profile]
        [--durable] [--durability process|power] [--cross]
"""

from __future__ import annotations

import argparse
import collections
import glob
import itertools
import multiprocessing
import multiprocessing.connection
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import threading
import uuid
from collections.abc import Callable
from pathlib import Path
from types import CodeType, FrameType
from typing import Any

import _harness
from bench_core import ActorEcho, Echo
from bench_transport import _registrar_main, registrar_child, setup_echo

import rr_actors as rr
from rr_actors._registrar import Served
from rr_actors._transport.unix.system import System, SystemAddress

PACKAGE = Path(rr.__file__).resolve().parent
OPERATIONS = ("hit", "unload", "pykka", "actor")


class Camera:
    """A request of a user class."""

    def __init__(self, index: int) -> None:
        self.index = index

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Camera) and other.index == self.index

    def __hash__(self) -> int:
        return hash(self.index)

    def __repr__(self) -> str:
        return f"Camera({self.index})"


def _noop(*_: object) -> None:
    return None


# -- counting, in one process and across (`--cross`) ------------------------------------------


def where(code: CodeType) -> str:
    """A function's name for a table: its module inside rr_actors (or its file), line, name."""
    path = Path(code.co_filename)
    module = str(path.relative_to(PACKAGE.parent)) if path.is_relative_to(PACKAGE) else path.name
    return f"{module}:{code.co_firstlineno} {code.co_qualname}"


class Bytecodes:
    """Every Python bytecode executed and function called, on every thread started later."""

    def __init__(self) -> None:
        self._threads: list[tuple[collections.Counter[CodeType], collections.Counter[CodeType]]]
        self._threads = []
        self._local = threading.local()

    def start(self) -> None:
        threading.settrace(self._call)
        sys.settrace(self._call)

    def _call(self, frame: FrameType, event: str, _: Any) -> Any:
        mine = self._local.__dict__.get("mine")
        if mine is None:
            mine = self._local.mine = self._thread()
        calls, local = mine
        calls[frame.f_code] += 1
        frame.f_trace_opcodes = True
        frame.f_trace_lines = False
        return local

    def _thread(self) -> tuple[collections.Counter[CodeType], Callable[..., Any]]:
        """This thread's counters (no two threads race on one) and its frames' tracer."""
        ops: collections.Counter[CodeType] = collections.Counter()
        calls: collections.Counter[CodeType] = collections.Counter()
        self._threads.append((ops, calls))

        def local(frame: FrameType, event: str, _: Any) -> Any:
            if event == "opcode":
                ops[frame.f_code] += 1
            return local

        return calls, local

    def mark(self) -> dict[str, tuple[int, int]]:
        """Bytecodes and calls of each function since the last mark: {where: (ops, calls)}."""
        sys.settrace(None)  # (the mark itself not counted)
        seen: dict[str, tuple[int, int]] = {}
        for ops, calls in list(self._threads):
            taken_ops, taken_calls = dict(ops), dict(calls)
            ops.subtract(taken_ops)
            calls.subtract(taken_calls)
            for code in taken_ops.keys() | taken_calls.keys():
                name = where(code)
                was_ops, was_calls = seen.get(name, (0, 0))
                seen[name] = (
                    was_ops + taken_ops.get(code, 0),
                    was_calls + taken_calls.get(code, 0),
                )
        sys.settrace(self._call)
        return {name: counts for name, counts in seen.items() if counts != (0, 0)}


class Callgrind:
    """Marks for callgrind: it dumps and zeroes its counters when `getsid` is called."""

    def mark(self) -> None:
        os.getsid(0)


def callgrind_run(command: list[str], work: str) -> str:
    """Run `command` under callgrind (children followed), dumping at each mark; its stdout."""
    done = subprocess.run(
        [
            *("valgrind", "--tool=callgrind", "--trace-children=yes", "--dump-instr=no"),
            *("--dump-before=getsid", f"--callgrind-out-file={work}/cg.%p"),
            *command,
        ],
        env={**os.environ, "PYTHONHASHSEED": "0"},
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise RuntimeError(f"callgrind run failed:\n{done.stdout}\n{done.stderr[-3000:]}")
    return done.stdout


def phase_instructions(work: str, pid: int) -> list[int]:
    """The instructions of each phase of process `pid`: one per dump, in order."""
    totals = []
    for number in range(1, 1000):
        try:
            with open(f"{work}/cg.{pid}.{number}") as text:
                for line in text:
                    if line.startswith(("summary:", "totals:")):
                        totals.append(int(line.split()[1]))
                        break
        except FileNotFoundError:
            break
    return totals


def per_operation(first: float, second: float, calls: int) -> float:
    """What one operation costs, from a phase of `calls` and one of `3 * calls`."""
    return (second - first) / (2 * calls)


Counts = dict[str, tuple[int, int]]
"""What `Bytecodes.mark` returns: {function: (bytecodes, calls)} of one phase."""


def per_function(first: Counts, second: Counts, calls: int) -> dict[str, tuple[float, float]]:
    """Bytecodes and calls of each function per operation, from its two phases."""
    return {
        name: (
            per_operation(first.get(name, (0, 0))[0], second.get(name, (0, 0))[0], calls),
            per_operation(first.get(name, (0, 0))[1], second.get(name, (0, 0))[1], calls),
        )
        for name in first.keys() | second.keys()
    }


def bytecode_row(first: Counts, second: Counts, calls: int) -> tuple[float, float, int]:
    """Bytecodes, function calls per operation, and the distinct functions of its 3x phase."""
    functions = per_function(first, second, calls).values()
    return sum(f[0] for f in functions), sum(f[1] for f in functions), len(second)


def print_profile(title: str, first: Counts, second: Counts, calls: int) -> None:
    """The functions run at least once per operation, by bytecodes; then the modules."""
    functions = per_function(first, second, calls)
    print(f"\n{title}: bytecodes and calls per operation, by function")
    for name, (ops, made) in sorted(functions.items(), key=lambda kv: -kv[1][0]):
        if made >= 0.99:
            print(f"  {ops:7.1f} {made:5.1f}  {name}")
    modules: collections.Counter[str] = collections.Counter()
    for name, (ops, _) in functions.items():
        modules[name.split(":")[0]] += ops
    print(f"{title}: bytecodes per operation, by module")
    for module, ops in modules.most_common():
        if ops >= 0.5:
            print(f"  {ops:7.1f}  {module}")


# -- the operations ------------------------------------------------------------------------------


class Bench:
    """The registrars and actors every operation uses, started once."""

    def __init__(self, user: bool, *, durable: bool = False) -> None:
        self.echo = Echo.start()
        self.actor_echo = ActorEcho.start()
        self.folder = tempfile.TemporaryDirectory() if durable else None
        self.provider = rr.ResourceRegistrar.start(self.config("count-provider"))
        self.consumer = rr.ResourceRegistrar.start(self.config("count-consumer"))
        self.provider.register_server("res", load=lambda request: request, unload=_noop)
        self.consumer.register_server("idle", load=lambda request: request, unload=_noop)
        self.request: Any = Camera(1) if user else "shared"
        self.consumer.call(self.provider.name, "res", self.request)  # every call after: a hit
        self.ids: list[str] = []
        self.operations: dict[str, Callable[[], object]] = dict(
            zip(OPERATIONS, (self.hit, self.unload, self.pykka, self.actor), strict=True)
        )

    def config(self, name: str) -> rr.RegistrarConfig:
        """`name`'s configuration: with `--durable`, a backup with `save_on_modify`."""
        if self.folder is None:
            return rr.RegistrarConfig(name=name)
        backup = f"{self.folder.name}/{name}.db"
        return rr.RegistrarConfig(name=name, backup_path=backup, save_on_modify=True)

    def hit(self) -> None:
        self.ids.append(self.consumer.call(self.provider.name, "res", self.request).id)

    def unload(self) -> None:
        self.consumer.unload(self.ids.pop())

    def pykka(self) -> None:
        self.echo.ask("ping")

    def actor(self) -> None:
        self.actor_echo.ask("ping")

    def sync(self) -> None:
        """Return once the consumer's actor has handled what it was handed."""
        self.consumer.server_queries("idle")

    def stop(self) -> None:
        self.consumer.stop()
        self.provider.stop()
        self.echo.stop()
        self.actor_echo.stop()
        if self.folder is not None:
            self.folder.cleanup()


def phases(bench: Bench, calls: int, mark: Callable[[str], None]) -> None:
    """Each operation `calls` times, then each `3 * calls` times, a mark after each."""
    for count in (calls, 3 * calls):
        for name, operation in bench.operations.items():
            for _ in range(count):
                operation()
            bench.sync()
            mark(name)


def warm(bench: Bench) -> None:
    """Each operation a few times: threads, caches and clients made before counting."""
    for _ in range(2):
        for operation in bench.operations.values():
            for _ in range(50):
                operation()
    bench.sync()


def cpu(bench: Bench, calls: int, rounds: int) -> None:
    """CPU and context switches per operation, in rounds of each operation in turn."""
    samples: dict[str, list[tuple[float, float]]] = {name: [] for name in bench.operations}
    for _ in range(rounds):
        for name, operation in bench.operations.items():
            before = resource.getrusage(resource.RUSAGE_SELF)
            for _ in range(calls):
                operation()
            bench.sync()
            after = resource.getrusage(resource.RUSAGE_SELF)
            seconds = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
            switches = after.ru_nvcsw + after.ru_nivcsw - before.ru_nvcsw - before.ru_nivcsw
            samples[name].append((seconds / calls * 1e6, switches / calls))
    floor = statistics.median(s[0] for s in samples["pykka"])
    _harness.head(
        f"{rounds} rounds x {calls} of each operation, CPU of every thread, medians",
        ["operation", "CPU per op (us)", "context switches per op", "/ pykka ask"],
    )
    for name, rows in samples.items():
        us = statistics.median(s[0] for s in rows)
        switches = statistics.median(s[1] for s in rows)
        print(f"| {name} | {us:.1f} | {switches:.2f} | {us / floor:.2f}x |")


def commits(calls: int, durability: str) -> None:
    """SQLite commits per operation, one caller, a durable provider and a durable consumer.

    Both registrars have a backup with `save_on_modify`; commits are counted by wrapping
    the store's one write path (`SqliteStore._run`: a call is a transaction), so the count
    reads the same on any tree, on each side. Operations: a dedup hit, a miss (a new
    request: loaded), the unload of a hit's id (not the last consumer) and the last
    unload (the resource is unloaded). Then the same with a plain consumer (no backup:
    nothing on its side).
    """
    from rr_actors._store.saver import SqliteStore  # noqa: PLC0415 - a backup's store

    made: collections.Counter[str] = collections.Counter()
    run = SqliteStore._run

    def counted_run(store: Any, ops: Any) -> None:
        run(store, ops)
        made[Path(store.path).stem.split("-")[-1]] += 1

    SqliteStore._run = counted_run  # type: ignore[method-assign]
    tables = {"durable": side_commits(calls, durability, made, durable_consumer=True)}
    tables["plain"] = side_commits(calls, durability, made, durable_consumer=False)
    SqliteStore._run = run  # type: ignore[method-assign]
    _harness.head(
        f"SQLite commits per operation, one caller, durability={durability} ({calls} each)",
        ["operation", "commits", "provider", "consumer", "plain consumer: commits (its side)"],
    )
    for name, (provider, consumer) in tables["durable"].items():
        plain_p, plain_c = tables["plain"][name]
        print(
            f"| {name} | {provider + consumer:.2f} | {provider:.2f} | {consumer:.2f} "
            f"| {plain_p + plain_c:.2f} ({plain_c:.2f}) |"
        )


def side_commits(
    calls: int, durability: str, made: collections.Counter[str], *, durable_consumer: bool
) -> dict[str, tuple[float, float]]:
    """Each operation's commits per call: (the provider's, the consumer's)."""
    with tempfile.TemporaryDirectory() as work:

        def start(name: str, *, durable: bool = True) -> rr.ResourceRegistrar:
            if not durable:
                return rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name))
            return rr.ResourceRegistrar.start(
                rr.RegistrarConfig(
                    name=name,
                    backup_path=Path(work, f"{name}.db"),
                    save_on_modify=True,
                    durability=durability,  # type: ignore[arg-type]
                )
            )

        provider = start("commits-provider")
        consumer = start("commits-consumer", durable=durable_consumer)
        provider.register_server("res", load=lambda request: request, unload=_noop)
        consumer.call(provider.name, "res", "shared")  # held: every call of it after, a hit
        hits: list[str] = []
        misses: list[str] = []
        fresh = iter(range(10**9))
        operations: dict[str, Callable[[], object]] = {
            "hit": lambda: hits.append(consumer.call(provider.name, "res", "shared").id),
            "miss": lambda: misses.append(consumer.call(provider.name, "res", next(fresh)).id),
            "unload": lambda: consumer.unload(hits.pop()),
            "last unload": lambda: consumer.unload(misses.pop()),
        }
        rows = {}
        for name, operation in operations.items():
            provider.server_queries("res")  # (a round trip to each: nothing left over)
            consumer.client_queries()
            made.clear()
            for _ in range(calls):
                operation()
            provider.server_queries("res")
            consumer.client_queries()
            rows[name] = (made["provider"] / calls, made["consumer"] / calls)
        consumer.stop()
        provider.stop()
    return rows


def counted(args: argparse.Namespace) -> None:
    """The run under a counter (inside valgrind, or traced): its phases, marked."""
    bytecodes = Bytecodes() if args.count == "bytecodes" else None
    if bytecodes is not None:
        bytecodes.start()  # (before the actors start: their threads inherit it)
    marker: Callgrind | Bytecodes = bytecodes or Callgrind()
    marks: list[Counts] = []
    bench = Bench(args.user, durable=args.durable)
    try:
        warm(bench)
        marker.mark()
        phases(bench, args.calls, lambda _: marks.append(marker.mark() or {}))
    finally:
        sys.settrace(None)
        threading.settrace(None)  # type: ignore[arg-type]
        bench.stop()
    if bytecodes is None:
        return
    n = len(OPERATIONS)
    _harness.head(
        f"Python bytecodes per operation, every thread ({args.calls} and {3 * args.calls})",
        ["operation", "bytecodes", "function calls", "distinct functions"],
    )
    for name, first, second in zip(OPERATIONS, marks[:n], marks[n:], strict=True):
        ops, made, distinct = bytecode_row(first, second, args.calls)
        print(f"| {name} | {ops:.0f} | {made:.1f} | {distinct} |")
    if args.profile:
        for name, first, second in zip(OPERATIONS, marks[:n], marks[n:], strict=True):
            print_profile(name, first, second, args.calls)


def callgrind(args: argparse.Namespace) -> None:
    """Run this script under callgrind; print the instructions per operation."""
    command = [sys.executable, str(Path(__file__).resolve()), "--calls", str(args.calls)]
    command += ["--count", "inside-callgrind", *(["--user"] if args.user else [])]
    command += ["--durable"] if args.durable else []
    with tempfile.TemporaryDirectory() as work:
        stdout = callgrind_run(command, work)
        found = re.search(r"^PID (\d+)$", stdout, re.MULTILINE)
        if found is None:
            raise RuntimeError(f"no pid in the output:\n{stdout}")
        totals = phase_instructions(work, int(found.group(1)))[1:]  # (the first: the start)
    n = len(OPERATIONS)
    if len(totals) != 2 * n:
        raise RuntimeError(f"{len(totals)} phases counted, not {2 * n}")
    per = {
        name: per_operation(first, second, args.calls)
        for name, first, second in zip(OPERATIONS, totals[:n], totals[n:], strict=True)
    }
    _harness.head(
        f"instructions per operation, every thread ({args.calls} and {3 * args.calls})",
        ["operation", "instructions", "/ pykka ask"],
    )
    for name, count in per.items():
        print(f"| {name} | {count / 1e3:.1f}k | {count / per['pykka']:.2f}x |")


def protocol_row(
    name: str, calls: int, writes: collections.Counter[str], handled: collections.Counter[str]
) -> str:
    """One operation's row of `protocol`'s table: per operation."""
    kinds = ", ".join(f"{k} {n / calls:g}" for k, n in sorted(handled.items()))
    total = sum(handled.values()) / calls
    queued = sum(n for k, n in handled.items() if not k.endswith("(inline)")) / calls
    commits = sum(writes.values()) / calls
    return f"| {name} | {commits:g} | {total:g} | {queued:g} | {kinds} |"


def protocol(calls: int) -> None:
    """Commits and registrar actor messages per hit, miss and unload, durable registrars."""
    from rr_actors._registrar.actor import RegistrarActor  # noqa: PLC0415
    from rr_actors._store.saver import SqliteStore  # noqa: PLC0415

    writes: collections.Counter[str] = collections.Counter()
    handled: collections.Counter[str] = collections.Counter()
    write, receive = SqliteStore.write, RegistrarActor.on_receive

    def counted_write(store: Any, *args: Any, **kwargs: Any) -> None:
        writes[str(Path(store.path).stem)] += 1
        write(store, *args, **kwargs)

    def counted_receive(actor: Any, message: Any) -> None:
        # on the actor's own thread: it came through its mailbox (a thread hand-off);
        # else a carrier's or an actor's thread ran it in the actor's turn (`deliver`)
        inline = threading.current_thread() is not threads.get(id(actor))
        handled[f"{actor.name}: {type(message).__name__}{' (inline)' if inline else ''}"] += 1
        receive(actor, message)

    threads: dict[int, threading.Thread] = {}  # each registrar actor's own thread
    start = RegistrarActor.on_start

    def on_start(actor: Any) -> None:
        threads[id(actor)] = threading.current_thread()
        start(actor)

    SqliteStore.write = counted_write  # type: ignore[method-assign]
    RegistrarActor.on_receive = counted_receive  # type: ignore[method-assign]
    RegistrarActor.on_start = on_start  # type: ignore[method-assign]
    with tempfile.TemporaryDirectory() as folder:
        configs = [
            rr.RegistrarConfig(name=name, backup_path=f"{folder}/{name}.db", save_on_modify=True)
            for name in ("count-provider", "count-consumer")
        ]
        provider, consumer = (rr.ResourceRegistrar.start(c) for c in configs)
        try:
            provider.register_server("res", load=lambda request: request, unload=_noop)
            consumer.register_server("idle", load=lambda request: request, unload=_noop)
            consumer.call(provider.name, "res", "shared")
            ids: list[str] = []
            misses = itertools.count()
            operations: dict[str, Callable[[], object]] = {
                "hit": lambda: ids.append(consumer.call(provider.name, "res", "shared").id),
                "unload": lambda: consumer.unload(ids.pop()),
                "miss": lambda: consumer.call(provider.name, "res", f"new {next(misses)}"),
            }
            print(f"durable registrars, {calls} of each operation: per operation")
            print("| operation | commits | registrar messages | through a mailbox | by type |")
            print("|---|---:|---:|---:|---|")
            for name, operation in operations.items():
                consumer.server_queries("idle")  # (what came before is handled)
                writes.clear()
                handled.clear()
                for _ in range(calls):
                    operation()
                consumer.server_queries("idle")
                handled.pop("count-consumer: ListServerQueries", None)
                print(protocol_row(name, calls, writes, handled))
        finally:
            consumer.stop()
            provider.stop()
            SqliteStore.write = write  # type: ignore[method-assign]
            RegistrarActor.on_receive = receive  # type: ignore[method-assign]
            RegistrarActor.on_start = start  # type: ignore[method-assign]


# -- across processes (`--cross`) ---------------------------------------------------------


CROSS_OPERATIONS = ("hit", "unload")


def _threads(pid: int) -> tuple[float, int]:
    """CPU seconds and voluntary context switches so far of every thread of `pid`."""
    cpu, switches = 0.0, 0
    for task in glob.glob(f"/proc/{pid}/task/*"):
        try:
            with open(f"{task}/schedstat") as stat:
                cpu += int(stat.read().split()[0]) / 1e9
            with open(f"{task}/status") as status:
                for line in status:
                    if line.startswith("voluntary_ctxt_switches"):
                        switches += int(line.split()[1])
        except OSError:  # (a thread that ended meanwhile)
            continue
    return cpu, switches


class CrossCPU:
    """Marks for `--count cpu`: every thread's CPU and wake-ups so far, of both processes."""

    def __init__(self, pids: tuple[int, int]) -> None:
        self.pids = pids

    def mark(self) -> list[tuple[float, int]]:
        return [_threads(pid) for pid in self.pids]


def _cross_provider(
    address: SystemAddress,
    name: str,
    setup: bytes,
    control: multiprocessing.connection.Connection,
    count: str,
) -> None:
    """The provider's process: its counter started first, each mark answered with it."""
    marker: Bytecodes | Callgrind | None = None
    if count == "bytecodes":
        marker = Bytecodes()
        marker.start()
    elif count == "inside-callgrind":
        marker = Callgrind()
    _registrar_main(address, name, setup, control, lambda _: marker and marker.mark())


def _cross_config(name: str, folder: str | None) -> rr.RegistrarConfig:
    """`name`'s configuration: with a `folder` (`--durable`), a backup there with
    `save_on_modify`."""
    if folder is None:
        return rr.RegistrarConfig(name=name)
    backup = Path(folder, f"{name}.db")
    return rr.RegistrarConfig(name=name, backup_path=backup, save_on_modify=True)


def cross_run(calls: int, count: str, durable: bool = False) -> list[Any]:
    """Each operation `calls` times, then `3 * calls` times: the marks of both processes."""
    with tempfile.TemporaryDirectory() as folder:
        return _cross_run(calls, count, folder if durable else None)


def _cross_run(calls: int, count: str, folder: str | None) -> list[Any]:
    ctx = multiprocessing.get_context("forkserver")
    own: Bytecodes | Callgrind | CrossCPU | None = None
    if count == "bytecodes":
        own = Bytecodes()
        own.start()  # (before any thread starts)
    system = System.create()
    marks: list[Any] = []
    try:
        consumer = rr.ResourceRegistrar.start(
            _cross_config(f"count-{uuid.uuid4().hex[:6]}", folder)
        )
        consumer.register_server("idle", load=lambda request: request, unload=lambda *_: None)
        system.serve(Served(consumer))
        provider = f"provider-{uuid.uuid4().hex[:6]}"
        try:
            with registrar_child(
                ctx,
                system.address,
                _cross_config(provider, folder),
                setup_echo,
                target=_Target(count),
                started=900,  # (under valgrind on a loaded machine, minutes)
            ) as (process, control):
                assert process.pid is not None
                ids = [consumer.call(provider, "echo", {"cam": 1}).id for _ in range(200)]
                for query_id in ids[100:]:
                    consumer.unload(query_id)
                print(f"PIDS {os.getpid()} {process.pid}", flush=True)
                if count == "cpu":
                    own = CrossCPU((os.getpid(), process.pid))
                elif count == "inside-callgrind":
                    own = Callgrind()

                def mark() -> None:
                    consumer.server_queries("idle")  # (the consumer's actor caught up)
                    control.send("mark")
                    theirs = control.recv()
                    marks.append((own.mark() if own else None, theirs))

                mark()
                for size in (calls, 3 * calls):
                    made = [consumer.call(provider, "echo", {"cam": 1}).id for _ in range(size)]
                    mark()
                    for query_id in made:
                        consumer.unload(query_id)
                    mark()
                for query_id in ids[:100]:
                    consumer.unload(query_id)
        finally:
            consumer.stop()
    finally:
        if count == "bytecodes":
            sys.settrace(None)
        system.close()
    return marks


class _Target:
    """The provider process's target, with the count it runs under (picklable)."""

    def __init__(self, count: str) -> None:
        self.count = count

    def __call__(self, *args: Any) -> None:
        _cross_provider(*args, count=self.count)


def cross_cpu(calls: int, durable: bool) -> None:
    marks = cross_run(calls, "cpu", durable)
    print(
        f"CPU per operation, every thread of both processes ({calls} and {3 * calls})"
        + (", durable" if durable else "")
    )
    _harness.head(None, ["operation", "CPU (us)", "wake-ups"])
    totals = [(sum(p[0] for p in own), sum(p[1] for p in own)) for own, _ in marks]
    phases = [
        (b[0] - a[0], b[1] - a[1]) for a, b in itertools.pairwise(totals)
    ]  # (cpu, wake-ups) of each phase: hit, unload, hit, unload
    for index, name in enumerate(CROSS_OPERATIONS):
        first, second = phases[index], phases[index + 2]
        us = per_operation(first[0], second[0], calls) * 1e6
        wakes = per_operation(first[1], second[1], calls)
        print(f"| {name} | {us:.1f} | {wakes:.2f} |")


def cross_bytecodes(calls: int, profile: bool, durable: bool) -> None:
    marks = cross_run(calls, "bytecodes", durable)[1:]  # (the first: the warm-up's)
    _harness.head(
        f"Python bytecodes per operation, every thread ({calls} and {3 * calls})",
        ["operation", "process", "bytecodes", "function calls", "distinct functions"],
        right=2,
    )
    for index, name in enumerate(CROSS_OPERATIONS):
        (own_1, theirs_1), (own_3, theirs_3) = marks[index], marks[index + 2]
        rows = [bytecode_row(own_1, own_3, calls), bytecode_row(theirs_1, theirs_3, calls)]
        for process, row in zip(("caller's", "provider's"), rows, strict=True):
            print(f"| {name} | {process} | {row[0]:.0f} | {row[1]:.1f} | {row[2]} |")
        both = [sum(column) for column in zip(*rows, strict=True)]
        print(f"| {name} | both | {both[0]:.0f} | {both[1]:.1f} | {both[2]} |")
    if profile:
        for index, name in enumerate(CROSS_OPERATIONS):
            (own_1, theirs_1), (own_3, theirs_3) = marks[index], marks[index + 2]
            print_profile(f"{name}, caller's process", own_1, own_3, calls)
            print_profile(f"{name}, provider's process", theirs_1, theirs_3, calls)


def cross_callgrind(calls: int, durable: bool) -> None:
    """Run `run` under callgrind; print the instructions per operation of each process."""
    command = [sys.executable, str(Path(__file__).resolve()), "--calls", str(calls)]
    command += ["--durable"] if durable else []
    with tempfile.TemporaryDirectory() as work:
        stdout = callgrind_run([*command, "--cross", "--count", "inside-callgrind"], work)
        found = re.search(r"^PIDS (\d+) (\d+)$", stdout, re.MULTILINE)
        if found is None:
            raise RuntimeError(f"no pids in the output:\n{stdout}")
        phases = [phase_instructions(work, int(pid))[1:] for pid in found.groups()]
    if any(len(each) != 4 for each in phases):  # (after the start, to the warm-up's mark)
        raise RuntimeError(f"phases counted: {[len(each) for each in phases]}, not 4 each")
    durably = ", durable" if durable else ""
    _harness.head(
        f"instructions per operation ({calls} and {3 * calls} operations{durably})",
        ["operation", "caller's process", "provider's process", "both"],
    )
    for index, name in enumerate(CROSS_OPERATIONS):
        per = [per_operation(each[index], each[index + 2], calls) for each in phases]
        print(f"| {name} | {per[0] / 1e3:.1f}k | {per[1] / 1e3:.1f}k | {sum(per) / 1e3:.1f}k |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=1000, help="operations (default 1000)")
    parser.add_argument(
        "--count",
        choices=["cpu", "callgrind", "bytecodes", "inside-callgrind", "protocol", "commits"],
        default="cpu",
    )
    parser.add_argument("--durability", choices=["process", "power"], default="process")
    parser.add_argument("--rounds", type=int, default=5, help="rounds of --count cpu")
    parser.add_argument("--user", action="store_true", help="a request of a user class")
    parser.add_argument("--profile", action="store_true", help="bytecodes by function")
    parser.add_argument(
        "--durable", action="store_true", help="registrars with backups (save_on_modify)"
    )
    parser.add_argument("--cross", action="store_true", help="the provider in a process of its own")
    args = parser.parse_args()
    if args.profile:
        args.count = "bytecodes"
    if args.cross and args.count == "callgrind":
        cross_callgrind(args.calls, args.durable)
    elif args.cross and args.count == "cpu":
        cross_cpu(args.calls, args.durable)
    elif args.cross and args.count == "bytecodes":
        cross_bytecodes(args.calls, args.profile, args.durable)
    elif args.cross:
        cross_run(args.calls, args.count, args.durable)
    elif args.count == "commits":
        commits(args.calls, args.durability)
    elif args.count == "callgrind":
        callgrind(args)
    elif args.count == "protocol":
        protocol(args.calls)
    elif args.count == "cpu":
        bench = Bench(args.user, durable=args.durable)
        try:
            warm(bench)
            cpu(bench, args.calls, args.rounds)
        finally:
            bench.stop()
    else:
        if args.count == "inside-callgrind":
            print(f"PID {os.getpid()}", flush=True)
        counted(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
