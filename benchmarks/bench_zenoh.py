"""Zenoh benchmark: rr_actors across two hosts next to a raw Zenoh `get` between the same two.

Run: `python benchmarks/bench_zenoh.py [--rounds N] [--kills N] [--cuts N] [--only raw]`. The two
hosts are two Linux network namespaces joined by a veth pair (`tests/support/hosts.py`), which needs
root; without root only the loopback rows run. Everything is measured in one run, so the
ratios are comparable:

* the floor: a raw Zenoh `get` round trip (a queryable that echoes 200 bytes) between two
  processes on loopback and between the two namespaces; next to it a raw put/subscribe
  ping-pong between the same two, the pattern the carrier uses (one-way puts on
  publishers as its outboxes declare them, the echo put from Zenoh's callback, the
  answer handed to the waiting thread); a raw liveliness token's end seen
  from the other host after a SIGKILL of its process, and after a link cut (lease 1 s);
* rr_actors over Zenoh (issue 22's `rr.ZenohNetwork`; these rows run once `rr_actors` has
  it, and say so when it has not): a dedup-hit `call` to a registrar on the other host
  (target: <= 2x the raw get between the same two), `send_status` over 3 hops across hosts,
  from a SIGKILL of a remote manager to its calls failing (target: < 50 ms), and from a link
  cut to the calls failing (target: the lease); and, paired round by round with a raw get
  to a queryable in the provider's process over the same two sessions (the floor of the
  same seconds, so the ratio holds under load), the dedup hit again (target: <= 1.5x);
* a reference: the AF_UNIX carrier's dedup-hit `call` across two processes of one host (the
  carrier of `bench_transport.py`), against the loopback floor.

Each host's workers are fresh interpreters started inside its namespace; the functions below
run in them (sent with cloudpickle), and every time is taken with `time.monotonic` or
`time.perf_counter`, one clock for every namespace of the machine.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import _harness

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # the repository: tests.support

from tests.support import hosts  # noqa: E402 (tests/support/hosts.py: the two-host harness)

PORT = 7447
"""The Zenoh port inside each namespace (a namespace has its own ports: no clash)."""

LEASE = 1.0
"""Seconds of silence after which a peer counts as gone (the default of `rr.ZenohNetwork`)."""

SYSTEM = "bench"

KEY = "rr/bench/echo"


# -- raw Zenoh --------------------------------------------------------------------------------


def raw_pair(
    server: hosts.Host, client: hosts.Host, port: int
) -> tuple[hosts.Worker, hosts.Worker]:
    """A raw Zenoh peer on `server` (echo queryable, a token) and one on `client` that sees it."""
    near, far = server.spawn(), client.spawn()
    near.call(hosts.zenoh_open, listen=[server.endpoint(port)], lease=LEASE, timeout=30)
    near.call(hosts.zenoh_echo, KEY, timeout=10)
    near.call(hosts.zenoh_token, "rr/bench/alive", timeout=10)
    far.call(hosts.zenoh_open, connect=[server.endpoint(port)], lease=LEASE, timeout=30)
    far.call(hosts.zenoh_watch, "rr/bench/alive", timeout=10)
    kind, _, _ = far.call(hosts.zenoh_next_event, 15.0, timeout=20)
    if kind != "put":
        raise RuntimeError("the raw peers did not meet")
    return near, far


def raw_round_trips(
    server: hosts.Host, client: hosts.Host, port: int, rounds: int
) -> tuple[list[float], list[float]]:
    """A raw `get` round trip, and a raw put/subscribe ping-pong, between the same two."""
    near, far = raw_pair(server, client, port)
    try:
        gets = far.call(hosts.zenoh_round_trips, KEY, rounds, timeout=600)
        near.call(put_echo, f"{KEY}/ping", f"{KEY}/pong", timeout=10)
        puts = far.call(put_round_trips, f"{KEY}/ping", f"{KEY}/pong", rounds, timeout=600)
        return gets, puts
    finally:
        far.stop()
        near.stop()


def _publisher(session: Any, key: str) -> Any:
    """A publisher as the carrier's outboxes make them (reliable, BLOCK, express)."""
    import zenoh  # noqa: PLC0415

    return session.declare_publisher(
        key,
        congestion_control=zenoh.CongestionControl.BLOCK,
        express=True,
        reliability=zenoh.Reliability.RELIABLE,
    )


