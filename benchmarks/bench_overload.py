"""A provider offered ten times what it can load (issue 53): goodput, wasted loads, RSS.

One server whose `load` takes `--load-s` seconds (0.05), on a registrar with
`--workers` worker threads (2): its capacity is workers / load-s loads a second (40).
One consumer (this process, one event loop) offers `--factor` times that (10x: 400
distinct requests a second) for `--seconds` (30; `--seconds 600` for the 10-minute
run), each an awaited call with `--timeout` seconds (1.0); each answered call is
unloaded at once (with the same bound). Printed per `--window` seconds (10):

    acked/s     calls answered a second (goodput), beside the capacity
    wasted      loads that started after their caller had given up (timed out): work
                nobody will use (each load's first statement reads the monotonic clock
                its call's deadline is on; a caller's giving up is read on it too)
    unl. t/o    unloads of answered ids that timed out
    RSS         of this process (the consumer) and of the provider's process

then, `--drain` seconds (10) after the offer ends, the loads still run for nobody.

Callers (`--callers`): `asyncio` (one event loop, an awaited call per request, as
many in flight as the offer makes), `threads` (10 threads, each a blocking call at a
time, at most 40 a second each: the 400 together) or `thread` (one such thread). A
blocking caller waits within its timeout, so threads offer no more than they can wait
for: the bound slows them instead of queueing for them.

`--bystander`: a second consumer registrar makes one call a second meanwhile (timeout
`--bystander-timeout`, 2 s), and its answers and their latency are printed: with a
server bound (`--max-pending`, the provider's `max_pending`) that the flood fills, what
is left of it for another consumer (issue 53: each takes at most its share).

Placements: `--placement thread` (both registrars in this process) or `process` (the
provider in a manager process of a `Supervisor`, with its default heartbeat: the
provider's restarts, which a busy provider killed as hung would show, and the tree's
stop time are printed); `--kind threads` (a blocking `load`:
its calls wait for a worker) or `asyncio` (a coroutine `load`: it holds a worker's place,
not its thread, while it runs, so its calls queue for a worker too; its own
`asyncio.Semaphore(workers)` no longer queues any, as the registrar runs no more at once).

Usage:
    python benchmarks/bench_overload.py [--placement thread|process]
        [--callers asyncio|threads|thread] [--kind threads|asyncio] [--seconds 30]
        [--factor 10] [--load-s 0.05] [--workers 2] [--timeout 1.0] [--window 10] [--drain 10]
        [--max-pending 1000] [--bystander] [--bystander-timeout 2.0]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import itertools
import os
import platform
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import _harness

import rr_actors as rr


def rss_mib(pid: int | None = None) -> float:
    return (_harness.memory_kib(pid) or 0) / 1024


def server_setup(log: str, load_s: float, workers: int, kind: str) -> Callable[[Any], None]:
    """A setup registering server "slow": each load writes `<time> <monotonic> <request>`
    to `log`, both read as its first statement, then takes `load_s` seconds."""

    def setup(registrar: Any) -> None:
        def started(request: Any, began: float, wall: float) -> None:
            with open(log, "a") as out:
                out.write(f"{wall} {began} {request}\n")

        if kind == "threads":

            def load(request: Any) -> Any:
                started(request, time.monotonic(), time.time())
                time.sleep(load_s)
                return request

            registrar.register_server("slow", load=load, unload=lambda _r, _s: None)
            return
        gate: list[asyncio.Semaphore] = []

        async def aload(request: Any) -> Any:
            began, wall = time.monotonic(), time.time()
            if not gate:
                gate.append(asyncio.Semaphore(workers))
            async with gate[0]:
                started(request, began, wall)
                await asyncio.sleep(load_s)
            return request

        async def aunload(_request: Any, _response: Any) -> None:
            return None

        registrar.register_server("slow", load=aload, unload=aunload)

    return setup


class GaveUp:
    """The requests whose caller gave up, when (`time.monotonic()`, the clock of a call's
    deadline, as the caller heard of it) and its call's deadline at the latest (the
    monotonic time before the call, plus its timeout), kept in file `path` (one line
    each), not in memory: a 10-minute offer gives up on some 200,000, which a dict here
    would count as the consumer's RSS growth."""

    def __init__(self, path: str) -> None:
        self.path, self.count = path, 0
        self._out = open(path, "a")  # noqa: SIM115 (closed by `read`)
        self._lock = threading.Lock()

    def add(self, request: int, deadline: float) -> None:
        at = time.monotonic()
        with self._lock:
            self._out.write(f"{request} {at} {deadline}\n")
            self.count += 1

    def read(self) -> dict[int, tuple[float, float]]:
        """Request -> when its caller gave up, and its deadline (the file closed)."""
        self._out.close()
        with open(self.path) as lines:
            return {int(n): (float(at), float(d)) for n, at, d in (line.split() for line in lines)}


