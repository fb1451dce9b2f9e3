"""Status fan-out to a hung consumer (issues 53, 51): threads held, what `send_status` does,
and whether the healthy consumers hear their statuses in order.

A provider serves one resource to `--consumers` consumer ids (200), spread over
`--registrars` consumer registrars (4); the callback of one id (the first) never returns
(it blocks on an event set at teardown), the others record and return. The provider
sends `--statuses` statuses (2,000), each a `send_status(..., timeout=--timeout)`, from
`--senders` threads (4): flaps, OK and ERROR in turn, the message its sequence number
(then one last, numbered `--statuses`). Printed per run:

    threads     of the consumers' process before the first status and after the last
                (`threading.active_count()` here; the manager's threads by psutil in the
                process placement), and the difference
    wall        seconds the 2,000 sends took
    timed out   sends that raised `CallTimeoutError`
    gave up     sends whose result named a consumer given up on (when `send_status`
                returns a `StatusDelivery`; "-" where it returns None)
    last heard  whether every healthy id heard the last status (its callback's record)
    out of order  healthy ids whose callback saw the sequence numbers not increasing
                (issue 51 finding 6: the docs promise arrival order for each id; a gap is
                fine, statuses coalesce behind a running callback); "-" unless
                `--senders 1` (with more, the send order is not defined)
    queued      calls waiting in the hung id's lane after the last send, and tasks on the
                process's own loop (coroutine callbacks: each would run) (thread
                placement: the process's status runner, read directly; "-" in a manager
                process)

Each placement runs twice: `hung` (the one hung callback) and its floor `none` (the
same, no callback hangs), in the same run. `--callback coroutine`: the callbacks are
`async def` (the hung one awaits its release on a thread of its own, `asyncio.to_thread`).

Placements: `thread` (provider and consumers in this process) and `process` (the
consumers in a manager process of a `System`, the provider here; the threads counted
are the manager's, read with psutil).

Usage:
    python benchmarks/bench_status_hang.py [--placement thread process]
        [--consumers 200] [--registrars 4] [--statuses 2000] [--senders 4]
        [--timeout 0.5] [--callback plain|coroutine] [--cold]

The flap order (issue 51 finding 6): `--senders 1 --statuses 1000`, beside busy loops.
`--cold`: no warm-up status, so the provider learns where the consumers live from the
answers to the first numbered ones and switches its way to them as they go (issue 68
item 1: `--placement process --senders 1 --cold`, beside three busy loops).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import _harness

import rr_actors as rr
from rr_actors.testing import RemoteRegistrar, System


def consumer_setup(
    address: Any,
    provider: str,
    registrars: int,
    consumers: int,
    hang: bool,
    coroutine: bool = False,
) -> Callable[[rr.ResourceRegistrar], None]:
    """Consumer registrars (in the process of `host`), `consumers` ids of `provider`'s
    resource, the first id's callback hung if `hang`; server "probe" answers what the ids
    heard last ("heard"), how many healthy ids heard theirs out of order ("order": the
    count and one such sequence around its first step back), releases the hung callback
    and stops them ("stop")."""

    def setup(host: rr.ResourceRegistrar) -> None:
        network = address.attach() if address is not None else None
        release = threading.Event()
        lock = threading.Lock()
        last: dict[str, str] = {}
        seen: dict[str, list[int]] = {}  # id -> the sequence numbers its callback saw
        registrars_here: list[rr.ResourceRegistrar] = []
        hung: list[str] = []

        def record(query: rr.Query, update: rr.StatusUpdate) -> None:
            if hung and query.id == hung[0] and update.message != "warm-up":
                release.wait()
                return
            with lock:
                last[query.id] = update.message
                if update.message.isdigit():
                    seen.setdefault(query.id, []).append(int(update.message))

        async def record_awaited(query: rr.Query, update: rr.StatusUpdate) -> None:
            if hung and query.id == hung[0] and update.message != "warm-up":
                await asyncio.to_thread(release.wait)
                return
            with lock:
                last[query.id] = update.message
                if update.message.isdigit():
                    seen.setdefault(query.id, []).append(int(update.message))

        callback = record_awaited if coroutine else record
        registrars_here.extend(
            rr.ResourceRegistrar.start(f"{host.name}-c{number}", network=network)
            for number in range(registrars)
        )
        for index in range(consumers):
            consumer = registrars_here[index % registrars]
            query = consumer.call(provider, "leaf", "r", on_status=callback, timeout=30)
            if hang and index == 0:
                hung.append(query.id)

        def probe(request: tuple[str, str]) -> Any:
            if request[0] == "heard":
                with lock:
                    return dict(last)
            if request[0] == "order":
                with lock:
                    return out_of_order(seen)
            release.set()
            for registrar in reversed(registrars_here):
                registrar.stop()
            return None

        host.register_server("probe", load=probe, unload=lambda _r, _s: None)

    return setup


def out_of_order(seen: dict[str, list[int]]) -> tuple[int, str]:
    """How many of `seen`'s sequences are not increasing, and one around its first step back."""
    wrong = 0
    example = ""
    for numbers in seen.values():
        back = next((i for i in range(1, len(numbers)) if numbers[i] <= numbers[i - 1]), None)
        if back is None:
            continue
        wrong += 1
        example = example or " ".join(map(str, numbers[max(0, back - 3) : back + 3]))
    return wrong, example


