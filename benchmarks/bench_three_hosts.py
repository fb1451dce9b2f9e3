"""Three hosts in a line: a call routed through a third host's router, and its cuts.

Run (as root): `python benchmarks/bench_three_hosts.py [--rounds N] [--cuts N]`. Three Linux
network namespaces `a` - `b` - `c` (`tests/support/hosts.py`'s `ThreeHosts`: two veth pairs, no
link a-c), each with one `rr.ZenohNetwork` of mutual TLS: `b` listens on both of its
addresses, `a` and `c` dial only `b`. Measured, with the default lease (1 s):

* a dedup-hit `call` from `a` to a registrar on `b` (one link) and to one on `c` (two
  links, through `b`'s router): the cost of the hop;
* per cut of the veth b-c (no FIN): from the cut to `a`'s call in flight to `c` failing
  (`RegistrarUnavailableError`), and from the veth up again to `a`'s first call to `c`
  answered; the same for a cut of the veth a-b (`a`'s own link), for comparison.

`--managers N` (issue 69, goal 6) measures instead a system of 3 x N managers: the same
three hosts (`b` the one router `a` and `c` dial), each starting a `Supervisor` of N
managers (`--kind thread`, or `process`: each manager process then joins through its
host's router, a Zenoh session of its own) at the same time. Measured from that moment:
each host's `start()` returning; every host seeing all 3 x N names served
(`ZenohNetwork.wait_for`); and `a` answered by one call to each of the 3 x N managers (N
on `a`, N on `b` over one link, N on `c` through `b`'s router). Counted: `wait_for`s and
calls that failed (each retried until `--bound`), and the lines of Zenoh's own log
(`RUST_LOG=warn`, in every worker's output) that speak of a timeout or of a refused or
closed session.

Every time is taken with `time.monotonic` or `time.perf_counter`, one clock for every
namespace of the machine. Without root nothing is measured (one line says why).
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import _harness

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # the repository: tests.support

from tests.support import hosts, pki  # noqa: E402 (the namespaces, the certificates)

PORT = 7447
SYSTEM = "bench"
MEMBERS = ["alpha", "bravo", "charlie"]


# -- what runs in the workers ------------------------------------------------------------------


def setup_provider(registrar: Any) -> None:
    """`echo` answers its request; `hang` blocks until released (a call in flight)."""
    hosts.KEPT.setdefault("gate", threading.Event())
    hosts.KEPT.setdefault("started", threading.Event())

    def hang(request: Any) -> Any:
        gate = hosts.KEPT["gate"]  # (the one of this cut: `release` arms a new one)
        hosts.KEPT["started"].set()
        gate.wait(30)
        return request

    registrar.register_server("echo", load=lambda request: request, unload=lambda _q, _r: None)
    registrar.register_server("hang", load=hang, unload=lambda _q, _r: None)


def release() -> None:
    """Open the hang gate (and arm a new one for the next cut)."""
    hosts.KEPT["gate"].set()
    hosts.KEPT["gate"] = threading.Event()
    hosts.KEPT["started"].clear()


def hang_started(timeout: float) -> bool:
    return bool(hosts.KEPT["started"].wait(timeout))


def dedup_hits(consumer: str, provider: str, rounds: int, warmup: int = 100) -> list[float]:
    """Seconds per dedup-hit call of `provider`/echo (one resource held the whole time)."""
    registrar = hosts.KEPT["registrars"][consumer]
    held = registrar.call(provider, "echo", "x", timeout=10)
    samples = []
    try:
        for n in range(warmup + rounds):
            start = time.perf_counter()
            query = registrar.call(provider, "echo", "x", timeout=10)
            took = time.perf_counter() - start
            registrar.unload(query.id)
            if n >= warmup:
                samples.append(took)
    finally:
        registrar.unload(held.id)
    return samples


def call_in_flight(consumer: str, provider: str) -> float:
    """A call of `provider`/hang that must fail: when it failed (`time.monotonic`)."""
    import rr_actors as rr  # noqa: PLC0415

    try:
        hosts.KEPT["registrars"][consumer].call(provider, "hang", "r", timeout=30)
    except rr.RegistrarUnavailableError:
        return time.monotonic()
    raise RuntimeError("the call in flight did not fail")


def setup_echo(registrar: Any) -> None:
    """Each of the many managers: one server, `echo`."""
    registrar.register_server("echo", load=lambda request: request, unload=lambda _q, _r: None)


def start_many(prefix: str, count: int, kind: str, bound: float) -> float:
    """A `Supervisor` of `count` managers `<prefix>0`... on this worker's network; when its
    `start()` returned (`time.monotonic`)."""
    import rr_actors as rr  # noqa: PLC0415

    specs = [
        rr.ManagerSpec(f"{prefix}{n}", setup_echo, isolation=kind, start_timeout=bound)
        for n in range(count)
    ]
    supervisor = rr.Supervisor(specs, network=hosts.KEPT["network"], name=f"many-{prefix}")
    hosts.KEPT["many"] = supervisor
    supervisor.start()
    return time.monotonic()


def running_many() -> int:
    """How many of this worker's managers run now (its supervisor may still be starting)."""
    supervisor = hosts.KEPT.get("many")
    if supervisor is None:
        return 0
    return sum(child.state == "running" for child in supervisor.which_children())