async def bystand(
    other: Any, provider: str, args: argparse.Namespace, stop: asyncio.Event
) -> list[float | str]:
    """One call a second from another consumer until `stop`: each one's latency (s), or
    the name of its error (requests -1, -2, ...: apart from the flood's)."""
    outcomes: list[float | str] = []
    n = 0
    while not stop.is_set():
        n += 1
        began = time.perf_counter()
        try:
            query = await other.acall(provider, "slow", -n, timeout=args.bystander_timeout)
            outcomes.append(time.perf_counter() - began)
            await other.aunload(query.id, timeout=args.bystander_timeout)
        except rr.RrError as exc:
            outcomes.append(type(exc).__name__)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), max(0.0, 1.0 - (time.perf_counter() - began)))
    return outcomes


async def offer(app: Any, provider: str, args: argparse.Namespace) -> dict[str, Any]:
    """Offer the load; what came of each call."""
    capacity = args.workers / args.load_s
    rate = capacity * args.factor
    gave_up = GaveUp(args.gave_up_log)
    acked: list[float] = []
    unload_timeouts: list[float] = []
    errors: dict[str, int] = {}

    async def one(n: int) -> None:
        deadline = time.monotonic() + args.timeout
        try:
            query = await app.acall(provider, "slow", n, timeout=args.timeout)
        except rr.CallTimeoutError:
            gave_up.add(n, deadline)
            return
        except rr.RrError as exc:
            errors[type(exc).__name__] = errors.get(type(exc).__name__, 0) + 1
            return
        acked.append(time.time())
        try:
            await app.aunload(query.id, timeout=args.timeout)
        except rr.CallTimeoutError:
            unload_timeouts.append(time.time())
        except rr.RrError as exc:
            errors[type(exc).__name__] = errors.get(type(exc).__name__, 0) + 1

    tasks: set[asyncio.Task[None]] = set()
    start = time.time()
    offered = 0
    while (now := time.time()) - start < args.seconds:
        due = int((now - start) * rate)
        while offered < due:
            task = asyncio.ensure_future(one(offered))
            tasks.add(task)
            task.add_done_callback(tasks.discard)
            offered += 1
        await asyncio.sleep(0.005)
    while tasks:
        await asyncio.sleep(0.05)
    return {
        "start": start,
        "offered": offered,
        "gave_up": gave_up,
        "acked": acked,
        "unload_timeouts": unload_timeouts,
        "errors": errors,
        "capacity": capacity,
    }