def put_echo(ping: str, pong: str) -> None:
    """In a worker: put every sample of `ping` back on `pong`, from Zenoh's callback."""
    session = hosts.KEPT["session"]
    publisher = _publisher(session, pong)
    subscriber = session.declare_subscriber(
        ping, lambda sample: publisher.put(sample.payload.to_bytes())
    )
    hosts.KEPT.setdefault("kept", []).extend([publisher, subscriber])


def put_round_trips(ping: str, pong: str, rounds: int, warmup: int = 100) -> list[float]:
    """In a worker: seconds per put on `ping` until its echo on `pong` wakes this thread
    (the carrier's pattern: one-way puts, the answer handed over from Zenoh's callback)."""
    import queue  # noqa: PLC0415

    session = hosts.KEPT["session"]
    answers: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    subscriber = session.declare_subscriber(pong, lambda s: answers.put(s.payload.to_bytes()))
    publisher = _publisher(session, ping)
    payload = b"x" * 200
    try:
        deadline = time.monotonic() + 15
        while True:  # until the routes are there both ways (earlier puts are dropped)
            publisher.put(payload)
            try:
                answers.get(timeout=0.2)
                break
            except queue.Empty:
                if time.monotonic() > deadline:
                    raise RuntimeError("the put echo never answered") from None
        samples = []
        for number in range(warmup + rounds):
            start = time.perf_counter()
            publisher.put(payload)
            answers.get(timeout=5)
            if number >= warmup:
                samples.append(time.perf_counter() - start)
        return samples
    finally:
        publisher.undeclare()
        subscriber.undeclare()


def raw_kills(two: hosts.TwoHosts, repeats: int) -> list[float]:
    """Seconds from a SIGKILL of the token's process on a to its end seen from b."""
    samples = []
    for _ in range(repeats):
        near, far = raw_pair(two.a, two.b, PORT)
        try:
            start = time.monotonic()
            os.kill(near.pid, signal.SIGKILL)
            samples.append(next_change(far, "delete") - start)
        finally:
            far.stop()
            near.kill()
    return samples


def raw_cuts(two: hosts.TwoHosts, repeats: int) -> tuple[list[float], list[float]]:
    """Seconds from a link cut to the token's end seen from b, and from the link up again
    to the token back (Zenoh reconnects by itself)."""
    gone, back = [], []
    for _ in range(repeats):
        near, far = raw_pair(two.a, two.b, PORT)
        try:
            start = time.monotonic()
            two.link_down()
            gone.append(next_change(far, "delete") - start)
            start = time.monotonic()
            two.link_up()
            back.append(next_change(far, "put") - start)
        finally:
            two.link_up()
            far.stop()
            near.stop()
    return gone, back


def next_change(worker: hosts.Worker, expected: str) -> float:
    """When the next liveliness change seen by `worker` happened; it must be `expected`."""
    kind, _, seen = worker.call(hosts.zenoh_next_event, 30.0, timeout=40)
    if kind != expected:
        raise RuntimeError(f"expected a token's {expected}, saw its {kind}")
    return seen


# -- rr_actors over Zenoh (issue 22) -------------------------------------------------------------
#
# Written against the public API of issue 22 before its carrier landed:
#     net = rr.ZenohNetwork(system=, listen=, connect=, tls=None, lease=)
#     rr.ResourceRegistrar.start(config, setup=..., network=net)
# (`hosts.rr_join`, `hosts.rr_start`). Each function below runs in a worker: one `ZenohNetwork`
# per worker process (a process belongs to one system), kept in the worker's `hosts.KEPT` with
# its registrars.


def setup_echo(registrar: Any) -> None:
    registrar.register_server(
        "echo", load=lambda request: {"resource": request}, unload=lambda _q, _r: None
    )


def setup_hang(registrar: Any) -> None:
    """`hang` blocks its load; a load of `started` returns once a `hang` load runs."""
    started = threading.Event()

    def hang(_request: Any) -> Any:
        started.set()
        threading.Event().wait(60)

    registrar.register_server("echo", load=lambda r: r, unload=lambda _q, _r: None)
    registrar.register_server("hang", load=hang, unload=lambda _q, _r: None)
    registrar.register_server(
        "started", load=lambda _request: started.wait(10), unload=lambda _q, _r: None
    )


