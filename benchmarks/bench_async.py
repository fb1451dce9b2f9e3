"""The registrar awaited from an event loop: calls in flight, a dedup hit, the loop's lag.

Three measurements, each next to its floor in the same run (docs/performance.md):

    in flight   `--calls` calls awaited at once from one event loop (`acall`), each a new
                request to a provider whose coroutine `load` awaits a slow resource (a
                gate the benchmark opens once every load has started): the threads of
                the process and its RSS while all of them wait, then every call
                answered and every id released (`aunload`; the provider serves nothing
                and the consumer holds nothing after). Floors: 16 threads, 200 MiB.
    dedup hit   an awaited in-process dedup hit (`await acall` of a request loaded
                already) next to a raw pykka `ask` to an echoing actor, and the blocking
                `call` of the same hit, in interleaved rounds. Floor: 1.5x the ask.
                Run it pinned (`taskset -c 0`), as the other in-process ratios are.
    loop lag    a ticker task on the loop (every `TICK` seconds, the lateness of its
                wake-up) while the loop drives `--rate` calls a second for `--seconds`,
                each a new request whose coroutine `load` awaits `--slow` seconds, then
                its `unload`: through the async API, then the blocking API called from
                the loop. Floor: p99 lag 5 ms (async).

Usage:
    taskset -c 0 python benchmarks/bench_async.py [--calls 10000] [--rounds 10]
        [--batch 200] [--rate 1000] [--seconds 3] [--slow 0.02]
"""

from __future__ import annotations

import argparse
import asyncio
import concurrent.futures
import importlib.metadata
import itertools
import os
import platform
import statistics
import sys
import threading
import time
import uuid
from typing import Any

import _harness
from bench_core import Echo

import rr_actors as rr

TICK = 0.001
"""Seconds between the ticker's wake-ups."""

THREADS_FLOOR = 16
RSS_FLOOR_MIB = 200.0
DEDUP_FLOOR = 1.5
LAG_FLOOR_MS = 5.0


async def _noop_unload(_request: Any, _response: Any) -> None:
    return None


# -- in flight ------------------------------------------------------------------------


async def in_flight(calls: int) -> dict[str, Any]:
    """`calls` awaited calls in flight at once, each waiting on the provider's gate."""
    suffix = uuid.uuid4().hex[:6]
    provider = rr.ResourceRegistrar.start(  # (a server sized to take them all at once)
        rr.RegistrarConfig(
            name=f"async-provider-{suffix}",
            call_timeout=120.0,
            max_workers=calls,
            max_pending=calls,
        )
    )
    consumer = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=f"async-consumer-{suffix}", call_timeout=120.0)
    )
    gate: concurrent.futures.Future[None] = concurrent.futures.Future()
    all_started: concurrent.futures.Future[None] = concurrent.futures.Future()
    started = itertools.count(1)

    async def load(request: Any) -> Any:  # on the registrar's loop
        if next(started) == calls:
            all_started.set_result(None)
        await asyncio.wrap_future(gate)  # the slow resource
        return request

    try:
        await provider.aregister_server("slow", load=load, unload=_noop_unload)
        rss_before = (_harness.memory_kib() or 0) / 1024
        begun = time.perf_counter()
        tasks = [
            asyncio.ensure_future(consumer.acall(provider.name, "slow", n)) for n in range(calls)
        ]
        await asyncio.wait_for(asyncio.wrap_future(all_started), 120.0)
        waiting = time.perf_counter() - begun
        threads = threading.active_count()
        rss = (_harness.memory_kib() or 0) / 1024
        gate.set_result(None)
        queries = await asyncio.gather(*tasks)
        answered = sum(1 for q in queries if q.response == q.request)
        await asyncio.gather(*(consumer.aunload(q.id) for q in queries))
        served = len(await provider.aserver_queries("slow"))
        held = len(await consumer.aclient_queries())
        total = time.perf_counter() - begun
    finally:
        if not gate.done():
            gate.set_result(None)
        await consumer.astop()
        await provider.astop()
    return {
        "calls": calls,
        "in flight after (s)": waiting,
        "threads": threads,
        "rss": rss,
        "rss_before": rss_before,
        "answered": answered,
        "served after": served,
        "held after": held,
        "total (s)": total,
    }


# -- the dedup hit ----------------------------------------------------------------------


