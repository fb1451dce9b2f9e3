"""A cross-process actor call in xoscar next to rr_actors' cross-process dedup-hit call.

Both on one CPU (`os.sched_setaffinity`, inherited by every process started here) that a
busy loop in another process shares (a loaded machine: each side gets what the scheduler
gives it). The two are measured in alternating batches, so the load spreads over both.

* xoscar: `await ref.echo(x)` from this process to an actor in a sub pool process
  (`xo.create_actor_pool(n_process=1)`, the actor placed at process index 1);
* rr_actors: `consumer.call(provider, "echo", {"cam": 1})` from this process to a provider
  registrar in another process, a dedup hit (`bench_transport.py` starts it).

Usage:
    python benchmarks/bench_xoscar.py [--rounds 5] [--batch 200] [--no-load]

Needs `pip install xoscar` (the `dev` extra has it).
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.metadata
import multiprocessing
import os
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import _harness
import xoscar as xo
from bench_transport import registrar_process, setup_echo

import rr_actors as rr
from rr_actors._registrar import Served
from rr_actors._transport.unix.system import System


class Echo(xo.Actor):  # type: ignore[misc]
    """xoscar's side: the cheapest useful method call."""

    def echo(self, value: Any) -> Any:
        return value


@contextlib.contextmanager
def busy_loop(cpu: int) -> Iterator[None]:
    """Another process spinning on `cpu` for the duration of the block."""
    command = ["taskset", "-c", str(cpu), sys.executable, "-c", "while True: pass"]
    spinner = subprocess.Popen(command)
    try:
        yield
    finally:
        spinner.kill()
        spinner.wait(10)


async def run_xoscar(rounds: int, batch: int, ours: Callable[[], Any]) -> dict[str, list[float]]:
    """Alternate a batch of xoscar calls with a batch of `ours` (run in a thread)."""
    pool = await xo.create_actor_pool("127.0.0.1", n_process=1)
    samples: dict[str, list[float]] = {"xoscar": [], "rr_actors": []}
    try:
        ref = await xo.create_actor(
            Echo,
            address=pool.external_address,
            uid="echo",
            allocate_strategy=xo.allocate_strategy.ProcessIndex(1),
        )
        clock = time.perf_counter
        for _ in range(batch):  # warm-up
            await ref.echo({"cam": 1})
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(None, lambda: _harness.each(ours, batch))
        for _ in range(rounds):
            for _ in range(batch):
                start = clock()
                await ref.echo({"cam": 1})
                samples["xoscar"].append(clock() - start)
            samples["rr_actors"] += await loop.run_in_executor(
                None, lambda: _harness.each(ours, batch)
            )
    finally:
        await pool.stop()
    return samples


def main(argv: list[str] | None = None) -> int:
    parser = _harness.options(__doc__, rounds=5, batch=200)
    parser.add_argument("--no-load", action="store_true", help="without the busy loop")
    args = _harness.parse(parser, argv)
    os.sched_setaffinity(0, {0})
    ctx = multiprocessing.get_context("forkserver")
    suffix = uuid.uuid4().hex[:6]
    system = System.create()
    ids: list[str] = []
    try:
        consumer = rr.ResourceRegistrar.start(f"main-{suffix}")
        system.serve(Served(consumer))
        provider = f"provider-{suffix}"
        try:
            with registrar_process(ctx, system.address, provider, setup_echo):

                def ours() -> None:
                    ids.append(consumer.call(provider, "echo", {"cam": 1}).id)

                load = contextlib.nullcontext() if args.no_load else busy_loop(0)
                with load:
                    samples = asyncio.run(run_xoscar(args.rounds, args.batch, ours))
                for query_id in ids:
                    consumer.unload(query_id)
        finally:
            consumer.stop()
    finally:
        system.close()
    print(
        _harness.header(
            f"xoscar {importlib.metadata.version('xoscar')}, one CPU"
            f"{'' if args.no_load else ' shared with a busy loop'}, {args.rounds} rounds x "
            f"{args.batch} calls per row"
        )
    )
    print()
    base = _harness.median(samples["xoscar"])
    rows = [
        (
            name,
            f"{_harness.median(v) * 1e6:.1f}",
            f"{_harness.percentile(v, 0.9) * 1e6:.1f}",
            f"{_harness.median(v) / base:.2f}x",
        )
        for name, v in samples.items()
    ]
    print(
        _harness.table(["cross-process call", "median (us)", "p90 (us)", "median / xoscar"], rows)
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