def agent_setup(provider: str) -> Callable[[Any], None]:
    """The agent's `composite` server depends on the provider's `echo` (a dependency)."""

    def setup(registrar: Any) -> None:
        def load(request: Any) -> Any:
            return registrar.call(provider, "echo", request).response

        registrar.register_server("composite", load=load, unload=lambda _q, _r: None)

    return setup


def timed(fn: Callable[[], Any], rounds: int, warmup: int = 100) -> list[float]:
    """Seconds per call of `fn`, `rounds` times after `warmup` untimed calls."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(rounds):
        start = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - start)
    return samples


def rr_events_unlogged() -> None:
    """In a worker: rr_actors' events not logged, as by default.

    `hosts.rr_join` keeps the `rr_actors` logger's records from INFO up for the tests
    (`hosts.rr_logs`), which turns on the INFO line of every event: a dedup hit then builds
    and logs two of them (`ConsumerAdded` in the provider, `CallAnswered` in the consumer) and
    wakes the consumer's registrar actor to publish its own. A program that leaves logging
    alone pays none of that, so the rows measure without it (the link watch's lines, on
    the `rr_actors` logger itself, are still kept).
    """
    import logging  # noqa: PLC0415

    logging.getLogger("rr_actors.events").setLevel(logging.WARNING)


def rr_dedup_hits(consumer: str, provider: str, rounds: int) -> list[float]:
    registrar = hosts.KEPT["registrars"][consumer]
    ids: list[str] = []

    def once() -> None:
        ids.append(registrar.call(provider, "echo", {"cam": 1}).id)

    samples = timed(once, rounds)
    for query_id in ids:
        registrar.unload(query_id)
    return samples


def rr_raw_echo(key: str) -> None:
    """In a worker: a raw queryable that echoes on `key`, on its `ZenohNetwork`'s own session."""
    hosts.KEPT["session"] = hosts.KEPT["network"].services().session
    hosts.zenoh_echo(key)


def rr_paired(
    consumer: str, provider: str, key: str, rounds: int
) -> tuple[list[float], list[float]]:
    """In a worker: raw gets on `key` and dedup hits on `provider`, one of each per round
    (their order alternating), on the same session and link: both see the same load.

    Returns:
        Seconds per get and seconds per call.
    """
    registrar = hosts.KEPT["registrars"][consumer]
    session = hosts.KEPT["network"].services().session
    payload = b"x" * 200
    ids: list[str] = []

    def get() -> None:
        for reply in session.get(key, payload=payload, timeout=5.0):
            if reply.ok is None:
                raise LookupError(f"an error reply to a get on {key!r}")

    def call() -> None:
        ids.append(registrar.call(provider, "echo", {"cam": 1}).id)

    for _ in range(100):  # warm-up
        get()
        call()
    gets, calls = [], []
    for number in range(rounds):
        for fn, samples in ((get, gets), (call, calls))[:: 1 if number % 2 else -1]:
            start = time.perf_counter()
            fn()
            samples.append(time.perf_counter() - start)
    for query_id in ids:
        registrar.unload(query_id)
    return gets, calls


def rr_hold_composite(consumer: str, agent: str) -> str:
    """Load the agent's `composite` and count the statuses it brings (`KEPT["heard"]`)."""
    registrar = hosts.KEPT["registrars"][consumer]
    heard: list[Any] = []
    hosts.KEPT["heard"] = heard
    query = registrar.call(agent, "composite", {"cam": 2}, on_status=lambda _q, u: heard.append(u))
    return str(query.id)


def rr_heard() -> int:
    return len(hosts.KEPT["heard"])


def rr_status_timings(provider: str, rounds: int) -> list[float]:
    """In the provider's worker: time `send_status` of its first `echo` query."""
    import rr_actors as rr  # noqa: PLC0415

    registrar = hosts.KEPT["registrars"][provider]
    query_id = registrar.server_queries("echo")[0].id
    return timed(lambda: registrar.send_status(query_id, rr.Status.UPDATE, "tick"), rounds)


def rr_call_in_flight(consumer: str, provider: str) -> float:
    """Call `hang` on `provider`; `time.monotonic()` when it failed as unavailable."""
    import rr_actors as rr  # noqa: PLC0415

    try:
        hosts.KEPT["registrars"][consumer].call(provider, "hang", "r", timeout=30)
    except rr.RegistrarUnavailableError:
        return time.monotonic()
    raise RuntimeError("the call in flight did not fail as unavailable")


