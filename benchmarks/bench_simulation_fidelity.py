"""Fidelity of the simulation: does a seed give the same history every time, everywhere?

    python benchmarks/bench_simulation_fidelity.py --seeds 1-10            # 2 x 10 runs a seed
    python benchmarks/bench_simulation_fidelity.py --seeds 1-10 --busy 2   # beside 2 busy loops

Issue 42's fidelity figure: the same seed gives the same history hash in 10 runs out of
10, in two different processes. The plan is the shipped `killheavy` without its
`cut_connections` fault (not simulated yet; `--plan` runs another): a chain
edge -> api -> db of manager processes, 4 clients, about 600 calls and 20 SIGKILLs in 6
virtual seconds.

`--processes` (2) processes start at once, each under `PYTHONHASHSEED=0` (as a sweep
runs), and each runs every seed `--runs` (10) times: run 1 of every seed, then run 2,
and so on (`simulate.run_seed`, what `rr-actors experiment --simulate` runs per seed).
They differ on purpose in what a simulated run must not depend on:

- the heap: before each run a process allocates a few thousand objects of random sizes
  and keeps them (`--no-shake`: not), so the objects of a run lie at other addresses
  from run to run and from process to process, and anything ordered by address (a set
  of callbacks, `id()`) comes in another order;
- the garbage collector: the second process collects 7 times as often (threshold 100,
  not 700) between runs (while a run runs, the simulation collects on its own
  schedule: `GC_STEPS`);
- real time: `--busy N` processes that only spin run beside them, so the OS preempts
  the simulation's thread at other moments and every real-time wait differs.

Printed: per seed, how many of its runs gave its most common hash and how many distinct
hashes it gave (with `--against`, whether that hash is the one a sweep recorded in its
`seeds.jsonl`), then the total: runs that matched out of runs made. The histories of
seeds that gave more than one are written to `--keep DIR` (one file per hash) to diff.
Exits 1 if a seed gave two histories (or not the recorded one).
"""

from __future__ import annotations

import argparse
import collections
import datetime
import gc
import json
import logging
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import _harness
from bench_simulation import killheavy_without_cut

HASH_SEED = "0"
"""The `PYTHONHASHSEED` of a sweep (`rr-actors experiment --simulate`)."""

GC_THRESHOLDS = (None, 100)
"""Each process's gc threshold of the youngest generation (`None`: CPython's 700)."""


def parse_seeds(text: str) -> list[int]:
    """`1-10` or `1,4,7` (or both: `1-3,9`)."""
    seeds: list[int] = []
    for part in text.split(","):
        first, _, last = part.partition("-")
        seeds.extend(range(int(first), int(last or first) + 1))
    return seeds


def shake(rng: random.Random, kept: list[Any]) -> None:
    """Allocate objects of many sizes and keep them: the heap's free slots move."""
    for _ in range(rng.randrange(1, 5_000)):
        kind = rng.randrange(4)
        if kind == 0:
            kept.append(lambda: None)
        elif kind == 1:
            kept.append([0] * rng.randrange(64))
        elif kind == 2:
            kept.append(object())
        else:
            kept.append({rng.random(): "x" * rng.randrange(100)})


def worker(args: argparse.Namespace) -> None:
    """One process: every seed `--runs` times; a JSON line per run (and its history, if
    asked for, on the side)."""
    from rr_actors_lab.experiments import simulate  # noqa: PLC0415 - after the hash seed check
    from rr_actors_lab.experiments.reading import load_plan  # noqa: PLC0415

    if os.environ.get("PYTHONHASHSEED") != HASH_SEED:
        raise SystemExit(f"a worker runs under PYTHONHASHSEED={HASH_SEED}")
    logging.disable(logging.WARNING)  # (the supervisor logs each kill)
    if args.gc_threshold:
        gc.set_threshold(args.gc_threshold, 10, 10)
    plan = load_plan(args.plan)
    if args.duration is not None:
        plan = plan.with_changes(duration=args.duration)
    rng = random.Random()  # noqa: S311 - unseeded on purpose: each process its own heap
    kept: list[Any] = []
    for number in range(1, args.runs + 1):
        for seed in parse_seeds(args.seeds):
            if args.shake:
                shake(rng, kept)
            run = simulate.run_seed(plan, seed)
            if args.keep is not None:
                path = Path(args.keep) / f"seed-{seed}-{run.hash[:16]}.jsonl"
                if not path.exists():
                    path.write_text(run.history, encoding="utf-8")
            line = {"seed": seed, "run": number, "hash": run.hash, "cpu_s": run.cpu_s}
            print(json.dumps(line), flush=True)