def threads_of(pid: int | None) -> int:
    if pid is None:
        return threading.active_count()
    import psutil  # noqa: PLC0415 - a dev dependency

    return psutil.Process(pid).num_threads()


def queued_here() -> int:
    """The longest lane of this process's status runner now (its private state: a
    benchmark's look inside)."""
    from rr_actors._core.loops import process_loop  # noqa: PLC0415
    from rr_actors._registrar.status import DESK  # noqa: PLC0415

    async def tasks() -> int:
        return len(asyncio.all_tasks()) - 1  # (not this one)

    on_loop = asyncio.run_coroutine_threadsafe(tasks(), process_loop()).result(timeout=30)
    lanes = [
        *list(DESK.runner._lanes.values()),
        *list(getattr(DESK.runner, "_loop_lanes", {}).values()),
    ]
    return max((len(lane) for lane in lanes), default=0) + on_loop


def heard_last(
    provider: Any, host: Any, query_id: str, hang: bool, args: argparse.Namespace
) -> int:
    """Send one last status; how many healthy ids heard it (a bounded poll)."""
    last = str(args.statuses)
    with contextlib.suppress(rr.CallTimeoutError):  # (all heard it? the hung one not)
        provider.send_status(query_id, rr.Status.UPDATE, last, timeout=max(args.timeout, 5))
    healthy_last = 0
    for _ in range(100):  # (a bounded poll: a benchmark, not a test)
        heard = host.call(host.name, "probe", ("heard", uuid.uuid4().hex), timeout=30).response
        healthy_last = sum(1 for message in heard.values() if message == last)
        if healthy_last >= args.consumers - (1 if hang else 0):
            break
        time.sleep(0.1)
    return healthy_last