def rr_wait_started(consumer: str, provider: str) -> bool:
    registrar = hosts.KEPT["registrars"][consumer]
    query = registrar.call(provider, "started", None, timeout=10)
    registrar.unload(query.id)  # (held over a cut, it would only add a reconciliation)
    return bool(query.response)


def rr_until_working(consumer: str, provider: str, server: str, timeout: float) -> list[str]:
    """After a healed link: call until a call succeeds, then unload it. What went wrong on
    the way, as the bench reports it instead of failing: "timeout" for a call that timed
    out (sent right after the heal, it got no answer), "revoked" if the successful call's
    id was gone by its unload (released by the reconciliation after the heal)."""
    import rr_actors as rr  # noqa: PLC0415

    registrar = hosts.KEPT["registrars"][consumer]
    deadline = time.monotonic() + timeout
    trouble = []
    while True:
        try:
            query = registrar.call(provider, server, {"probe": 1}, timeout=2)
        except (rr.UnknownRegistrarError, rr.RegistrarUnavailableError, rr.CallTimeoutError) as exc:
            if time.monotonic() > deadline:
                raise
            if isinstance(exc, rr.CallTimeoutError):
                trouble.append("timeout")
            continue
        try:
            registrar.unload(query.id)
        except rr.UnknownQueryError:
            trouble.append("revoked")
        return trouble


@contextlib.contextmanager
def rr_worker(
    host: hosts.Host, listen: list[str], connect: list[str], *names: tuple[str, Any]
) -> Iterator[hosts.Worker]:
    """A worker on `host` with its network and the registrars `(name, setup)`; stopped after."""
    worker = host.spawn()
    try:
        worker.call(hosts.rr_join, system=SYSTEM, listen=listen, connect=connect, timeout=30)
        worker.call(rr_events_unlogged, timeout=10)
        for name, setup in names:
            worker.call(hosts.rr_start, name, setup, timeout=30)
        yield worker
    finally:
        if worker.alive:
            with contextlib.suppress(Exception):
                worker.call(hosts.rr_stop, timeout=30)
            worker.stop()


def rr_dedup(
    server: hosts.Host, client: hosts.Host, ports: tuple[int, int], rounds: int
) -> list[float]:
    """ROW "rr_actors cross-host dedup hit": a call from `client` to a registrar on `server`."""
    near, far = server.endpoint(ports[0]), client.endpoint(ports[1])
    with (
        rr_worker(server, [near], [], ("erm", setup_echo)),
        rr_worker(client, [far], [near], ("app", None)) as consumer,
    ):
        consumer.call(hosts.rr_until_answered, "app", "erm", "echo", 30.0, timeout=60)
        return consumer.call(rr_dedup_hits, "app", "erm", rounds, timeout=600)


def rr_dedup_paired(
    server: hosts.Host, client: hosts.Host, ports: tuple[int, int], rounds: int
) -> tuple[list[float], list[float]]:
    """ROWS "raw Zenoh get between the two rr_actors processes, paired" and "rr_actors
    cross-host dedup hit, paired": a get to a raw queryable in the provider's process and a
    dedup hit to its registrar, one of each per round, from the consumer's process."""
    near, far = server.endpoint(ports[0]), client.endpoint(ports[1])
    with (
        rr_worker(server, [near], [], ("erm", setup_echo)) as provider,
        rr_worker(client, [far], [near], ("app", None)) as consumer,
    ):
        provider.call(rr_raw_echo, PAIRED_KEY, timeout=10)
        consumer.call(hosts.rr_until_answered, "app", "erm", "echo", 30.0, timeout=60)
        gets: list[float]
        calls: list[float]
        gets, calls = consumer.call(rr_paired, "app", "erm", PAIRED_KEY, rounds, timeout=600)
        return gets, calls


PAIRED_KEY = "bench/paired/echo"
"""The raw queryable's key in `rr_dedup_paired` (outside `rr/`: no registrar's key)."""


def rr_status(two: hosts.TwoHosts, rounds: int) -> list[float]:
    """ROW "status over 3 hops across hosts": provider (a) -> agent (b) -> consumer (a)."""
    a, b = two.a.endpoint(PORT), two.b.endpoint(PORT)
    with (
        rr_worker(two.a, [a], [], ("provider", setup_echo), ("main", None)) as near,
        rr_worker(two.b, [b], [a], ("agent", agent_setup("provider"))),
    ):
        near.call(hosts.rr_until_answered, "main", "agent", "composite", 30.0, timeout=60)
        near.call(rr_hold_composite, "main", "agent", timeout=30)
        samples = near.call(rr_status_timings, "provider", rounds, timeout=600)
        heard = near.call(rr_heard, timeout=10)
        if heard < rounds:
            raise RuntimeError(f"only {heard} statuses reached the consumer")
        return samples