async def dedup(rounds: int, batch: int) -> dict[str, tuple[float, float]]:
    """Median and p90 (us) of an ask, an awaited dedup hit and a blocking one."""
    suffix = uuid.uuid4().hex[:6]
    echo = Echo.start()
    provider = rr.ResourceRegistrar.start(f"dedup-provider-{suffix}")
    consumer = rr.ResourceRegistrar.start(f"dedup-consumer-{suffix}")
    provider.register_server("res", load=lambda request: request, unload=lambda *_: None)
    consumer.call(provider.name, "res", "shared")
    ids: list[str] = []
    samples: dict[str, list[float]] = {"pykka ask": [], "awaited dedup hit": [], "dedup hit": []}
    clock = time.perf_counter_ns

    async def one_round(record: bool) -> None:
        ask, awaited, blocking = (samples[k] if record else [] for k in samples)
        for _ in range(batch):
            start = clock()
            echo.ask("ping")
            ask.append(clock() - start)
        for _ in range(batch):
            start = clock()
            query = await consumer.acall(provider.name, "res", "shared")
            awaited.append(clock() - start)
            ids.append(query.id)
        for _ in range(batch):
            start = clock()
            query = consumer.call(provider.name, "res", "shared")
            blocking.append(clock() - start)
            ids.append(query.id)
        for query_id in ids:
            consumer.unload(query_id)
        ids.clear()

    try:
        await one_round(record=False)  # warm-up
        for _ in range(rounds):
            await one_round(record=True)
    finally:
        consumer.stop()
        provider.stop()
        echo.stop()
    return {
        name: (statistics.median(s) / 1000, _harness.percentile(s, 0.9) / 1000)
        for name, s in samples.items()
    }


# -- the loop's lag -----------------------------------------------------------------------


async def ticker(late: list[float], stop: asyncio.Event) -> None:
    """Wake every `TICK` seconds until `stop`; append each wake-up's lateness to `late`."""
    loop = asyncio.get_running_loop()
    due = loop.time() + TICK
    while not stop.is_set():
        await asyncio.sleep(max(0.0, due - loop.time()))
        now = loop.time()
        late.append(now - due)
        due = max(due + TICK, now)  # (a tick missed is not made up)


async def lag(awaited: bool, rate: float, seconds: float, slow: float) -> dict[str, float]:
    """The ticker's lateness while the loop drives `rate` calls a second for `seconds`."""
    suffix = uuid.uuid4().hex[:6]
    provider = rr.ResourceRegistrar.start(f"lag-provider-{suffix}")
    consumer = rr.ResourceRegistrar.start(f"lag-consumer-{suffix}")

    async def load(request: Any) -> Any:
        await asyncio.sleep(slow)
        return request

    await provider.aregister_server("res", load=load, unload=_noop_unload)
    late: list[float] = []
    done = 0
    stop = asyncio.Event()
    requests = itertools.count()

    async def one_call() -> None:
        nonlocal done
        query = await consumer.acall(provider.name, "res", next(requests))
        await consumer.aunload(query.id)
        done += 1

    async def driver() -> None:
        nonlocal done
        loop = asyncio.get_running_loop()
        begun = loop.time()
        sent = 0
        calls: set[asyncio.Task[None]] = set()
        while loop.time() - begun < seconds:
            due = int((loop.time() - begun) * rate) + 1
            while sent < due and loop.time() - begun < seconds:
                sent += 1
                if awaited:
                    task = asyncio.ensure_future(one_call())
                    calls.add(task)
                    task.add_done_callback(calls.discard)
                else:  # the blocking API, called from the loop
                    query = consumer.call(provider.name, "res", next(requests))
                    consumer.unload(query.id)
                    done += 1
            await asyncio.sleep(TICK)
        if calls:
            await asyncio.gather(*calls)

    try:
        ticking = asyncio.ensure_future(ticker(late, stop))
        begun = time.perf_counter()
        await driver()
        elapsed = time.perf_counter() - begun
        stop.set()
        await ticking
    finally:
        await consumer.astop()
        await provider.astop()
    return {
        "calls/s": done / elapsed,
        "p50": statistics.median(late) * 1000,
        "p99": _harness.percentile(late, 0.99) * 1000,
        "max": max(late) * 1000,
    }


