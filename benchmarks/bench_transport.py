"""Cross-process transport benchmark: rr_actors calls vs a raw multiprocessing.Pipe round trip.

Run: `python benchmarks/bench_transport.py [--rounds N]`. Everything is measured in one run
on the same machine, so the ratios are comparable:

* the floor: a raw `multiprocessing.Pipe` round trip between two processes (bytes echo,
  and an object echo with pickling);
* a dedup-hit `call` from this process to a provider registrar in another process
  (target: <= 3x the raw round trip), next to the same call with both registrars in this
  process;
* the same cross-process call *paired* with both raw round trips: rounds of each in
  turn (their order alternating), so that the three share the machine's moods; its
  ratio is the median of the rounds' ratios (steadier on a shared machine than the
  ratio of two medians taken minutes apart);
* `send_status` over three hops across processes: provider process -> agent process ->
  consumer in this process, and the acknowledgements back (target: <= 1 ms);
* the CPU time per round trip of the floor and of the cross-process dedup hit, every
  thread of both processes (`/proc/<pid>/task/*/schedstat`, Linux): on a loaded machine
  the wall-clock medians swing with the load, the CPU a call costs much less.
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing
import multiprocessing.connection
import os
import signal
import statistics
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import _harness
import cloudpickle

import rr_actors as rr
from rr_actors._registrar import Served
from rr_actors._transport.unix.system import System, SystemAddress, attach

Setup = Callable[[rr.ResourceRegistrar], None]


# -- child processes ----------------------------------------------------------------------------


def _echo(conn: multiprocessing.connection.Connection, objects: bool) -> None:
    """Echo until the pipe closes (the raw floor)."""
    with contextlib.suppress(EOFError, OSError):
        while True:
            if objects:
                conn.send(conn.recv())
            else:
                conn.send_bytes(conn.recv_bytes())


def _registrar_main(
    address: SystemAddress,
    name: str | rr.RegistrarConfig,
    setup: bytes,
    control: multiprocessing.connection.Connection,
    answer: Callable[[Any], Any] | None = None,
) -> None:
    """Serve one registrar on the system until the control pipe says stop (or closes).

    Anything else on the control pipe is answered with `answer(it)` (`count_dedup.py --cross`'s
    marks).
    """
    attached = attach(address)
    registrar = rr.ResourceRegistrar.start(name)
    try:
        cloudpickle.loads(setup)(registrar)
        attached.serve(Served(registrar))
        control.send("ready")
        with contextlib.suppress(EOFError, OSError):
            while (order := control.recv()) != "stop" and answer is not None:
                control.send(answer(order))
    finally:
        registrar.stop()
        attached.close()


@contextlib.contextmanager
def registrar_process(
    ctx: Any, address: SystemAddress, name: str, setup: Setup
) -> Iterator[multiprocessing.process.BaseProcess]:
    """A registrar `name` in its own process for the duration of the block."""
    with registrar_child(ctx, address, name, setup) as (process, _):
        yield process


@contextlib.contextmanager
def registrar_child(
    ctx: Any,
    address: SystemAddress,
    name: str | rr.RegistrarConfig,
    setup: Setup,
    target: Callable[..., None] = _registrar_main,
    started: float = 60,
) -> Iterator[tuple[multiprocessing.process.BaseProcess, multiprocessing.connection.Connection]]:
    """`registrar_process`, with the control pipe: `target` runs in the process.

    `target` is `_registrar_main` or one that calls it; it must say it is ready within
    `started` seconds.
    """
    parent, child = ctx.Pipe()
    process = ctx.Process(
        target=target, args=(address, name, cloudpickle.dumps(setup), child), daemon=True
    )
    process.start()
    child.close()
    try:
        if not parent.poll(started) or parent.recv() != "ready":
            raise RuntimeError(f"registrar process {name} did not start")
        yield process, parent
    finally:
        with contextlib.suppress(OSError):
            parent.send("stop")
        process.join(10)
        if process.is_alive():
            process.kill()
            process.join(5)


# -- measurements -------------------------------------------------------------------------------


CPU: dict[str, float] = {}
"""CPU seconds per timed round of a row (`timed(..., cpu=(row, pids))`), both processes."""


def timed(
    fn: Callable[[], Any], rounds: int, warmup: int = 200, cpu: tuple[str, list[int]] | None = None
) -> list[float]:
    """Seconds per call of `fn`, `rounds` times after `warmup` untimed calls; with `cpu`
    (a row's name and the pids), the CPU per timed call of those processes into `CPU`."""
    for _ in range(warmup):
        fn()
    samples = []
    before = 0.0 if cpu is None else _harness.cpu_seconds(cpu[1])
    for _ in range(rounds):
        start = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - start)
    if cpu is not None:
        CPU[cpu[0]] = (_harness.cpu_seconds(cpu[1]) - before) / rounds
    return samples