_victims = itertools.count()


def rr_failures(two: hosts.TwoHosts, repeats: int, *, cut: bool) -> tuple[list[float], list[float]]:
    """ROWS "SIGKILL of a remote manager to calls failing", "link cut to calls failing" and
    "link up to calls working".

    Seconds from the SIGKILL of a provider's process on host a (or from the link cut) to
    the failure of a call in flight to it from host b; after a cut, also from the link up
    again to the first call that succeeds (an empty list for kills).
    """
    b = two.b.endpoint(PORT)
    failed, working = [], []
    with rr_worker(two.b, [b], [], ("app", None)) as consumer:
        for _ in range(repeats):
            name = f"victim-{next(_victims)}"
            listen = [two.a.endpoint(PORT + 1)]
            with rr_worker(two.a, listen, [b], (name, setup_hang)) as victim:
                consumer.call(hosts.rr_until_answered, "app", name, "echo", 30.0, timeout=60)
                in_flight: Future[float] = consumer.submit(rr_call_in_flight, "app", name)
                if not consumer.call(rr_wait_started, "app", name, timeout=30):
                    raise RuntimeError("the load never started")
                start = time.monotonic()
                if cut:
                    two.link_down()
                else:
                    os.kill(victim.pid, signal.SIGKILL)
                try:
                    failed.append(in_flight.result(30) - start)
                finally:
                    if cut:
                        start = time.monotonic()
                        two.link_up()
                if cut:
                    AFTER_HEALS.extend(
                        consumer.call(rr_until_working, "app", name, "echo", 30.0, timeout=60)
                    )
                    working.append(time.monotonic() - start)
    return failed, working


AFTER_HEALS: list[str] = []
"""What went wrong right after the heals (`rr_until_working`): "timeout", "revoked"."""


# -- the AF_UNIX carrier (a reference row) ----------------------------------------------------


def unix_dedup(rounds: int) -> list[float]:
    """ROW "AF_UNIX carrier cross-process dedup hit": from this process to a registrar in
    another process of the same host, over the AF_UNIX carrier (as `bench_transport.py`)."""
    import multiprocessing  # noqa: PLC0415
    import uuid  # noqa: PLC0415

    import bench_transport  # noqa: PLC0415 (benchmarks/: this script's directory)

    import rr_actors as rr  # noqa: PLC0415
    from rr_actors._registrar import Served  # noqa: PLC0415
    from rr_actors._transport.unix.system import System  # noqa: PLC0415

    ctx = multiprocessing.get_context("forkserver")
    suffix = uuid.uuid4().hex[:6]
    system = System.create()
    try:
        consumer = rr.ResourceRegistrar.start(f"main-{suffix}")
        try:
            system.serve(Served(consumer))
            provider = f"provider-{suffix}"
            with bench_transport.registrar_process(
                ctx, system.address, provider, bench_transport.setup_echo
            ):
                return bench_transport.dedup_hits(consumer, provider, rounds)
        finally:
            consumer.stop()
    finally:
        system.close()


# -- report -----------------------------------------------------------------------------------


def stats(samples: list[float]) -> tuple[float, float]:
    """Median and p90 (nearest rank: the largest sample when there are few)."""
    return _harness.median(samples), _harness.percentile(samples, 0.9)


Trips = list[tuple[str, list[float], list[float]]]
"""Round-trip rows: (name, samples, the samples of the floor the ratio divides by)."""

Ends = list[tuple[str, list[float], str]]
"""Failure-detection rows: (name, samples, target)."""


def measure_loopback(rounds: int, *, with_rr: bool) -> Trips:
    with hosts.local_host() as local:
        ports = (hosts.free_port(), hosts.free_port())
        floor, puts = raw_round_trips(local, local, ports[0], rounds)
        trips = [
            ("raw Zenoh get, loopback (floor)", floor, floor),
            ("raw Zenoh put ping-pong, loopback", puts, floor),
        ]
        if with_rr:
            ports = (hosts.free_port(), hosts.free_port())
            trips.append(
                ("rr_actors dedup-hit call, loopback", rr_dedup(local, local, ports, rounds), floor)
            )
            trips.append(
                ("AF_UNIX carrier dedup hit, 2 processes (reference)", unix_dedup(rounds), floor)
            )
    return trips