def stop_many() -> None:
    supervisor = hosts.KEPT.pop("many", None)
    if supervisor is not None:
        supervisor.stop()


def all_served(names: list[str], bound: float) -> tuple[float, int]:
    """Wait until this host sees each of `names` served; when the last was
    (`time.monotonic`) and how many waits (10 s each at most) ran out first."""
    import rr_actors as rr  # noqa: PLC0415

    network = hosts.KEPT["network"]
    deadline = time.monotonic() + bound
    ran_out = 0
    for name in names:
        while True:
            try:
                network.wait_for(name, timeout=max(0.1, min(10.0, deadline - time.monotonic())))
                break
            except rr.RegistrarUnavailableError:
                ran_out += 1
                if time.monotonic() > deadline:
                    raise
    return time.monotonic(), ran_out


def call_each(registrar: Any, names: list[str], bound: float) -> tuple[float, dict[str, int]]:
    """One call answered by each of `names` (each unloaded after); when the last was
    (`time.monotonic`) and the failed attempts by error (each retried until `bound`)."""
    import rr_actors as rr  # noqa: PLC0415

    deadline = time.monotonic() + bound
    failed: Counter[str] = Counter()
    for name in names:
        while True:
            try:
                query = registrar.call(name, "echo", name, timeout=10.0)
                registrar.unload(query.id)
                break
            except rr.RrError as exc:
                failed[type(exc).__name__] += 1
                if time.monotonic() > deadline:
                    raise
    return time.monotonic(), dict(failed)


ZENOH_TROUBLE = re.compile(
    r"time(d)? ?out|refus|max_sessions|too many|closing session|is closed|close message", re.I
)
"""What a line of Zenoh's own log (`RUST_LOG=warn`) says when a session or an accept failed."""


def kind_of(line: str) -> str:
    """A log line without its colours, time, thread, ids and numbers: what kind it is."""
    plain = re.sub(r"\x1b\[[0-9;]*m", "", line)
    plain = re.sub(r"^\S+Z\s+", "", plain)  # (the time)
    plain = re.sub(r"ThreadId\(\d+\)", "", plain)
    return re.sub(r"[0-9a-f]{6,}(:\d+)*|\d+", "#", plain).strip()[:160]


def zenoh_trouble(net: hosts.ThreeHosts) -> tuple[dict[str, list[str]], int]:
    """Per host, the lines of its workers' output that `ZENOH_TROUBLE` matches; how many
    lines they wrote in all."""
    found: dict[str, list[str]] = {}
    written = 0
    for name in "abc":
        lines = []
        for log in sorted(net.directory.glob(f"{name}-*.log")):
            text = log.read_text(errors="replace").splitlines()
            written += len(text)
            lines += [line for line in text if ZENOH_TROUBLE.search(line)]
        found[name] = lines
    return found, written


