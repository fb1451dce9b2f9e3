"""Group commit: operations per second and SQLite commits per operation, many callers on one
durable provider (issue 52, parts 2 and 4).

One process: a provider registrar with a backup and `save_on_modify=True` (every change
durable before it is acknowledged), one consumer registrar (without a backup unless
`--durable-consumer`), and `--callers` threads that each, in a loop, make a dedup-hit
`call` to the provider and `unload` the id (one consumer id stays held, so no unload is
the last). An operation is one call or one unload. Commits are counted in the process by
wrapping the store's one write path (`SqliteStore._run`: one call, one transaction), so
the same worker measures any tree.

`--trees A,B` runs the worker once per tree and round (`PYTHONPATH=tree`), alternating, so
both see the same machine load; `--pin` runs each worker under `taskset -c 0`.

Usage:
    python benchmarks/bench_group_commit.py --trees /work/main,$PWD [--rounds 3]
        [--seconds 3] [--callers 16] [--durability process|power] [--durable-consumer] [--pin]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import _harness


def worker(args: argparse.Namespace) -> None:
    """Run the callers for `args.seconds` after a warm-up; print one JSON line."""
    import rr_actors as rr  # noqa: PLC0415 - the tree PYTHONPATH names
    from rr_actors._store.saver import SqliteStore  # noqa: PLC0415

    commits = [0]
    run = SqliteStore._run

    def counted(store: Any, ops: Any) -> None:
        run(store, ops)
        commits[0] += 1

    SqliteStore._run = counted  # type: ignore[method-assign]
    with tempfile.TemporaryDirectory() as work:
        provider = rr.ResourceRegistrar.start(
            rr.RegistrarConfig(
                name="gc-provider",
                backup_path=Path(work, "p.db"),
                save_on_modify=True,
                durability=args.durability,
            )
        )
        consumer = rr.ResourceRegistrar.start(
            rr.RegistrarConfig(
                name="gc-consumer",
                backup_path=Path(work, "c.db") if args.durable_consumer else None,
                save_on_modify=args.durable_consumer,
                durability=args.durability,
            )
        )
        provider.register_server("res", load=lambda request: request, unload=lambda *_: None)
        consumer.call(provider.name, "res", "shared")  # held throughout: every call a hit
        done = [0] * args.callers
        stop = threading.Event()
        counting = threading.Event()

        def caller(index: int) -> None:
            while not stop.is_set():
                query = consumer.call(provider.name, "res", "shared", timeout=30)
                consumer.unload(query.id)
                if counting.is_set():
                    done[index] += 2

        threads = [threading.Thread(target=caller, args=(i,)) for i in range(args.callers)]
        for thread in threads:
            thread.start()
        stop.wait(args.warm)
        before, began = commits[0], time.perf_counter()
        counting.set()
        stop.wait(args.seconds)
        counting.clear()
        ops, took, made = sum(done), time.perf_counter() - began, commits[0] - before
        stop.set()
        for thread in threads:
            thread.join(60)
        consumer.stop()
        provider.stop()
    print(json.dumps({"ops_per_s": ops / took, "commits_per_op": made / max(ops, 1), "ops": ops}))


def drive(args: argparse.Namespace) -> None:
    """Alternate the worker over the trees; print a table of medians."""
    trees = args.trees.split(",")
    results: dict[str, list[dict[str, float]]] = {tree: [] for tree in trees}
    command = [sys.executable, str(Path(__file__).resolve()), "--worker"]
    command += ["--seconds", str(args.seconds), "--warm", str(args.warm)]
    command += ["--callers", str(args.callers), "--durability", args.durability]
    command += ["--durable-consumer"] if args.durable_consumer else []
    if args.pin:
        command = ["taskset", "-c", "0", *command]
    for _ in range(args.rounds):
        for tree in trees:
            env = {**os.environ, "PYTHONPATH": tree}
            out = subprocess.run(command, env=env, capture_output=True, text=True, check=True)
            results[tree].append(json.loads(out.stdout.strip().splitlines()[-1]))
    consumer = "durable" if args.durable_consumer else "no backup"
    _harness.print_table(
        f"{args.callers} callers, durability={args.durability}, consumer {consumer}, "
        f"{args.rounds} rounds of {args.seconds} s{' (taskset -c 0)' if args.pin else ''}",
        ("tree", "ops/s (median)", "commits per op (median)", "ops/s of each round"),
        [
            (
                tree,
                f"{_harness.median(r['ops_per_s'] for r in rows):,.0f}",
                f"{_harness.median(r['commits_per_op'] for r in rows):.3f}",
                ", ".join(f"{r['ops_per_s']:.0f}" for r in rows),
            )
            for tree, rows in results.items()
        ],
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--trees", default=str(Path(__file__).resolve().parent.parent))
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--warm", type=float, default=1.0)
    parser.add_argument("--callers", type=int, default=16)
    parser.add_argument("--durability", choices=["process", "power"], default="process")
    parser.add_argument("--durable-consumer", action="store_true")
    parser.add_argument("--pin", action="store_true", help="taskset -c 0")
    args = parser.parse_args()
    if args.worker:
        worker(args)
    else:
        drive(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
