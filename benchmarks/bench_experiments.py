"""What the experiment machinery costs and how exact it is: two tables.

1. **Injector timing.** A tree of three process managers under load (four clients calling
   back to back through nested loads) while faults fire at seeded random times: SIGKILLs
   of random managers, SIGSTOPs (hangs) and connection cuts. For every injected fault:
   the time its signal was sent minus the time it was scheduled (`FaultRecord.late_s`),
   per kind and over all: median, p90, p99, max. Target: p99 under 5 ms. Twice: with the
   trigger process at real-time priority (where this user may: root or CAP_SYS_NICE)
   and at normal priority (`RR_ACTORS_NO_REALTIME=1`).

2. **Cost of recording events.** The same tree without faults, four clients, once with
   the run's subscription recording every event to `events.jsonl` and once without any
   subscriber (then manager processes do not even forward events). Two workloads:
   calling as fast as they can (`rate = "max"`, `hold = 0`: call then unload; the run
   process is saturated, the worst case), and a paced one (40 calls/s per client), where
   recording shows in the calls' latency rather than in their number. Rounds alternate
   the two settings, so noise from other programs spreads over both; the tables show each
   round and the median overhead. Target: under 10 % of the throughput.

    python benchmarks/bench_experiments.py                       # about 5 minutes
    python benchmarks/bench_experiments.py --runs 1 --rounds 2   # a quick look
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from typing import Any

import _harness

import rr_actors as rr
from rr_actors_lab.experiments import Plan, RunResult, parse_plan, run
from rr_actors_lab.experiments._trigger import NO_REALTIME
from rr_actors_lab.experiments.metrics import percentile

SERVICE = "rr_actors_lab.experiments.services:service"

TREE = f"""\
[tree]
max_restarts = 1000
period = 1.0

[[tree.children]]
name = "db"
setup = "{SERVICE}"

[[tree.children]]
name = "api"
setup = "{SERVICE}"
options = {{ uses = ["db"] }}
heartbeat = 0.1

[[tree.children]]
name = "cache"
setup = "{SERVICE}"
"""

TIMING = f"""\
name = "injector-timing"
duration = DURATION
seed = 1
{TREE}
[workload]
clients = 4
rate = "max"
hold = 0.0
timeout = 5.0

[[workload.calls]]
manager = "api"
server = "resource"
shared = 0.5

[[workload.calls]]
manager = "cache"
server = "resource"
shared = 0.9

[[faults]]
kind = "kill_manager"
target = ["db", "api", "cache"]
every = {{ min = 0.2, max = 0.4 }}

[[faults]]
kind = "hang_manager"
target = "cache"
every = {{ min = 1.0, max = 2.0 }}
for = 0.2

[[faults]]
kind = "cut_connections"
target = ["db", "api"]
every = {{ min = 0.5, max = 1.0 }}
"""

THROUGHPUT = f"""\
name = "recording-cost"
duration = DURATION
seed = 1
{TREE}
[workload]
clients = 4
rate = RATE
hold = 0.0

[[workload.calls]]
manager = "api"
server = "resource"
shared = 0.5
"""


def ms(value: float | None) -> str:
    return "-" if value is None else f"{value * 1e3:.2f}"


def timing(runs: int, duration: float, *, realtime: bool) -> None:
    plan: Plan = parse_plan(TIMING.replace("DURATION", repr(duration)))
    if realtime:
        os.environ.pop(NO_REALTIME, None)
    else:
        os.environ[NO_REALTIME] = "1"  # the run processes (and their trigger) inherit it
    try:
        results = run(plan, repeat=runs)
    finally:
        os.environ.pop(NO_REALTIME, None)
    late: dict[str, list[float]] = {}
    skipped = 0
    for _, fault in results.faults():
        if fault.late_s is None:
            skipped += 1
            continue
        late.setdefault(fault.kind, []).append(fault.late_s)
    every = [v for values in late.values() for v in values]
    policy = "real-time priority where allowed" if realtime else "normal priority"
    print(
        f"\n## Injector timing, trigger at {policy}: {runs} run(s) of {duration:g} s, "
        f"{len(every)} faults injected"
    )
    print(f"({skipped} skipped: their manager was being restarted when they were due)\n")
    print(
        _harness.table(
            ("fault kind", "injected", "median (ms)", "p90 (ms)", "p99 (ms)", "max (ms)"),
            [
                (kind, len(values), *(ms(percentile(values, q)) for q in (50, 90, 99)),
                 ms(max(values) if values else None))
                for kind, values in [*sorted(late.items()), ("all", every)]
            ],
        )
    )  # fmt: skip
    calls = sum(r.calls_ok for r in results.runs) / (runs * duration)
    print(f"\nload meanwhile: {calls:.0f} calls/s answered (all clients)")


def throughput(rounds: int, duration: float, rate: str) -> None:
    text = THROUGHPUT.replace("DURATION", repr(duration)).replace("RATE", rate)
    plan = parse_plan(text)
    rows: list[tuple[int, dict[bool, RunResult]]] = []
    for number in range(1, rounds + 1):
        pair: dict[bool, RunResult] = {}
        for record in (True, False) if number % 2 else (False, True):
            (pair[record],) = run(plan, record_events=record).runs
        rows.append((number, pair))
    print(f"\n## Cost of recording events, rate = {rate}: {rounds} round(s) of {duration:g} s\n")
    overheads, table = [], []
    for number, pair in rows:
        off, on = (calls_per_s(pair[r]) for r in (False, True))
        overheads.append(1.0 - on / off)
        table.append(
            (
                number, f"{off:.0f}", f"{on:.0f}", f"{overheads[-1]:+.1%}",
                latency(pair[False]), latency(pair[True]), pair[True].events,
            )
        )  # fmt: skip
    columns = (
        "round", "calls/s, not recorded", "calls/s, recorded", "overhead",
        "latency p50 / p99 (ms), not recorded", "recorded", "events",
    )  # fmt: skip
    print(_harness.table(columns, table, right=0))
    print(f"\nmedian overhead: {_harness.median(overheads):+.1%}")


def calls_per_s(result: RunResult) -> float:
    return result.calls_ok / result.duration_s


def latency(result: RunResult) -> str:
    times = [c.end_s - c.start_s for c in result.calls if c.ok]
    return f"{ms(percentile(times, 50))} / {ms(percentile(times, 99))}"


def _realtime_allowed() -> bool:
    """Whether a child of this process may take SCHED_FIFO (tried in a throwaway child)."""
    pid = os.fork()
    if pid == 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        except OSError:
            os._exit(1)
        os._exit(0)
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status) == 0


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3, help="runs of the timing table")
    parser.add_argument("--rounds", type=int, default=6, help="rounds of the recording table")
    parser.add_argument("--duration", type=float, default=8.0, help="seconds per run")
    parser.add_argument(
        "--only", choices=("timing", "recording"), default=None, help="only one of the tables"
    )
    args = parser.parse_args(argv)
    info: dict[str, Any] = {
        "python": platform.python_version(),
        "rr_actors": rr.__version__,
        "cpus": len(os.sched_getaffinity(0)),
    }
    print(f"# bench_experiments ({', '.join(f'{k} {v}' for k, v in info.items())})")
    if args.only in (None, "timing"):
        can = "can" if _realtime_allowed() else "cannot"
        print(f"\n(this process {can} take real-time priority: SCHED_FIFO)")
        timing(args.runs, args.duration, realtime=True)
        timing(args.runs, args.duration, realtime=False)
    if args.only in (None, "recording"):
        throughput(args.rounds, args.duration, '"max"')
        throughput(args.rounds, args.duration, "40.0")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