def rss_mib(where: dict[str, hosts.Host]) -> dict[str, str]:
    """Each host's worker's resident memory (MiB; Linux `/proc`), and its pid."""
    found = {}
    for h, host in where.items():
        pid = host.worker.pid
        status = Path(f"/proc/{pid}/status").read_text()
        kib = int(re.search(r"VmRSS:\s+(\d+)", status)[1])  # type: ignore[index]
        found[h] = f"{kib // 1024} (pid {pid})"
    return found


def many(managers: int, kind: str, bound: float) -> None:
    """Three hosts of `managers` managers each: until served and answered (goal 6)."""
    os.environ.setdefault("RUST_LOG", "warn")  # (the workers inherit it: Zenoh's own log)
    with line() as (net, a):
        where = {"a": net.a, "b": net.b, "c": net.c}
        names = [f"{h}{n}" for h in where for n in range(managers)]
        try:
            began = time.monotonic()
            starting = {
                h: host.worker.submit(start_many, h, managers, kind, bound)
                for h, host in where.items()
            }
            started = {}
            while not all(future.done() for future in starting.values()):
                with suppress(TimeoutError):  # (a look every 30 s, to stderr)
                    starting[next(h for h in where if not starting[h].done())].result(30)
                running = {h: host.call(running_many, timeout=60) for h, host in where.items()}
                print(
                    f"# {time.monotonic() - began:.0f} s: running {running}; "
                    f"worker RSS (MiB) {rss_mib(where)}; Zenoh trouble lines so far "
                    f"{ {h: len(lines) for h, lines in zenoh_trouble(net)[0].items()} }",
                    file=sys.stderr,
                )
                if time.monotonic() - began > bound:
                    raise TimeoutError(f"not every tree started within {bound:g} s: {running}")
            for h, future in starting.items():
                started[h] = future.result() - began
                print(f"# {h}: start() returned after {started[h]:.1f} s", file=sys.stderr)
            seeing = {h: host.worker.submit(all_served, names, bound) for h, host in where.items()}
            served = {h: future.result(bound + 60) for h, future in seeing.items()}
            print(
                f"# every host sees every name: {time.monotonic() - began:.1f} s", file=sys.stderr
            )
            answered, failed = a.call(
                hosts.rr_run, "app", call_each, names, bound, timeout=bound + 60
            )
        finally:
            for host in where.values():  # (one that does not stop in 2 min is killed)
                with suppress(Exception):
                    host.call(stop_many, timeout=120)
        trouble, written = zenoh_trouble(net)
    _harness.print_table(
        f"## {len(names)} managers on three hosts ({managers} {kind} managers each; b routes)",
        ("host", "start() returned (s)", "all names served here (s)", "waits that ran out"),
        [(h, f"{started[h]:.1f}", f"{served[h][0] - began:.1f}", served[h][1]) for h in where],
    )
    print()
    print(
        f"all {len(names)} calls from a answered: {answered - began:.1f} s after the start "
        f"({answered - max(at for at, _ in served.values()):.1f} s after the last host saw "
        f"every name); failed attempts: {sum(failed.values())} {failed or ''}"
    )
    counts = ", ".join(f"{h} {len(lines)}" for h, lines in trouble.items())
    print(
        f"Zenoh log lines of timeouts, refusals or closed sessions: {counts} "
        f"(of {written} lines the workers wrote)"
    )
    kinds = Counter(kind_of(line) for lines in trouble.values() for line in lines)
    for what, seen in kinds.most_common(5):
        print(f"  {seen} x {what}")
    print(_harness.header("the end"))


# -- the test process's side -------------------------------------------------------------------


def tls_of(net: hosts.ThreeHosts, ca: Any, name: str, *addresses: str) -> dict[str, Any]:
    cert, key = pki.issue(net.directory, name, addresses, ca=ca)
    return {"ca": str(ca[0]), "cert": str(cert), "key": str(key), "members": MEMBERS}


