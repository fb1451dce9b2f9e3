"""Cross-process dedup hits counted, not timed: CPU, instructions and bytecodes per call.

On a shared machine a wall-clock median moves by a tenth between two runs of the same
code; what a change buys a cross-process call is easier to see in what the call costs.
A consumer registrar in this process calls a provider registrar in a process of its own
(the AF_UNIX carrier, as `bench_transport.py` sets it up). Two operations, each counted
on its own between two marks (both rows are always printed):

    hit      a dedup-hit `call` (the request is loaded: a consumer id is added)
    unload   `unload` of one of those ids (not the last consumer: nothing is unloaded)

How (`--count`):

* `cpu` (the default): the CPU time of every thread of both processes per operation,
  and the voluntary context switches (thread wake-ups), from `/proc` (Linux). Pin it
  for steadier figures: `taskset -c 0 python benchmarks/count_cross.py`.
* `callgrind`: the script runs itself under `valgrind --tool=callgrind`, following the
  provider into its process; callgrind dumps (and zeroes) a process's counters when it
  calls `getsid` (`--dump-before=getsid`), which each process does at each mark (the
  provider when the control pipe asks it). Each operation runs `--calls` times, then
  three times as many; the difference over the difference of the calls is what one
  costs in each process, the same to a tenth of a percent run after run. Instructions
  do not count the kernel's work (a thread wake-up is mostly that).
* `bytecodes`: the Python bytecodes executed per operation in each process, every
  thread (`sys.settrace`/`threading.settrace` with `f_trace_opcodes`, installed before
  any thread starts, in the provider's process too: see `count_dedup.Bytecodes`); the
  Python function calls, and the distinct functions run over the 3x phase. With
  `--profile`, each process's functions and modules by bytecodes per operation.

A plain call's answer is recorded by the consumer's actor before its next message:
every phase ends with a message to that actor (`server_queries` of an empty server),
so the record counts in the hit's phase; the marks and that message are fixed costs,
which the difference cancels.

`--durable` gives both registrars a backup with `save_on_modify` (each in a temporary
folder), as a supervisor's managers have: a hit then also costs the commits of both
sides (`count_dedup.py --count commits` counts them).

Usage:
    python benchmarks/count_cross.py [--calls 2000] [--count cpu|callgrind|bytecodes]
        [--profile] [--durable]
"""

from __future__ import annotations

import argparse
import glob
import itertools
import multiprocessing
import multiprocessing.connection
import os
import re
import sys
import tempfile
import uuid
from pathlib import Path
from typing import Any

from bench_transport import _registrar_main, registrar_child, setup_echo
from count_dedup import (
    Bytecodes,
    Callgrind,
    bytecode_row,
    callgrind_run,
    per_operation,
    phase_instructions,
    print_profile,
)

import rr_actors as rr
from rr_actors._registrar import Served
from rr_actors._transport.unix.system import System, SystemAddress

OPERATIONS = ("hit", "unload")


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


class CPU:
    """Marks for `--count cpu`: every thread's CPU and wake-ups so far, of both processes."""

    def __init__(self, pids: tuple[int, int]) -> None:
        self.pids = pids

    def mark(self) -> list[tuple[float, int]]:
        return [_threads(pid) for pid in self.pids]