def offer_blocking(
    app: Any, provider: str, args: argparse.Namespace, threads: int
) -> dict[str, Any]:
    """Offer the load from `threads` threads, each a blocking call at a time (at most
    `rate / threads` a second each); what came of each call."""
    capacity = args.workers / args.load_s
    spacing = threads / (capacity * args.factor)  # seconds between one thread's calls
    gave_up = GaveUp(args.gave_up_log)
    acked: list[float] = []
    unload_timeouts: list[float] = []
    errors: dict[str, int] = {}
    numbers = itertools.count()
    lock = threading.Lock()
    start = time.time()

    def caller() -> None:
        due = time.time()
        while time.time() - start < args.seconds:
            wait = due - time.time()
            if wait > 0:
                time.sleep(wait)  # (pacing the offer, not synchronising)
            due = max(due + spacing, time.time())
            with lock:
                n = next(numbers)
            deadline = time.monotonic() + args.timeout
            try:
                query = app.call(provider, "slow", n, timeout=args.timeout)
            except rr.CallTimeoutError:
                gave_up.add(n, deadline)
                continue
            except rr.RrError as exc:
                with lock:
                    errors[type(exc).__name__] = errors.get(type(exc).__name__, 0) + 1
                continue
            acked.append(time.time())
            try:
                app.unload(query.id, timeout=args.timeout)
            except rr.CallTimeoutError:
                unload_timeouts.append(time.time())
            except rr.RrError as exc:
                with lock:
                    errors[type(exc).__name__] = errors.get(type(exc).__name__, 0) + 1

    workers = [threading.Thread(target=caller, name=f"caller-{i}") for i in range(threads)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    return {
        "start": start,
        "offered": next(numbers),
        "gave_up": gave_up,
        "acked": acked,
        "unload_timeouts": unload_timeouts,
        "errors": errors,
        "capacity": capacity,
    }


def report(result: dict[str, Any], log: str, args: argparse.Namespace, rss: list[str]) -> None:
    start, gave_up = result["start"], result["gave_up"].read()
    runs, began = [], {}
    with contextlib.suppress(FileNotFoundError), open(log) as lines:
        for line in lines:
            at, mono, request = line.split()
            runs.append((float(at), int(request)))
            began[int(request)] = float(mono)
    after = {n: began[n] - gave_up[n][0] for n in began if n in gave_up}
    wasted = [at for at, n in runs if after.get(n, 0) > 0]
    late = max(after.values(), default=0)
    past = sorted(began[n] - gave_up[n][1] for n in began if n in gave_up)
    past = [d for d in past if d > 0]
    print(
        f"\n| window (s) | offered/s | acked/s (capacity {result['capacity']:.0f}) "
        "| loads run | wasted | unl. t/o | RSS consumer / provider (MiB) |"
    )
    print("|---|---|---|---|---|---|---|")
    end = max([start + args.seconds, *(at for at, _ in runs), *result["acked"]])
    w = args.window
    for i, lo in enumerate(range(0, int(end - start) + 1, int(w))):
        a, b = start + lo, start + lo + w

        def count(times: list[float], a: float = a, b: float = b) -> int:
            return sum(a <= t < b for t in times)

        offered = (
            result["offered"] * min(w, max(0.0, args.seconds - lo)) / args.seconds
            if lo < args.seconds
            else 0
        )
        print(
            f"| {lo}-{lo + w:g} | {offered / w:.0f} | {count(result['acked']) / w:.1f} "
            f"| {count([t for t, _ in runs])} | {count(wasted)} "
            f"| {count(result['unload_timeouts'])} | {rss[i] if i < len(rss) else '-'} |"
        )
    print(
        f"\noffered {result['offered']}, acknowledged {len(result['acked'])}, gave up "
        f"{len(gave_up)}, loads run {len(runs)} ({len(wasted)} after their caller gave up, "
        f"the latest {max(late, 0) * 1000:.1f} ms after; {len(past)} after their call's "
        f"deadline, by {', '.join(f'{d * 1000:.1f}' for d in past[-5:]) or '-'} ms at most), "
        f"unloads timed out {len(result['unload_timeouts'])}, other errors {result['errors']}"
    )


async def sample_rss(pid: int | None, window: float, into: list[str], stop: asyncio.Event) -> None:
    """Every `window` seconds, the RSS of this process and of `pid`."""
    while True:
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), window)
        into.append(f"{rss_mib():.0f} / {rss_mib(pid) if pid else rss_mib():.0f}")
        if stop.is_set():
            return


def lines_in(path: str) -> int:
    """The lines of file `path` (0 if there is none)."""
    if not os.path.exists(path):
        return 0
    with open(path) as lines:
        return sum(1 for _ in lines)