@contextmanager
def line() -> Iterator[tuple[hosts.ThreeHosts, hosts.Worker]]:
    """The three hosts, `hub` served on `b`, `erm` on `c`, `app` on `a`; `a`'s worker."""
    with hosts.ThreeHosts() as net:
        ca = pki.make_ca(net.directory, SYSTEM)
        b_for_a, b_for_c = f"tls/{net.b.address}:{PORT}", f"tls/{net.b_toward_c}:{PORT}"
        joins = [
            (net.b, [b_for_a, b_for_c], [], ("bravo", net.b.address, net.b_toward_c), "hub"),
            (net.c, [], [b_for_c], ("charlie", net.c.address), "erm"),
            (net.a, [], [b_for_a], ("alpha", net.a.address), "app"),
        ]
        for host, listen, connect, names, registrar in joins:
            host.call(
                hosts.rr_join,
                system=SYSTEM,
                listen=listen,
                connect=connect,
                tls=tls_of(net, ca, *names),
                timeout=30,
            )
            setup = None if registrar == "app" else setup_provider
            host.call(hosts.rr_start, registrar, setup, timeout=30)
        net.a.call(hosts.rr_until_answered, "app", "erm", "echo", 20.0, timeout=60)
        try:
            yield net, net.a.worker
        finally:
            for host in (net.a, net.c, net.b):
                with suppress(Exception):
                    host.call(hosts.rr_stop, timeout=30)


def cut_and_heal(
    net: hosts.ThreeHosts, pair: tuple[str, str], cuts: int
) -> tuple[list[float], list[float]]:
    """Per cut of `pair`: seconds to `a`'s call in flight to `erm` failing; seconds from
    the link up again to `a`'s next call of `erm` answered."""
    failed, healed = [], []
    for _ in range(cuts):
        in_flight = net.a.worker.submit(call_in_flight, "app", "erm")
        if not net.c.call(hang_started, 10.0, timeout=15):
            raise RuntimeError("the call in flight never reached erm")
        cut = time.monotonic()
        net.link_down(*pair)
        failed.append(in_flight.result(10) - cut)
        up = time.monotonic()
        net.link_up(*pair)
        net.c.call(release, timeout=10)
        net.a.call(hosts.rr_until_answered, "app", "erm", "echo", 20.0, timeout=30)
        healed.append(time.monotonic() - up)
    return failed, healed


def stats(samples: list[float]) -> tuple[float, float, float]:
    """Median, p90 (nearest rank) and the largest."""
    return _harness.median(samples), _harness.percentile(samples, 0.9), max(samples)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=1000, help="timed calls per row")
    parser.add_argument("--cuts", type=int, default=5, help="cuts per link")
    parser.add_argument("--managers", type=int, help="instead: managers per host (goal 6)")
    parser.add_argument("--kind", choices=["thread", "process"], default="thread")
    parser.add_argument("--bound", type=float, default=600.0, help="seconds each step may take")
    args = parser.parse_args()
    why_not = hosts.require_root()
    if why_not is not None:
        print(f"nothing measured: {why_not}")
        return
    if args.managers:
        many(args.managers, args.kind, args.bound)
        return
    with line() as (net, a):
        direct = a.call(dedup_hits, "app", "hub", args.rounds, timeout=600)
        routed = a.call(dedup_hits, "app", "erm", args.rounds, timeout=600)
        ends = {pair: cut_and_heal(net, pair, args.cuts) for pair in (("b", "c"), ("a", "b"))}
    _harness.print_table(
        f"rounds per row: {args.rounds}; lease 1 s; mutual TLS",
        ("dedup-hit call from a", "median us", "p90 us", "max us"),
        [
            (name, *(f"{x * 1e6:.1f}" for x in stats(samples)))
            for name, samples in (("to b (one link)", direct), ("to c, through b's router", routed))
        ],
    )
    rows = []
    for (left, right), (failed, healed) in ends.items():
        for what, samples in (("cut", failed), ("up again", healed)):
            median, _, worst = stats(samples)
            seen = "call in flight to c fails" if what == "cut" else "a call to c answered"
            rows.append(
                (
                    f"veth {left}-{right} {what} -> {seen}",
                    f"{median * 1e3:.1f}",
                    f"{worst * 1e3:.1f}",
                )
            )
    _harness.print_table(
        f"cuts per link: {args.cuts}", ("event -> seen at a", "median ms", "max ms"), rows
    )


if __name__ == "__main__":
    main()