async def main_async(args: argparse.Namespace) -> int:
    print(
        f"python {platform.python_version()}, pykka {importlib.metadata.version('pykka')}, "
        f"{sys.platform}, CPUs allowed: {len(os.sched_getaffinity(0))}, "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    print()
    if "flight" in args.sections:
        await print_in_flight(args)
    if "dedup" in args.sections:
        await print_dedup(args)
    if "lag" in args.sections:
        await print_lag(args)
    return 0


async def print_in_flight(args: argparse.Namespace) -> None:
    """The in-flight table."""
    flight = await in_flight(args.calls)
    threads_ok = flight["threads"] <= THREADS_FLOOR
    rss_ok = flight["rss"] <= RSS_FLOOR_MIB
    released = flight["served after"] == 0 and flight["held after"] == 0
    print(f"In flight: {flight['calls']:,} calls awaited at once from one loop")
    print()
    print("| measure | value | floor | met? |")
    print("|---|---:|---:|---|")
    print(f"| all loads started after (s) | {flight['in flight after (s)']:.2f} | | |")
    print(
        f"| threads in the process | {flight['threads']} | {THREADS_FLOOR} | {_yes(threads_ok)} |"
    )
    print(
        f"| RSS (MiB; {flight['rss_before']:.0f} before) | {flight['rss']:.0f} | "
        f"{RSS_FLOOR_MIB:.0f} | {_yes(rss_ok)} |"
    )
    print(
        f"| calls answered | {flight['answered']:,} | {flight['calls']:,} | "
        f"{_yes(flight['answered'] == flight['calls'])} |"
    )
    print(
        f"| ids served / held after the unloads | {flight['served after']} / "
        f"{flight['held after']} | 0 / 0 | {_yes(released)} |"
    )
    print(f"| all answered and released after (s) | {flight['total (s)']:.2f} | | |")
    print()


async def print_dedup(args: argparse.Namespace) -> None:
    """The dedup-hit table."""
    rows = await dedup(args.rounds, args.batch)
    base = rows["pykka ask"][0]
    print(f"Dedup hit: {args.rounds} rounds x {args.batch} operations per row")
    print()
    print("| operation | median (us) | p90 (us) | median / pykka ask | floor |")
    print("|---|---:|---:|---:|---:|")
    for name, (median, p90) in rows.items():
        floor = f"{DEDUP_FLOOR}x" if name == "awaited dedup hit" else ""
        print(f"| {name} | {median:.1f} | {p90:.1f} | {median / base:.2f}x | {floor} |")
    print()


async def print_lag(args: argparse.Namespace) -> None:
    """The loop-lag table."""
    print(
        f"Loop lag: a ticker every {TICK * 1000:g} ms while the loop drives {args.rate:g} "
        f"calls/s for {args.seconds:g} s (each load awaits {args.slow * 1000:g} ms)"
    )
    print()
    print("| API | calls/s done | lag p50 (ms) | p99 (ms) | max (ms) | floor (p99) |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, awaited in (("async (acall, aunload)", True), ("blocking, from the loop", False)):
        row = await lag(awaited, args.rate, args.seconds, args.slow)
        floor = f"{LAG_FLOOR_MS:g} ms" if awaited else ""
        print(
            f"| {name} | {row['calls/s']:.0f} | {row['p50']:.2f} | {row['p99']:.2f} | "
            f"{row['max']:.2f} | {floor} |"
        )
    print()


def _yes(ok: bool) -> str:
    return "yes" if ok else "no"


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, run, print the tables."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=10_000, help="calls in flight at once")
    parser.add_argument("--rounds", type=int, default=10, help="dedup: interleaved rounds")
    parser.add_argument("--batch", type=int, default=200, help="dedup: operations per row")
    parser.add_argument("--rate", type=float, default=1000.0, help="lag: calls a second")
    parser.add_argument("--seconds", type=float, default=3.0, help="lag: how long")
    parser.add_argument("--slow", type=float, default=0.02, help="lag: each load's await (s)")
    parser.add_argument(
        "--sections",
        nargs="+",
        choices=("flight", "dedup", "lag"),
        default=("flight", "dedup", "lag"),
        help="which measurements to run (default: all)",
    )
    args = parser.parse_args(argv)
    return asyncio.run(main_async(args))


if __name__ == "__main__":
    sys.exit(main())