def _provider(
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


def _config(name: str, folder: str | None) -> rr.RegistrarConfig:
    """`name`'s configuration: with a `folder` (`--durable`), a backup there with
    `save_on_modify`."""
    if folder is None:
        return rr.RegistrarConfig(name=name)
    backup = Path(folder, f"{name}.db")
    return rr.RegistrarConfig(name=name, backup_path=backup, save_on_modify=True)


def run(calls: int, count: str, durable: bool = False) -> list[Any]:
    """Each operation `calls` times, then `3 * calls` times: the marks of both processes."""
    with tempfile.TemporaryDirectory() as folder:
        return _run(calls, count, folder if durable else None)


def _run(calls: int, count: str, folder: str | None) -> list[Any]:
    ctx = multiprocessing.get_context("forkserver")
    own: Bytecodes | Callgrind | CPU | None = None
    if count == "bytecodes":
        own = Bytecodes()
        own.start()  # (before any thread starts)
    system = System.create()
    marks: list[Any] = []
    try:
        consumer = rr.ResourceRegistrar.start(_config(f"count-{uuid.uuid4().hex[:6]}", folder))
        consumer.register_server("idle", load=lambda request: request, unload=lambda *_: None)
        system.serve(Served(consumer))
        provider = f"provider-{uuid.uuid4().hex[:6]}"
        try:
            with registrar_child(
                ctx,
                system.address,
                _config(provider, folder),
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
                    own = CPU((os.getpid(), process.pid))
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
        _provider(*args, count=self.count)


def cpu(calls: int, durable: bool) -> None:
    marks = run(calls, "cpu", durable)
    print(
        f"CPU per operation, every thread of both processes ({calls} and {3 * calls})"
        + (", durable" if durable else "")
    )
    print("| operation | CPU (us) | wake-ups |")
    print("|---|---:|---:|")
    totals = [(sum(p[0] for p in own), sum(p[1] for p in own)) for own, _ in marks]
    phases = [
        (b[0] - a[0], b[1] - a[1]) for a, b in itertools.pairwise(totals)
    ]  # (cpu, wake-ups) of each phase: hit, unload, hit, unload
    for index, name in enumerate(OPERATIONS):
        first, second = phases[index], phases[index + 2]
        us = per_operation(first[0], second[0], calls) * 1e6
        wakes = per_operation(first[1], second[1], calls)
        print(f"| {name} | {us:.1f} | {wakes:.2f} |")


def bytecodes(calls: int, profile: bool, durable: bool) -> None:
    marks = run(calls, "bytecodes", durable)[1:]  # (the first: the warm-up's)
    print(f"Python bytecodes per operation, every thread ({calls} and {3 * calls})")
    print("| operation | process | bytecodes | function calls | distinct functions |")
    print("|---|---|---:|---:|---:|")
    for index, name in enumerate(OPERATIONS):
        (own_1, theirs_1), (own_3, theirs_3) = marks[index], marks[index + 2]
        rows = [bytecode_row(own_1, own_3, calls), bytecode_row(theirs_1, theirs_3, calls)]
        for process, row in zip(("caller's", "provider's"), rows, strict=True):
            print(f"| {name} | {process} | {row[0]:.0f} | {row[1]:.1f} | {row[2]} |")
        both = [sum(column) for column in zip(*rows, strict=True)]
        print(f"| {name} | both | {both[0]:.0f} | {both[1]:.1f} | {both[2]} |")
    if profile:
        for index, name in enumerate(OPERATIONS):
            (own_1, theirs_1), (own_3, theirs_3) = marks[index], marks[index + 2]
            print_profile(f"{name}, caller's process", own_1, own_3, calls)
            print_profile(f"{name}, provider's process", theirs_1, theirs_3, calls)


def callgrind(calls: int, durable: bool) -> None:
    """Run `run` under callgrind; print the instructions per operation of each process."""
    command = [sys.executable, str(Path(__file__).resolve()), "--calls", str(calls)]
    command += ["--durable"] if durable else []
    with tempfile.TemporaryDirectory() as work:
        stdout = callgrind_run([*command, "--count", "inside-callgrind"], work)
        found = re.search(r"^PIDS (\d+) (\d+)$", stdout, re.MULTILINE)
        if found is None:
            raise RuntimeError(f"no pids in the output:\n{stdout}")
        phases = [phase_instructions(work, int(pid))[1:] for pid in found.groups()]
    if any(len(each) != 4 for each in phases):  # (after the start, to the warm-up's mark)
        raise RuntimeError(f"phases counted: {[len(each) for each in phases]}, not 4 each")
    durably = ", durable" if durable else ""
    print(f"instructions per operation ({calls} and {3 * calls} operations{durably})")
    print("| operation | caller's process | provider's process | both |")
    print("|---|---:|---:|---:|")
    for index, name in enumerate(OPERATIONS):
        per = [per_operation(each[index], each[index + 2], calls) for each in phases]
        print(f"| {name} | {per[0] / 1e3:.1f}k | {per[1] / 1e3:.1f}k | {sum(per) / 1e3:.1f}k |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=2000, help="dedup hits (default 2000)")
    parser.add_argument(
        "--count", choices=["cpu", "callgrind", "bytecodes", "inside-callgrind"], default="cpu"
    )
    parser.add_argument("--profile", action="store_true", help="bytecodes by function")
    parser.add_argument(
        "--durable", action="store_true", help="both registrars with a backup, save_on_modify"
    )
    args = parser.parse_args()
    if args.profile:
        args.count = "bytecodes"
    if args.count == "callgrind":
        callgrind(args.calls, args.durable)
    elif args.count == "cpu":
        cpu(args.calls, args.durable)
    elif args.count == "bytecodes":
        bytecodes(args.calls, args.profile, args.durable)
    else:
        run(args.calls, args.count, args.durable)
    return 0


if __name__ == "__main__":
    sys.exit(main())