def measure_hosts(rounds: int, kills: int, cuts: int, *, with_rr: bool) -> tuple[Trips, Ends]:
    with hosts.TwoHosts() as two:
        floor, puts = raw_round_trips(two.a, two.b, PORT, rounds)
        trips = [
            ("raw Zenoh get, across the veth (floor)", floor, floor),
            ("raw Zenoh put ping-pong, across the veth", puts, floor),
        ]
        gone, back = raw_cuts(two, cuts)
        ends = [
            ("raw: SIGKILL -> token gone", raw_kills(two, kills), ""),
            ("raw: link cut -> token gone", gone, ""),
            ("raw: link up -> token back", back, ""),
        ]
        if with_rr:
            dedup = rr_dedup(two.a, two.b, (PORT, PORT), rounds)
            trips.append(("rr_actors cross-host dedup hit (target <= 2x)", dedup, floor))
            gets, calls = rr_dedup_paired(two.a, two.b, (PORT, PORT), rounds)
            trips.append(
                ("raw Zenoh get between the rr_actors processes, paired (floor)", gets, gets)
            )
            trips.append(("rr_actors cross-host dedup hit, paired (target <= 1.5x)", calls, gets))
            trips.append(("send_status over 3 hops across hosts", rr_status(two, rounds), floor))
            killed, _ = rr_failures(two, kills, cut=False)
            ends.append(("SIGKILL of a remote manager -> call fails", killed, "< 50 ms"))
            cut, healed = rr_failures(two, cuts, cut=True)
            ends.append(("link cut -> call fails", cut, f"the lease, {LEASE:g} s"))
            ends.append(("link up -> a call works again", healed, "< 10 s"))
    return trips, ends


def report(rounds: int, trips: Trips, ends: Ends) -> None:
    rows = []
    for name, samples, floor in trips:
        median, p90 = stats(samples)
        ratio = median / _harness.median(floor)
        rows.append((name, f"{median * 1e6:.1f}", f"{p90 * 1e6:.1f}", f"{ratio:.2f}x"))
    _harness.print_table(
        f"rounds per row: {rounds}; times in microseconds; ratio = median / the floor's median",
        ("measurement", "median us", "p90 us", "ratio"),
        rows,
    )
    if ends:  # (`--kills 0`, `--cuts 0`: a row without samples is left out)
        _harness.print_table(
            f"failure detection, lease {LEASE:g} s; times in milliseconds",
            ("event -> seen", "runs", "median ms", "max ms", "target"),
            [
                (name, len(v), f"{stats(v)[0] * 1e3:.1f}", f"{max(v) * 1e3:.1f}", target)
                for name, v, target in ends
                if v
            ],
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2000, help="timed round trips per row")
    parser.add_argument("--kills", type=int, default=10, help="SIGKILLs per failure row")
    parser.add_argument("--cuts", type=int, default=3, help="link cuts per failure row")
    parser.add_argument(
        "--only", choices=["raw"], help="measure the raw Zenoh rows only (no rr_actors rows)"
    )
    args = parser.parse_args()
    why_not_hosts = hosts.require_root()
    why_not_rr = None
    if args.only == "raw":
        why_not_rr = "--only raw"
    elif not hosts.has_carrier():
        why_not_rr = "rr_actors has no ZenohNetwork yet (issue 22)"

    trips = measure_loopback(args.rounds, with_rr=why_not_rr is None)
    ends: Ends = []
    if why_not_hosts is None:
        more, ends = measure_hosts(args.rounds, args.kills, args.cuts, with_rr=why_not_rr is None)
        trips += more
    report(args.rounds, trips, ends)
    print()
    if why_not_hosts is not None:
        print(f"not measured across hosts: {why_not_hosts}")
    if why_not_rr is not None:
        print(f"rr_actors rows not measured: {why_not_rr}")
    if AFTER_HEALS:
        print(
            f"right after {args.cuts} heals: {AFTER_HEALS.count('timeout')} calls timed out "
            f"(2 s) before one was answered; {AFTER_HEALS.count('revoked')} answered ids were "
            f"released by the reconciliation before their unload (UnknownQueryError)"
        )


if __name__ == "__main__":
    main()
