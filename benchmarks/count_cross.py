"""Cross-process dedup hits counted, not timed: CPU per call, or instructions per call.

On a shared machine a wall-clock median moves by a tenth between two runs of the same
code; what a change buys a cross-process call is easier to see in what the call costs.
A consumer registrar in this process calls a provider registrar in a process of its own
(the AF_UNIX carrier, as `bench_transport.py` sets it up), `--calls` dedup hits in a loop:

* plain: the CPU time of every thread of both processes per call, and the voluntary
  context switches (thread wake-ups) per call, from `/proc` (Linux);
* `--callgrind`: the script runs itself twice under `valgrind --tool=callgrind`
  (following the provider into its process), with `--calls` and three times as many,
  and prints the difference over the difference of the calls: the instructions one
  call costs in each process, the same to a tenth of a percent run after run.

Pin it for steadier CPU figures: `taskset -c 0 python benchmarks/count_cross.py`.
Instructions do not count the kernel's work (a thread wake-up is mostly that), so a
change that removes a hand-off shows in the CPU figure more than in instructions.

Usage:
    python benchmarks/count_cross.py [--calls 2000] [--callgrind]
"""

from __future__ import annotations

import argparse
import glob
import multiprocessing
import os
import re
import subprocess
import sys
import tempfile
import uuid
from pathlib import Path

from bench_transport import registrar_process, setup_echo

import rr_actors as rr
from rr_actors._registrar import Served
from rr_actors._transport.unix.system import System


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


def run(calls: int) -> None:
    """`calls` dedup hits across processes; print both pids, then what they cost."""
    ctx = multiprocessing.get_context("forkserver")
    system = System.create()
    try:
        consumer = rr.ResourceRegistrar.start(f"count-{uuid.uuid4().hex[:6]}")
        system.serve(Served(consumer))
        provider = f"provider-{uuid.uuid4().hex[:6]}"
        try:
            with registrar_process(ctx, system.address, provider, setup_echo) as process:
                assert process.pid is not None
                ids = [consumer.call(provider, "echo", {"cam": 1}).id for _ in range(200)]
                print(f"PIDS {os.getpid()} {process.pid}", flush=True)
                pids = (os.getpid(), process.pid)
                before = [_threads(pid) for pid in pids]
                ids += [consumer.call(provider, "echo", {"cam": 1}).id for _ in range(calls)]
                after = [_threads(pid) for pid in pids]
                for query_id in ids:
                    consumer.unload(query_id)
        finally:
            consumer.stop()
    finally:
        system.close()
    cpu = sum(a[0] - b[0] for a, b in zip(after, before, strict=True)) / calls * 1e6
    wakes = sum(a[1] - b[1] for a, b in zip(after, before, strict=True)) / calls
    print(f"{calls} cross-process dedup hits")
    print(f"per call: {cpu:.1f} us of CPU (every thread of both processes), {wakes:.2f} wake-ups")


def _instructions(out: str) -> int:
    """The total instructions of one callgrind output file."""
    with open(out) as text:
        for line in text:
            if line.startswith(("summary:", "totals:")):
                return int(line.split()[1])
    raise RuntimeError(f"no total in {out}")


def callgrind(calls: int) -> None:
    """Run `run` under callgrind for `calls` and 3x `calls`; print instructions per call."""
    totals = []
    with tempfile.TemporaryDirectory() as work:
        for count in (calls, 3 * calls):
            done = subprocess.run(
                [
                    *("valgrind", "--tool=callgrind", "--trace-children=yes"),
                    f"--callgrind-out-file={work}/{count}.%p",
                    *(sys.executable, str(Path(__file__).resolve()), "--calls", str(count)),
                ],
                env={**os.environ, "PYTHONHASHSEED": "0"},
                capture_output=True,
                text=True,
                check=True,
            )
            found = re.search(r"^PIDS (\d+) (\d+)$", done.stdout, re.MULTILINE)
            if found is None:
                raise RuntimeError(f"no pids in the output:\n{done.stdout}\n{done.stderr}")
            totals.append([_instructions(f"{work}/{count}.{pid}") for pid in found.groups()])
    per = [(b - a) / (2 * calls) for a, b in zip(totals[0], totals[1], strict=True)]
    print(f"instructions per cross-process dedup hit ({calls} and {3 * calls} calls):")
    print(f"  caller's process {per[0] / 1e3:.1f}k, provider's process {per[1] / 1e3:.1f}k,")
    print(f"  both {sum(per) / 1e3:.1f}k")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=2000, help="dedup hits (default 2000)")
    parser.add_argument(
        "--callgrind", action="store_true", help="instructions per call, under valgrind"
    )
    args = parser.parse_args()
    if args.callgrind:
        callgrind(args.calls)
    else:
        run(args.calls)
    return 0


if __name__ == "__main__":
    sys.exit(main())