def recorded(path: str | None) -> dict[int, str]:
    """Seed -> hash of a sweep's `seeds.jsonl` (empty without one)."""
    if path is None:
        return {}
    lines = Path(path).read_text(encoding="utf-8").splitlines()
    rows = map(json.loads, filter(str.strip, lines))
    return {int(row["seed"]): row["hash"] for row in rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1-10", help="seeds: 1-10, 1,4,7 (1-10)")
    parser.add_argument("--runs", type=int, default=10, help="runs of each seed a process (10)")
    parser.add_argument("--processes", type=int, default=2, help="processes at once (2)")
    parser.add_argument("--busy", type=int, default=0, help="CPU-bound processes beside (0)")
    parser.add_argument("--plan", help="a plan file (the shipped killheavy without its cut)")
    parser.add_argument("--duration", type=float, help="the plan's duration instead (s)")
    parser.add_argument("--against", help="a sweep's seeds.jsonl: its hashes must come too")
    parser.add_argument("--keep", help="a folder for the histories of seeds that differed")
    parser.add_argument("--no-shake", dest="shake", action="store_false", help="keep the heap")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--gc-threshold", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args)
        return

    with tempfile.TemporaryDirectory(prefix="bench-fidelity-") as tmp:
        plan = args.plan or str(killheavy_without_cut(Path(tmp)))
        keep = args.keep or str(Path(tmp) / "histories")
        Path(keep).mkdir(parents=True, exist_ok=True)
        load_before = os.getloadavg()[0]
        started = time.monotonic()
        with _harness.busy(args.busy):
            outputs = run_workers(args, plan, keep)
        wall = time.monotonic() - started
        load_after = os.getloadavg()[0]
        failed = report(args, outputs, recorded(args.against), keep if args.keep else None)
    print(
        f"\n{args.processes} processes x {args.runs} runs of each seed, "
        f"{'heap shaken, ' if args.shake else ''}beside {args.busy} busy loop(s); "
        f"commit {_harness.commit()}, {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC, "
        f"{os.cpu_count()} cores, load average {load_before:.1f} before, {load_after:.1f} "
        f"after; {wall:.0f} s of wall time"
    )
    sys.exit(1 if failed else 0)


def run_workers(args: argparse.Namespace, plan: str, keep: str) -> list[dict[str, Any]]:
    """Start the processes at once; every run's line, tagged with its process."""
    env = {**os.environ, "PYTHONHASHSEED": HASH_SEED}
    common = [sys.executable, __file__, "--worker", "--plan", plan, "--seeds", args.seeds]
    common += ["--runs", str(args.runs), "--keep", keep]
    if args.duration is not None:
        common += ["--duration", str(args.duration)]
    if not args.shake:
        common.append("--no-shake")
    workers = []
    for index in range(args.processes):
        threshold = GC_THRESHOLDS[index % len(GC_THRESHOLDS)]
        extra = [] if threshold is None else ["--gc-threshold", str(threshold)]
        workers.append(
            subprocess.Popen([*common, *extra], env=env, stdout=subprocess.PIPE, text=True)
        )
    lines: list[dict[str, Any]] = []
    for index, process in enumerate(workers):
        out, _ = process.communicate()
        if process.returncode:
            raise SystemExit(f"worker {index + 1} exited {process.returncode}")
        lines.extend({**json.loads(line), "process": index + 1} for line in out.splitlines())
    return lines


def report(
    args: argparse.Namespace,
    lines: list[dict[str, Any]],
    expected: dict[int, str],
    keep: str | None,
) -> bool:
    """Print the table; whether a seed gave two histories or not the recorded one."""
    by_seed: dict[int, list[str]] = collections.defaultdict(list)
    for line in lines:
        by_seed[line["seed"]].append(line["hash"])
    print(f"{'seed':>6}  {'matched':>9}  {'hashes':>6}  {'hash':<16}  recorded")
    matched = total = 0
    failed = False
    for seed in sorted(by_seed):
        hashes = by_seed[seed]
        common, count = collections.Counter(hashes).most_common(1)[0]
        distinct = len(set(hashes))
        if seed in expected:
            same = "same" if expected[seed] == common else f"OTHER ({expected[seed][:16]})"
        else:
            same = "-"
        matched += count
        total += len(hashes)
        failed |= distinct > 1 or same.startswith("OTHER")
        print(f"{seed:>6}  {count:>4} / {len(hashes):<2}  {distinct:>6}  {common[:16]:<16}  {same}")
    cpu = [line["cpu_s"] for line in lines]
    print(
        f"\nmatched: {matched} of {total} runs gave their seed's most common history "
        f"({sum(1 for h in by_seed.values() if len(set(h)) == 1)} of {len(by_seed)} seeds "
        f"one history in {args.processes} processes x {args.runs} runs); "
        f"CPU s a run: median {sorted(cpu)[len(cpu) // 2]:.2f}"
    )
    if failed and keep is not None:
        print(f"the histories of the seeds that differed: {keep}/seed-S-HASH.jsonl")
    return failed


if __name__ == "__main__":
    main()