async def run(
    app: Any,
    provider: str,
    pid: int | None,
    args: argparse.Namespace,
    log: str,
    other: Any = None,
) -> None:
    rss: list[str] = []
    stop = asyncio.Event()
    sampler = asyncio.ensure_future(sample_rss(pid, args.window, rss, stop))
    quiet = asyncio.Event()
    bystander = asyncio.ensure_future(bystand(other, provider, args, quiet)) if other else None
    if args.callers == "asyncio":
        result = await offer(app, provider, args)
    else:
        threads = 10 if args.callers == "threads" else 1
        result = await asyncio.to_thread(offer_blocking, app, provider, args, threads)
    quiet.set()
    if bystander is not None:
        outcomes = await bystander
        times = sorted(o for o in outcomes if isinstance(o, float))
        failed = [o for o in outcomes if isinstance(o, str)]
        print(
            f"bystander: {len(times)} of {len(outcomes)} calls answered (timeout "
            f"{args.bystander_timeout:g} s), latency median "
            f"{times[len(times) // 2] if times else float('nan'):.3f} s, max "
            f"{times[-1] if times else float('nan'):.3f} s; failed: "
            f"{ {name: failed.count(name) for name in sorted(set(failed))} }"
        )
    await asyncio.sleep(args.drain)  # loads queued for nobody would run on now
    ran_before = lines_in(log)
    await asyncio.sleep(1.0)
    ran_after = lines_in(log)
    stop.set()
    await sampler
    report(result, log, args, rss)
    print(
        f"{args.drain:g} s after the offer ended: {ran_after - ran_before} loads started in "
        f"the next second (work still queued for callers gone)"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--placement", choices=["thread", "process"], default="thread")
    parser.add_argument("--callers", choices=["asyncio", "threads", "thread"], default="asyncio")
    parser.add_argument("--kind", choices=["threads", "asyncio"], default="threads")
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--factor", type=float, default=10.0)
    parser.add_argument("--load-s", type=float, default=0.05)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=1.0)
    parser.add_argument("--window", type=float, default=10.0)
    parser.add_argument("--drain", type=float, default=10.0)
    parser.add_argument("--max-pending", type=int, default=1000)
    parser.add_argument("--bystander", action="store_true")
    parser.add_argument("--bystander-timeout", type=float, default=2.0)
    args = parser.parse_args(argv)
    print(
        f"python {platform.python_version()}, {platform.machine()}, rr_actors from "
        f"{Path(rr.__file__).parent}; {args.placement} placement, {args.callers} callers, "
        f"{args.kind} load, "
        f"{args.workers} workers x {args.load_s:g} s, {args.factor:g}x for {args.seconds:g} s, "
        f"timeout {args.timeout:g} s; load average {os.getloadavg()[0]:.1f}"
    )
    suffix = uuid.uuid4().hex[:6]
    with tempfile.TemporaryDirectory() as tmp:
        log = str(Path(tmp) / "loads.log")
        args.gave_up_log = str(Path(tmp) / "gave-up.log")
        setup = server_setup(log, args.load_s, args.workers, args.kind)
        config = rr.RegistrarConfig(
            name=f"overload-{suffix}", max_workers=args.workers, max_pending=args.max_pending
        )
        if args.placement == "thread":
            provider = rr.ResourceRegistrar.start(config)
            app = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=f"app-{suffix}"))
            other = rr.ResourceRegistrar.start(f"other-{suffix}") if args.bystander else None
            try:
                setup(provider)
                asyncio.run(run(app, provider.name, None, args, log, other))
            finally:
                if other is not None:
                    other.stop()
                app.stop()
                provider.stop()
            return
        spec = rr.ManagerSpec(config.name, setup, isolation="process", config=config)
        sup = rr.Supervisor([spec]).start()
        try:
            app = sup.registrar(f"app-{suffix}")
            other = sup.registrar(f"other-{suffix}") if args.bystander else None
            pid = sup.child(config.name).pid
            asyncio.run(run(app, config.name, pid, args, log, other))
            after = sup.child(config.name).pid
            print(
                f"provider restarted (killed as hung or crashed): {'no' if after == pid else 'YES'}"
            )
        finally:
            began = time.monotonic()
            sup.stop()
            print(f"the tree stopped in {time.monotonic() - began:.2f} s")


if __name__ == "__main__":
    main()