def run(placement: str, hang: bool, args: argparse.Namespace) -> dict[str, Any]:
    uid = uuid.uuid4().hex[:6]
    system = System.create() if placement == "process" else None
    network = system if system is not None else None
    provider = rr.ResourceRegistrar.start(f"prov-{uid}", network=network)
    provider.register_server("leaf", load=lambda r: r, unload=lambda _r, _s: None)
    setup = consumer_setup(
        system.address if system is not None else None,
        provider.name,
        args.registrars,
        args.consumers,
        hang,
        args.callback == "coroutine",
    )
    if system is None:
        host = rr.ResourceRegistrar.start(f"host-{uid}")
        setup(host)
        pid = None
    else:
        config = rr.RegistrarConfig(name=f"host-{uid}", call_timeout=30.0)
        host = RemoteRegistrar.start(config, system, setup=setup, start_timeout=120)  # (loaded)
        pid = host.pid
    query_id = provider.server_queries("leaf")[0].id
    if not args.cold:
        provider.send_status(query_id, rr.Status.UPDATE, "warm-up", timeout=30)  # (routes)
    before = threads_of(pid)
    timed_out = gave_up = 0
    results: list[Any] = []
    lock = threading.Lock()

    def send(number: int) -> None:
        nonlocal timed_out, gave_up
        try:
            flap = rr.Status.ERROR if number % 2 else rr.Status.OK
            result = provider.send_status(query_id, flap, str(number), timeout=args.timeout)
        except rr.CallTimeoutError:
            with lock:
                timed_out += 1
            return
        with lock:
            results.append(result)
            if result is not None and getattr(result, "gave_up", ()):
                gave_up += 1

    started = time.perf_counter()
    with ThreadPoolExecutor(args.senders) as pool:
        list(pool.map(send, range(args.statuses)))
    wall = time.perf_counter() - started
    after = threads_of(pid)
    queued = queued_here() if pid is None else None
    healthy_last = heard_last(provider, host, query_id, hang, args)
    wrong, example = host.call(host.name, "probe", ("order", uuid.uuid4().hex), timeout=30).response
    host.call(host.name, "probe", ("stop", uuid.uuid4().hex), timeout=30)
    host.stop()
    provider.stop()
    if system is not None:
        system.close()
    returns_delivery = any(result is not None for result in results)
    return {
        "before": before,
        "after": after,
        "wall": wall,
        "timed_out": timed_out,
        "gave_up": gave_up if returns_delivery else None,
        "heard": f"{healthy_last}/{args.consumers - (1 if hang else 0)}",
        "queued": queued,
        "order": f"{wrong}/{args.consumers - (1 if hang else 0)}" if args.senders == 1 else "-",
        "example": example,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--placement", nargs="+", default=["thread", "process"])
    parser.add_argument("--consumers", type=int, default=200)
    parser.add_argument("--registrars", type=int, default=4)
    parser.add_argument("--statuses", type=int, default=2000)
    parser.add_argument("--senders", type=int, default=4)
    parser.add_argument("--timeout", type=float, default=0.5)
    parser.add_argument("--callback", choices=["plain", "coroutine"], default="plain")
    parser.add_argument("--cold", action="store_true", help="no warm-up status first")
    args = parser.parse_args()
    _harness.head(
        _harness.header(
            f"{args.consumers} consumer ids on {args.registrars} registrars, {args.statuses} "
            f"statuses from {args.senders} threads, timeout {args.timeout} s, "
            f"{args.callback} callbacks{', no warm-up' if args.cold else ''}"
        ),
        (
            "placement", "hung", "threads", "wall s", "timed out", "gave up", "last heard",
            "queued", "out of order",
        ),
        right=2,
    )  # fmt: skip
    examples: list[str] = []
    for placement in args.placement:
        for hang in (True, False):
            row = run(placement, hang, args)
            threads = f"{row['before']} -> {row['after']} ({row['after'] - row['before']:+d})"
            gave = "-" if row["gave_up"] is None else str(row["gave_up"])
            queued = "-" if row["queued"] is None else row["queued"]
            cells = (placement, "hung" if hang else "none", threads, f"{row['wall']:.2f}")
            cells += (row["timed_out"], gave, row["heard"], queued, row["order"])
            print(_harness.line(cells), flush=True)
            if row["example"] and args.senders == 1:
                examples.append(f"{placement} {'hung' if hang else 'none'}: ... {row['example']}")
    for example in examples:
        print(f"out of order, {example} ...")
    print(_harness.header("the end"))


if __name__ == "__main__":
    main()