def raw_pipe(ctx: Any, rounds: int, *, objects: bool) -> list[float]:
    parent, child = ctx.Pipe()
    process = ctx.Process(target=_echo, args=(child, objects), daemon=True)
    process.start()
    child.close()
    try:
        if objects:
            message = ("0f3b7b2c-1111-2222-3333-444455556666", "echo", {"cam": 1})

            def once() -> None:
                parent.send(message)
                parent.recv()
        else:
            payload = b"x" * 200

            def once() -> None:
                parent.send_bytes(payload)
                parent.recv_bytes()

        row = "CPU per raw Pipe round trip, send_bytes (floor)"
        return timed(once, rounds, cpu=None if objects else (row, [os.getpid(), process.pid]))
    finally:
        parent.close()
        process.join(10)


def setup_echo(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server(
        "echo", load=lambda request: {"resource": request}, unload=lambda _q, _r: None
    )


def dedup_hits(
    consumer: rr.ResourceRegistrar, provider: str, rounds: int, pid: int | None = None
) -> list[float]:
    """Seconds per dedup-hit call; with `pid` (the provider's process), its CPU too."""
    ids: list[str] = []

    def once() -> None:
        ids.append(consumer.call(provider, "echo", {"cam": 1}).id)

    row = "CPU per dedup hit across processes"
    samples = timed(once, rounds, cpu=None if pid is None else (row, [os.getpid(), pid]))
    for query_id in ids:
        consumer.unload(query_id)
    return samples


PAIRED_BATCH = 100
"""Timed round trips of each kind in one round of the paired rows."""


def paired_with_floors(
    ctx: Any, hit: Callable[[], object], rounds: int, after_round: Callable[[], object] = list
) -> dict[str, list[float]]:
    """`rounds` rounds, each a batch of raw Pipe bytes round trips, raw Pipe object round
    trips and `hit()` calls (their order alternating between rounds; `after_round()` runs,
    untimed, after each); the median seconds of each batch, per kind (`bytes`, `objects`,
    `hit`). The floors' echoes are processes of `ctx`."""
    pipes, echoes = [], []
    for objects in (False, True):
        parent, child = ctx.Pipe()
        echo = ctx.Process(target=_echo, args=(child, objects), daemon=True)
        echo.start()
        child.close()
        pipes.append(parent)
        echoes.append(echo)
    payload = b"x" * 200
    message = ("0f3b7b2c-1111-2222-3333-444455556666", "echo", {"cam": 1})

    def raw_bytes() -> None:
        pipes[0].send_bytes(payload)
        pipes[0].recv_bytes()

    def raw_objects() -> None:
        pipes[1].send(message)
        pipes[1].recv()

    kinds = [("bytes", raw_bytes), ("objects", raw_objects), ("hit", hit)]
    medians: dict[str, list[float]] = {name: [] for name, _ in kinds}
    try:
        for number in range(rounds):
            for name, fn in kinds if number % 2 == 0 else kinds[::-1]:
                medians[name].append(statistics.median(timed(fn, PAIRED_BATCH, warmup=10)))
            after_round()
    finally:
        for parent, echo in zip(pipes, echoes, strict=True):
            parent.close()
            echo.join(10)
    return medians


def paired(
    ctx: Any, consumer: rr.ResourceRegistrar, provider: str, rounds: int
) -> dict[str, list[float]]:
    """The paired rows (`paired_with_floors`) of cross-process dedup hits from `consumer`
    to `provider`'s `echo` server; each round's ids are unloaded after it."""
    ids: list[str] = []

    def hit() -> None:
        ids.append(consumer.call(provider, "echo", {"cam": 1}).id)

    def unload() -> None:
        for query_id in ids:
            consumer.unload(query_id)
        ids.clear()

    return paired_with_floors(ctx, hit, rounds, unload)


def status_timings(rounds: int) -> Callable[[rr.ResourceRegistrar], list[float]]:
    """A function to run in the provider: time `send_status` of its first query."""

    def measure(registrar: rr.ResourceRegistrar) -> list[float]:
        query_id = registrar.server_queries("echo")[0].id
        return timed(lambda: registrar.send_status(query_id, rr.Status.UPDATE, "tick"), rounds)

    return measure


def agent_setup(provider: str) -> Setup:
    """The agent's `composite` server depends on the provider's `echo` (a dependency)."""

    def setup(registrar: rr.ResourceRegistrar) -> None:
        def load(request: Any) -> Any:
            return registrar.call(provider, "echo", request).response

        registrar.register_server("composite", load=load, unload=lambda _q, _r: None)

    return setup


def setup_hang(registrar: rr.ResourceRegistrar) -> None:
    """`hang` blocks its load; a load of `started` returns once a `hang` load runs."""
    started = threading.Event()

    def hang(_request: Any) -> Any:
        started.set()
        threading.Event().wait(60)

    registrar.register_server("hang", load=hang, unload=lambda _q, _r: None)
    registrar.register_server(
        "started", load=lambda _request: started.wait(10), unload=lambda _q, _r: None
    )


def kill_detection(
    ctx: Any, system: System, consumer: rr.ResourceRegistrar, repeats: int
) -> list[float]:
    """Seconds from SIGKILL of a provider to the failure of a call in flight to it."""
    samples = []
    for number in range(repeats):
        name = f"victim-{number}-{uuid.uuid4().hex[:6]}"
        failed = threading.Event()
        ended: list[float] = []

        def call(
            name: str = name, failed: threading.Event = failed, ended: list[float] = ended
        ) -> None:
            try:
                consumer.call(name, "hang", "r", timeout=30)
            except rr.RegistrarUnavailableError:
                ended.append(time.perf_counter())
            failed.set()

        with registrar_process(ctx, system.address, name, setup_hang) as process:
            threading.Thread(target=call, daemon=True).start()
            if not consumer.call(name, "started", None, timeout=10).response:
                raise RuntimeError("the load never started")
            assert process.pid is not None
            killed = time.perf_counter()
            os.kill(process.pid, signal.SIGKILL)
            if not failed.wait(30) or not ended:
                raise RuntimeError("the call in flight did not fail as unavailable")
            samples.append(ended[0] - killed)
    return samples


# -- report ---------------------------------------------------------------------------------------


def row(name: str, samples: list[float], floor: float) -> str:
    median = statistics.median(samples)
    p90 = statistics.quantiles(samples, n=10)[-1]
    return f"| {name} | {median * 1e6:9.1f} | {p90 * 1e6:9.1f} | {median / floor:6.2f}x |"


def three_hops(
    ctx: Any,
    system: System,
    consumer: rr.ResourceRegistrar,
    provider: str,
    agent: str,
    rounds: int,
) -> list[float]:
    """Seconds per `send_status` from the provider's process, over the agent's (whose
    `composite` depends on the provider's `echo`) to `consumer`, acknowledged back."""
    with registrar_process(ctx, system.address, agent, agent_setup(provider)):
        heard: list[Any] = []
        query = consumer.call(
            agent, "composite", {"cam": 2}, on_status=lambda _q, u: heard.append(u)
        )
        status: list[float] = system.run(provider, status_timings(rounds), timeout=600)
        consumer.unload(query.id)
        if len(heard) < rounds:
            raise RuntimeError(f"only {len(heard)} statuses reached the consumer")
    return status


def paired_rows(
    pairs: dict[str, list[float]],
    hit_name: str = "dedup-hit call across processes, paired (target <= 3x)",
) -> None:
    """The paired rows: each kind's median over the rounds (of the rounds' medians), and
    the call's ratio to each floor as the median of the rounds' ratios."""
    ratios = {
        floor: statistics.median(h / f for h, f in zip(pairs["hit"], pairs[floor], strict=True))
        for floor in ("bytes", "objects")
    }
    spread = {
        floor: [h / f for h, f in zip(pairs["hit"], pairs[floor], strict=True)]
        for floor in ("bytes", "objects")
    }
    print()
    print(
        f"Paired: {len(pairs['hit'])} rounds of {PAIRED_BATCH} round trips of each kind, in "
        f"turn; ratio = the median of the rounds' ratios (lowest-highest round)"
    )
    print()
    _harness.head(None, ["measurement", "median us", "ratio to bytes", "ratio to objects"])
    names = {
        "bytes": "raw Pipe round trip, send_bytes, paired (floor)",
        "objects": "raw Pipe round trip, send/recv objects, paired",
        "hit": hit_name,
    }
    for kind, name in names.items():
        median = statistics.median(pairs[kind]) * 1e6
        if kind == "hit":
            cells = [
                f"{ratios[f]:.2f}x ({min(spread[f]):.2f}-{max(spread[f]):.2f})"
                for f in ("bytes", "objects")
            ]
        else:
            cells = ["1.00x" if kind == "bytes" else "", "1.00x" if kind == "objects" else ""]
        print(f"| {name} | {median:9.1f} | {cells[0]} | {cells[1]} |")


def print_rows(rounds: int, rows: list[tuple[str, list[float]]]) -> None:
    """The main table: each row's median and p90, as a multiple of the floor (row 1)."""
    floor = statistics.median(rows[0][1])
    print(f"rounds per row: {rounds}; times in microseconds; ratio = median / raw bytes median")
    print()
    _harness.head(None, ["measurement", "median us", "p90 us", "ratio"])
    for name, samples in rows:
        if samples:  # (`--only` skips some)
            print(row(name, samples, floor))
    cross, raw_objects = rows[3][1], rows[1][1]
    if cross:
        print()
        print(
            f"cross-process dedup hit vs raw object round trip: "
            f"{statistics.median(cross) / statistics.median(raw_objects):.2f}x"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2000, help="timed round trips per row")
    parser.add_argument(
        "--only",
        choices=["status", "paired"],
        help="measure only the floor and this row (quick runs to alternate with other code)",
    )
    parser.add_argument(
        "--paired-rounds",
        type=int,
        default=20,
        help=f"rounds of the paired rows ({PAIRED_BATCH} round trips of each kind a round)",
    )
    args = parser.parse_args()
    rounds: int = args.rounds
    every = args.only is None
    pairing = every or args.only == "paired"
    status_row = every or args.only == "status"
    ctx = multiprocessing.get_context("forkserver")

    raw_bytes = raw_pipe(ctx, rounds, objects=False)
    raw_objects = raw_pipe(ctx, rounds, objects=True) if every else []

    suffix = uuid.uuid4().hex[:6]
    system = System.create()
    try:
        consumer = rr.ResourceRegistrar.start(f"main-{suffix}")
        system.serve(Served(consumer))
        local = rr.ResourceRegistrar.start(f"local-{suffix}")
        setup_echo(local)
        provider = f"provider-{suffix}"
        agent = f"agent-{suffix}"
        status: list[float] = []
        try:
            in_process = dedup_hits(consumer, local.name, rounds) if every else []
            with registrar_process(ctx, system.address, provider, setup_echo) as process:
                cross = dedup_hits(consumer, provider, rounds, process.pid) if every else []
                pairs = paired(ctx, consumer, provider, args.paired_rounds) if pairing else {}
                if status_row:
                    status = three_hops(ctx, system, consumer, provider, agent, rounds)
            killed = kill_detection(ctx, system, consumer, repeats=10) if every else []
        finally:
            local.stop()
            consumer.stop()
    finally:
        system.close()

    print_rows(
        rounds,
        [
            ("raw Pipe round trip, send_bytes (floor)", raw_bytes),
            ("raw Pipe round trip, send/recv objects", raw_objects),
            ("dedup-hit call, both registrars in one process", in_process),
            ("dedup-hit call across processes (target <= 3x)", cross),
            ("send_status over 3 process hops (target <= 1000 us)", status),
            ("SIGKILL of provider -> call in flight fails (10 kills)", killed),
        ],
    )
    if pairs:
        paired_rows(pairs)
    print_cpu()


def print_cpu() -> None:
    """The CPU rows (`CPU`), each as a multiple of the floor's."""
    floor = CPU.get("CPU per raw Pipe round trip, send_bytes (floor)")
    if not floor:
        return
    print()
    print("CPU time per round trip, every thread of both processes (us; ratio to the floor's)")
    print()
    _harness.head(None, ["measurement", "CPU us", "ratio"])
    for name, seconds in CPU.items():
        print(f"| {name} | {seconds * 1e6:9.1f} | {seconds / floor:6.2f}x |")


if __name__ == "__main__":
    main()
