"""Zenoh TLS benchmark: mutual TLS against plain TCP across hosts; refused handshakes.

Run, as root: `taskset -c 0 python benchmarks/bench_zenoh_tls.py [--rounds N] [--handshakes N]
[--clients N] [--joins N] [--quiet S] [--interval S] [--cuts N] [--threads N] [--flood S]
[--give-up S] [--without-gate] [--sources N] [--spoof-rate R] [--spoofed N]
[--only trips burst flood spoof]`. The two hosts are two Linux network namespaces joined by a
veth pair, and a third one, the outsider, on a veth of its own to host a (`tests/support/hosts.py`);
without root nothing is measured (it says so). The certificates are made for the run
(`tests/support/pki.py`): a CA, members `robot` (host a, the listener), `operator` and `joiner`
(host b). Everything is measured in one run:

* round trips across the veth, each protocol on its own pair of fresh processes: a raw Zenoh
  `get` (a queryable that echoes 200 bytes; peers, no access control) over plain TCP and over
  mutual TLS, and a dedup-hit `call` from host b to a registrar on host a over
  `rr.ZenohNetwork` with `tls=None` and with `tls=rr.ZenohTLS(...)` (mutual TLS and the
  access control). Ratios: TLS / plain TCP for each, and rr_actors / the raw get of the same
  protocol;
* a burst of refused handshakes (issue 23's bound): `--handshakes` TLS handshakes (200) from
  `--clients` threads at once (20), Python `ssl` in a worker on host b, with a certificate of
  another CA, against host a's `tls/` listener. Around it the member `operator` on host b
  calls the registrar on host a every `--interval` s: its latency p50/p99 before (`--quiet`
  s), during and after (`--quiet` s) the burst (target: every call succeeds, p99 under
  100 ms during it); and a member's time to join, from making its `ZenohNetwork` to its
  first successful call, when quiet and during the burst (target: within 10 s).

* a flood of failed handshakes (issue 29): the outsider's `--threads` threads (4) connect to
  host a's `tls/` port, send a few bytes and close, as fast as they can, no certificate;
  after `--flood` s (2) member b's link to a is cut (`ip link set down` until b has lost
  a) and brought back, `--cuts` times (3) during the flood and as many after it stopped:
  the seconds from the link's return to b's first answered call (the re-join), and b's
  calls on its link in the flood's first seconds. With `--without-gate`, once each also
  with host a's listener kept by Zenoh alone and with only its queue shortened (the
  benchmark's own switch, `gate_mode`: rr_actors has none); those take minutes. Then the
  same flood from `--sources` (32) addresses of host c in turn (issue 40);
* forged SYNs (issue 40): member b goes out of reach (its end of the veth down, so a
  keeps its route to b) until it has lost a; host c sends `--spoof-rate` (13) SYNs a
  second whose source is b's address to a's `tls/` port (`tests/support/spoof.py`),
  `--spoofed` (40) more each time; b's end comes back: the seconds to its first answered
  call, `--cuts` times with the forging going on, `--cuts` times with it stopped before.

Zenoh pauses its TLS accept loop 100 ms after every failed handshake: the burst lasts about
`--handshakes` x 0.1 s, and a member that connects during it waits behind the handshakes
queued before its own. Under load from other processes the ratios move by a quarter between
runs; with every process on one CPU (`taskset -c 0`) they are stable.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import _harness

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # the repository: tests.support
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_zenoh  # noqa: E402 (this directory: the plain-TCP benchmark's helpers)

from tests.support import hosts, pki, spoof  # noqa: E402 (tests/support: harness, certificates)
from tests.support.waiting import wait_for  # noqa: E402

PORT = 7447
"""The first Zenoh port inside each namespace; each pair of processes gets its own."""

LEASE = 1.0

SYSTEM = "bench"

KEY = "rr/bench/echo"

MEMBERS = ["robot", "operator", "joiner"]
"""The system's members: `robot` listens on host a, `operator` and `joiner` are on host b."""

TARGET_P99 = 0.100
"""Seconds: a member's call p99 during the burst (issue 23)."""

TARGET_JOIN = 10.0
"""Seconds: a member's time to join during the burst (issue 23)."""

_ports = itertools.count(PORT)


class Certs:
    """The run's certificate files (in a temporary directory, deleted after the run)."""

    def __init__(self, directory: Path, two: hosts.TwoHosts) -> None:
        ca = pki.make_ca(directory, SYSTEM)
        self.ca = str(ca[0])
        self.files = {}
        for name, host in (("robot", two.a), ("operator", two.b), ("joiner", two.b)):
            cert, key = pki.issue(directory, name, (host.address,), ca=ca)
            self.files[name] = {"ca": self.ca, "cert": str(cert), "key": str(key)}
        other = pki.make_ca(directory / "other", "other")
        cert, key = pki.issue(directory / "other", "intruder", (two.b.address,), ca=other)
        self.intruder = (str(cert), str(key))

    def tls(self, name: str) -> dict[str, Any]:
        """`rr.ZenohTLS`'s keyword arguments for member `name`."""
        return {**self.files[name], "members": MEMBERS}


# -- raw Zenoh over TCP or TLS -----------------------------------------------------------------


def raw_open(
    listen: list[str], connect: list[str], lease: float, tls: dict[str, str] | None
) -> None:
    """In a worker: a raw Zenoh peer (`hosts.KEPT["session"]`), mutual TLS if `tls`."""
    import zenoh  # noqa: PLC0415

    config = hosts.zenoh_config(listen=listen, connect=connect, lease=lease)
    if tls is not None:
        settings = {
            "root_ca_certificate": tls["ca"],
            "listen_private_key": tls["key"],
            "listen_certificate": tls["cert"],
            "connect_private_key": tls["key"],
            "connect_certificate": tls["cert"],
            "enable_mtls": True,
            "verify_name_on_connect": True,
        }
        config.insert_json5("transport/link/tls", json.dumps(settings))
    hosts.KEPT["session"] = zenoh.open(config)


def raw_until_answered(key: str, timeout: float) -> None:
    """In a worker: `get` on `key` until one is answered (the route is there)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            hosts.zenoh_get(key, b"probe", 1.0)
        except LookupError:
            if time.monotonic() > deadline:
                raise
        else:
            return


def raw_gets(two: hosts.TwoHosts, rounds: int, certs: Certs | None) -> list[float]:
    """ROWS "raw Zenoh get": from host b to a queryable on host a, over TCP or TLS."""
    protocol = "tcp" if certs is None else "tls"
    endpoint = two.a.endpoint(next(_ports), protocol)
    near, far = two.a.spawn(), two.b.spawn()
    try:
        tls = None if certs is None else certs.files
        near.call(raw_open, [endpoint], [], LEASE, tls and tls["robot"], timeout=30)
        near.call(hosts.zenoh_echo, KEY, timeout=10)
        far.call(raw_open, [], [endpoint], LEASE, tls and tls["operator"], timeout=30)
        far.call(raw_until_answered, KEY, 30.0, timeout=40)
        return far.call(hosts.zenoh_round_trips, KEY, rounds, timeout=600)
    finally:
        far.stop()
        near.stop()


# -- rr_actors over TCP or TLS ------------------------------------------------------------------


@contextlib.contextmanager
def rr_worker(
    host: hosts.Host,
    listen: list[str],
    connect: list[str],
    tls: dict[str, Any] | None,
    *names: tuple[str, Any],
) -> Iterator[hosts.Worker]:
    """A worker on `host` with its network (TLS if `tls`) and the registrars `(name, setup)`."""
    worker = host.spawn()
    try:
        worker.call(
            hosts.rr_join, system=SYSTEM, listen=listen, connect=connect, tls=tls, timeout=30
        )
        for name, setup in names:
            worker.call(hosts.rr_start, name, setup, timeout=30)
        yield worker
    finally:
        if worker.alive:
            with contextlib.suppress(Exception):
                worker.call(hosts.rr_stop, timeout=30)
            worker.stop()


def rr_dedup(two: hosts.TwoHosts, rounds: int, certs: Certs | None) -> list[float]:
    """ROWS "rr_actors dedup-hit call": from host b to a registrar on host a, TCP or TLS."""
    protocol = "tcp" if certs is None else "tls"
    near = two.a.endpoint(next(_ports), protocol)
    far = two.b.endpoint(next(_ports), protocol)
    robot = None if certs is None else certs.tls("robot")
    operator = None if certs is None else certs.tls("operator")
    with (
        rr_worker(two.a, [near], [], robot, ("erm", bench_zenoh.setup_echo)),
        rr_worker(two.b, [far], [near], operator, ("app", None)) as consumer,
    ):
        consumer.call(hosts.rr_until_answered, "app", "erm", "echo", 30.0, timeout=60)
        return consumer.call(bench_zenoh.rr_dedup_hits, "app", "erm", rounds, timeout=600)


# -- a burst of refused handshakes ----------------------------------------------------------------


def calls_paced(consumer: str, provider: str, seconds: float | None, interval: float) -> Any:
    """In a worker: a dedup-hit call every `interval` s for `seconds` (or until `calls_stop`);
    each call's `(time.monotonic() at its start, seconds, error or None)`. The ids are
    unloaded at the end."""
    import rr_actors as rr  # noqa: PLC0415

    registrar = hosts.KEPT["registrars"][consumer]
    stop = threading.Event()
    if seconds is None:
        hosts.KEPT["calls_stop"] = stop
    held = registrar.call(provider, "echo", {"cam": 1}, timeout=10)  # the calls hit this one
    end = time.monotonic() + seconds if seconds is not None else float("inf")
    samples: list[tuple[float, float, str | None]] = []
    ids = [held.id]
    while not stop.is_set() and time.monotonic() < end:
        start = time.monotonic()
        try:
            ids.append(registrar.call(provider, "echo", {"cam": 1}, timeout=10).id)
            error = None
        except rr.RrError as exc:
            error = type(exc).__name__
        samples.append((start, time.monotonic() - start, error))
        stop.wait(interval)  # the pace of the calls (not a synchronisation)
    for query_id in ids:
        with contextlib.suppress(rr.RrError):
            registrar.unload(query_id)
    return samples


def calls_stop() -> None:
    hosts.KEPT["calls_stop"].set()


def refused_handshakes(
    address: str, port: int, clients: int, total: int, cert: str, key: str
) -> dict[str, Any]:
    """In a worker: `total` TLS handshakes with a non-member's certificate from `clients`
    threads at once; how many the listener refused, and when the burst began and ended."""
    import socket  # noqa: PLC0415
    import ssl  # noqa: PLC0415

    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE  # (the intruder does not care who listens)
    context.load_cert_chain(cert, key)
    started: threading.Event = hosts.KEPT["burst_started"]
    outcomes: list[str] = []
    lock = threading.Lock()
    barrier = threading.Barrier(clients + 1)

    def one() -> str:
        try:
            with (
                socket.create_connection((address, port), timeout=60) as raw,
                context.wrap_socket(raw) as tls,
            ):
                # TLS 1.3: the listener's verdict on our certificate comes after our side
                # of the handshake; read once to receive it
                return "accepted" if tls.recv(1) else "refused"
        except (ssl.SSLError, ConnectionError):
            return "refused"
        except TimeoutError:
            return "timed out"

    def client(count: int) -> None:
        barrier.wait()
        for _ in range(count):
            outcome = one()
            with lock:
                outcomes.append(outcome)

    shares = [total // clients + (1 if i < total % clients else 0) for i in range(clients)]
    threads = [threading.Thread(target=client, args=(n,), daemon=True) for n in shares]
    for thread in threads:
        thread.start()
    barrier.wait()
    began = time.monotonic()
    started.set()
    for thread in threads:
        thread.join()
    return {
        "began": began,
        "ended": time.monotonic(),
        "refused": outcomes.count("refused"),
        "other": len(outcomes) - outcomes.count("refused"),
    }


def burst_prepare() -> None:
    """In the intruder's worker, before `refused_handshakes`: the event it sets as it begins."""
    hosts.KEPT["burst_started"] = threading.Event()


def burst_started(timeout: float) -> bool:
    """In the intruder's worker: whether its burst has begun, waiting up to `timeout`."""
    started: threading.Event = hosts.KEPT["burst_started"]
    return started.wait(timeout)


def join_timed(
    name: str, connect: list[str], tls: dict[str, Any], provider: str, timeout: float
) -> tuple[float, float, float]:
    """In a fresh worker: join the system (a `ZenohNetwork` over TLS, a registrar `name`)
    and call `provider`'s `echo` until a call succeeds; `time.monotonic()` at the start,
    once the registrar is served (its network's Zenoh session open), and at the end."""
    import rr_actors as rr  # noqa: PLC0415

    start = time.monotonic()
    hosts.rr_join(system=SYSTEM, listen=[], connect=connect, tls=tls)
    hosts.rr_start(name)  # (the network opens its session here, at first use)
    opened = time.monotonic()
    registrar = hosts.KEPT["registrars"][name]
    deadline = start + timeout
    pause = threading.Event()
    while True:
        try:
            query = registrar.call(provider, "echo", {"join": name}, timeout=2)
            break
        except (rr.UnknownRegistrarError, rr.RegistrarUnavailableError, rr.CallTimeoutError):
            if time.monotonic() > deadline:
                raise
            pause.wait(0.01)  # (a retry's pace: a failure is immediate)
    end = time.monotonic()
    registrar.unload(query.id)
    return start, opened, end


_joiners = itertools.count()


def join_once(two: hosts.TwoHosts, certs: Certs, near: str, ready: hosts.Worker) -> Any:
    """A member's time to join, in `ready` (a fresh worker on host b, stopped after)."""
    name = f"joiner-{next(_joiners)}"
    try:
        return ready.call(join_timed, name, [near], certs.tls("joiner"), "erm", 30.0, timeout=60)
    finally:
        with contextlib.suppress(Exception):
            ready.call(hosts.rr_stop, timeout=30)
        ready.stop()


def burst(
    two: hosts.TwoHosts, certs: Certs, args: argparse.Namespace
) -> tuple[dict[str, list[Any]], dict[str, Any], dict[str, list[tuple[float, float]]]]:
    """The burst of refused handshakes: the member's calls by phase, the burst's outcome,
    and the joins (quiet and during the burst)."""
    port = next(_ports)
    near = two.a.endpoint(port, "tls")
    joins: dict[str, list[tuple[float, float]]] = {"quiet": [], "during": [], "ended": []}
    with (
        rr_worker(two.a, [near], [], certs.tls("robot"), ("erm", bench_zenoh.setup_echo)),
        rr_worker(two.b, [], [near], certs.tls("operator"), ("app", None)) as member,
    ):
        member.call(hosts.rr_until_answered, "app", "erm", "echo", 30.0, timeout=60)
        for _ in range(args.joins):
            start, opened, end = join_once(two, certs, near, two.b.spawn())
            joins["quiet"].append((end - start, opened - start))
        intruder = two.b.spawn()
        ready = [two.b.spawn() for _ in range(args.joins)]  # (started before the burst)
        before = member.call(calls_paced, "app", "erm", args.quiet, args.interval, timeout=600)
        during: Future[Any] = member.submit(calls_paced, "app", "erm", None, args.interval)
        cert, key = certs.intruder
        intruder.call(burst_prepare, timeout=10)
        outcome: Future[dict[str, Any]] = intruder.submit(
            refused_handshakes, two.a.address, port, args.clients, args.handshakes, cert, key
        )
        if not intruder.call(burst_started, 30.0, timeout=40):
            raise RuntimeError("the burst of handshakes did not begin")
        spans = []
        for worker in ready:
            if outcome.done():
                worker.stop()
                continue
            spans.append(join_once(two, certs, near, worker))
        result = outcome.result(600)
        member.call(calls_stop, timeout=10)
        calls = during.result(600)
        after = member.call(calls_paced, "app", "erm", args.quiet, args.interval, timeout=600)
    for start, opened, end in spans:
        joins["during" if end <= result["ended"] else "ended"].append((end - start, opened - start))
    phases = {
        "before": before,
        "during": [c for c in calls if result["began"] <= c[0] <= result["ended"]],
        "after": after,
    }
    return phases, result, joins


# -- a flood of failed handshakes from a third host (issue 29) -----------------------------------

PARTS = ("trips", "burst", "flood", "spoof")
"""What a run measures (`--only`): round trips, the burst, the floods, the forged SYNs."""

MODES = {
    "gate": "rr_actors (queue of 16, floods dropped)",
    "backlog": "queue of 16 only, no source dropped",
    "none": "Zenoh's listener alone (queue of 1024)",
}
"""How host a's listener is kept, by `gate_mode`."""


def gate_mode(mode: str) -> None:
    """In host a's worker, before it joins: keep its `tls/` listener as `MODES[mode]` says
    (the benchmark's own switch: rr_actors has none, its gate is always on)."""
    from rr_actors._transport.zenoh import net as zenoh_net  # noqa: PLC0415
    from rr_actors._transport.zenoh.ops import gate as zenoh_gate  # noqa: PLC0415

    if mode == "none":
        zenoh_net.open_gates = lambda listen: []  # type: ignore[assignment]
    elif mode == "backlog":
        zenoh_gate.HOLD = 10**9


def answered_within(two: hosts.TwoHosts, give_up: float) -> float | None:
    """Seconds from now to b's first answered call to `erm` (`None`: none within
    `give_up` s)."""
    start = time.monotonic()
    try:
        two.b.call(hosts.rr_until_answered, "app", "erm", "echo", give_up, timeout=give_up + 30)
    except Exception:  # (the member's call failed past the bound: it has not re-joined)
        return None
    return time.monotonic() - start


def rejoin(two: hosts.TwoHosts, give_up: float) -> float | None:
    """Cut the veth a-b until b has lost `erm`, bring it back: seconds to b's first
    answered call (`None`: none within `give_up` s)."""
    two.link_down()
    try:
        if not two.b.call(hosts.rr_unlinked_within, "erm", 30.0, timeout=40):
            raise RuntimeError("b still sees erm with the link cut")
    finally:
        two.link_up()
    return answered_within(two, give_up)


@contextlib.contextmanager
def lab(two: hosts.TwoHosts, certs: Certs, mode: str) -> Iterator[tuple[int, hosts.Worker]]:
    """`robot` on host a serving `erm` (its `tls/` listener kept as `MODES[mode]` says),
    `operator` on host b calling it (`app`), linked; the listener's port and a worker on
    host c, the outsider."""
    assert two.c is not None
    near = two.a.endpoint(next(_ports), "tls")
    robot = two.a.spawn()
    robot.call(gate_mode, mode, timeout=30)
    robot.call(
        hosts.rr_join, system=SYSTEM, listen=[near], connect=[], tls=certs.tls("robot"), timeout=30
    )
    robot.call(hosts.rr_start, "erm", bench_zenoh.setup_echo, timeout=30)
    two.b.call(
        hosts.rr_join,
        system=SYSTEM,
        listen=[],
        connect=[near],
        tls=certs.tls("operator"),
        timeout=30,
    )
    two.b.call(hosts.rr_start, "app", None, timeout=30)
    attacker = two.c.spawn()
    try:
        two.b.call(hosts.rr_until_answered, "app", "erm", "echo", 30.0, timeout=60)
        yield int(near.rsplit(":", 1)[1]), attacker
    finally:
        attacker.stop()
        for worker in (two.b.worker, robot):
            with contextlib.suppress(Exception):
                worker.call(hosts.rr_stop, timeout=30)
        two.b.kill()
        robot.stop()


def flood_run(
    two: hosts.TwoHosts,
    certs: Certs,
    mode: str,
    cuts: int,
    args: argparse.Namespace,
    sources: list[str] | None = None,
) -> dict[str, Any]:
    """Host c floods host a's `tls/` port (`args.threads` threads of connect-send-close,
    no certificate; from each of `sources` in turn, if given) while member b's link to
    a is cut `cuts` times, then `cuts` times more after the flood stopped; b's calls on
    its link meanwhile (before the cuts)."""
    with lab(two, certs, mode) as (port, attacker):
        calls: Future[Any] = two.b.worker.submit(calls_paced, "app", "erm", None, args.interval)
        attacker.call(hosts.flood, two.a.address, port, args.threads, sources, timeout=30)
        threading.Event().wait(args.flood)  # the flood's head start (a pace, not a sync)
        two.b.call(calls_stop, timeout=10)
        during_calls = calls.result(600)
        during = [rejoin(two, args.give_up) for _ in range(cuts)]
        counts = attacker.call(hosts.flood_stop, timeout=30)
        after = [rejoin(two, args.give_up) for _ in range(cuts)]
    return {"calls": during_calls, "during": during, "after": after, "counts": counts}


def sources_of_c(two: hosts.TwoHosts, count: int) -> list[str]:
    """`count` addresses of host c (its own and `count - 1` more, added to its veth)."""
    assert two.c is not None
    stem = two.c.address.rsplit(".", 1)[0]
    more = [f"{stem}.{n}" for n in range(100, 99 + count)]
    for address in more:
        two.c.run("ip", "addr", "add", f"{address}/24", "dev", hosts.OUTSIDE)
    return [two.c.address, *more]


# -- forged SYNs carrying member b's address, from a third host (issue 40) -------------------


def spoof_run(
    two: hosts.TwoHosts, certs: Certs, cuts: int, args: argparse.Namespace
) -> dict[str, Any]:
    """Member b goes out of reach (its end of the veth down: a keeps its route to b, as
    for a robot out of radio range) until it has lost a; host c's forged SYNs (source:
    b's address, `args.spoof_rate` a second) reach a's `tls/` port, `args.spoofed` more
    of them; b's end comes back: the seconds to its first answered call. `cuts` times with
    the forging going on through the returns, then `cuts` times with it stopped before
    each return (each cut a forging of its own)."""
    with lab(two, certs, "gate") as (port, attacker):

        def forging(start: bool) -> None:
            if start:
                attacker.call(
                    spoof.spoof_start,
                    *(two.b.address, two.a.address, port, args.spoof_rate),
                    timeout=10,
                )
            else:
                attacker.call(spoof.spoof_stop, timeout=10)

        def out_of_reach(alone: bool) -> float | None:
            two.b.run("ip", "link", "set", hosts.INTERFACE, "down")
            try:
                if not two.b.call(hosts.rr_unlinked_within, "erm", 30.0, timeout=40):
                    raise RuntimeError("b still sees erm out of reach")
                if alone:
                    forging(start=True)
                more = attacker.call(spoof.spoof_counts, timeout=10)["sent"] + args.spoofed
                if not wait_for(
                    lambda: attacker.call(spoof.spoof_counts, timeout=10)["sent"] >= more,
                    30.0 + args.spoofed / args.spoof_rate,
                ):
                    raise RuntimeError("the forged SYNs were not sent")
                if alone:
                    forging(start=False)
            finally:
                two.b.run("ip", "link", "set", hosts.INTERFACE, "up")
            return answered_within(two, args.give_up)

        forging(start=True)
        during = [out_of_reach(alone=False) for _ in range(cuts)]
        forging(start=False)
        after = [out_of_reach(alone=True) for _ in range(cuts)]
        return {"during": during, "after": after}


# -- report -----------------------------------------------------------------------------------


def quantile(samples: list[float], q: int) -> float:
    """The `q`th percentile (nearest rank; the sample itself when there is one)."""
    return _harness.percentile(samples, q / 100)


def report_trips(rounds: int, rows: dict[str, list[float]]) -> None:
    median = {name: _harness.median(samples) for name, samples in rows.items()}
    table = []
    for name, samples in rows.items():
        kind, protocol = name.rsplit(", ", 1)
        tcp = median[f"{kind}, plain TCP"]
        raw = median[f"raw Zenoh get, {protocol}"]
        table.append(
            (
                name, f"{median[name] * 1e6:.1f}", f"{quantile(samples, 90) * 1e6:.1f}",
                f"{median[name] / tcp:.2f}x", f"{median[name] / raw:.2f}x",
            )
        )  # fmt: skip
    _harness.print_table(
        f"round trips across the veth, {rounds} per row; times in microseconds",
        ("measurement", "median us", "p90 us", "TLS / TCP", "rr / raw get"),
        table,
    )


def report_burst(
    args: argparse.Namespace,
    phases: dict[str, list[Any]],
    result: dict[str, Any],
    joins: dict[str, list[tuple[float, float]]],
) -> None:
    took = result["ended"] - result["began"]
    calls_table = []
    for phase, calls in phases.items():
        times = [seconds for _, seconds, error in calls if error is None]
        failed = sum(1 for *_, error in calls if error is not None)
        target = f"all succeed, p99 < {TARGET_P99 * 1e3:g} ms" if phase == "during" else ""
        shown = [_harness.median(times), quantile(times, 99), max(times)] if times else []
        cells = [f"{x * 1e3:.2f}" for x in shown] or ["-"] * 3
        calls_table.append((f"{phase} the burst", len(calls), failed, *cells, target))
    _harness.print_table(
        f"{args.handshakes} TLS handshakes with another CA's certificate from {args.clients} "
        f"clients at once (host b -> host a's tls/ listener): {result['refused']} refused, "
        f"{result['other']} not refused, in {took:.1f} s ({took / args.handshakes * 1e3:.0f} ms "
        f"each); a member's dedup-hit call every {args.interval * 1e3:g} ms, times in ms",
        ("member's calls", "calls", "failed", "p50 ms", "p99 ms", "max ms", "target"),
        calls_table,
    )
    labels = {
        "quiet": "quiet (no burst)",
        "during": "during the burst",
        "ended": "began during the burst, in after it ended",
    }
    joins_table = []
    for when, spans in joins.items():
        if not spans:
            continue
        total = [span for span, _ in spans]
        opening = _harness.median(opened for _, opened in spans)
        joins_table.append(
            (
                labels[when], len(spans), f"{_harness.median(total):.2f}", f"{max(total):.2f}",
                f"{opening:.2f}", f"< {TARGET_JOIN:g} s" if when == "during" else "",
            )
        )  # fmt: skip
    _harness.print_table(
        "",
        (
            "a member joins (to its first successful call)", "runs", "median s", "max s",
            "of which its session's open, median s", "target",
        ),
        joins_table,
    )  # fmt: skip


def spans(seconds: list[float | None], give_up: float) -> str:
    """`median / max (n runs)` of re-join times, `> give_up` for a run with none."""
    shown = [give_up * 10 if s is None else s for s in seconds]
    text = [f"> {give_up:g}" if s is None else f"{s:.2f}" for s in seconds]
    order = sorted(range(len(shown)), key=shown.__getitem__)
    return f"{text[order[len(order) // 2]]} / {text[order[-1]]} ({len(seconds)} runs)"


def report_flood(args: argparse.Namespace, runs: dict[str, dict[str, Any]]) -> None:
    rows = []
    for name, run in runs.items():
        mode, _, addresses = name.partition("@")
        times = [seconds for _, seconds, error in run["calls"] if error is None]
        failed = sum(1 for *_, error in run["calls"] if error is not None)
        p99 = f"{quantile(times, 99) * 1e3:.1f}" if times else "-"
        counts = run["counts"]
        rows.append(
            (
                MODES[mode], addresses, spans(run["during"], args.give_up),
                spans(run["after"], args.give_up), f"{len(run['calls'])}, {failed}, {p99}",
                f"{counts['connected']} / {counts['attempts']}",
            )
        )  # fmt: skip
    _harness.print_table(
        f"host c floods host a's tls/ port ({args.threads} threads of connect-send-close, no "
        f"certificate; from one address, or from {args.sources} in turn) for {args.flood:g} "
        f"s, then member b's link to a is cut (ip link down until b has lost a) and brought "
        f"back, during the flood and after it stopped; re-join: seconds from the link's "
        f"return to b's first answered call (> {args.give_up:g}: none by then)",
        (
            "a's listener", "c's addresses", "re-joins during the flood, median / max s",
            "after it stopped, median / max s",
            f"b's calls on its link in the flood's first {args.flood:g} s: calls, failed, p99 ms",
            "c's connections made / attempts",
        ),
        rows,
    )  # fmt: skip


def report_spoof(args: argparse.Namespace, run: dict[str, Any]) -> None:
    _harness.print_table(
        f"member b out of reach (its end of the veth down until it has lost a); host c "
        f"sends {args.spoof_rate:g} SYNs a second whose source is b's address to a's tls/ "
        f"port ({args.spoofed} more each time b is out); b's end comes back: seconds to its "
        f"first answered call (> {args.give_up:g}: none by then)",
        ("re-join, the forging going on", "re-join, the forging stopped before the return"),
        [(spans(run["during"], args.give_up), spans(run["after"], args.give_up))],
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2000, help="timed round trips per row")
    parser.add_argument("--handshakes", type=int, default=200, help="refused handshakes")
    parser.add_argument("--clients", type=int, default=20, help="threads making them at once")
    parser.add_argument("--joins", type=int, default=3, help="joins quiet, and during the burst")
    parser.add_argument(
        "--quiet", type=float, default=5.0, help="seconds of calls before and after the burst"
    )
    parser.add_argument("--interval", type=float, default=0.01, help="seconds between calls")
    parser.add_argument("--cuts", type=int, default=3, help="link cuts during/after the flood")
    parser.add_argument("--threads", type=int, default=4, help="the flood's threads")
    parser.add_argument("--flood", type=float, default=2.0, help="seconds of flood before a cut")
    parser.add_argument("--give-up", type=float, default=60.0, help="a re-join's bound, s")
    parser.add_argument("--sources", type=int, default=32, help="c's addresses, many-address flood")
    parser.add_argument("--spoof-rate", type=float, default=13.0, help="forged SYNs a second")
    parser.add_argument("--spoofed", type=int, default=40, help="forged SYNs per time b is out")
    parser.add_argument(
        "--only",
        nargs="+",
        choices=PARTS,
        default=list(PARTS),
        help="measure these parts only (default: all)",
    )
    parser.add_argument(
        "--without-gate",
        action="store_true",
        help="also flood a listener without rr_actors' gate (one cut each; minutes)",
    )
    args = parser.parse_args()
    why_not = hosts.require_root() or (
        None if hosts.has_carrier() else "rr_actors has no ZenohNetwork"
    )
    if why_not is not None:
        print(f"not measured: {why_not}")
        return
    with (
        tempfile.TemporaryDirectory(prefix="rr-bench-tls-") as directory,
        hosts.TwoHosts(outsider=True) as two,
    ):
        certs = Certs(Path(directory), two)
        floods, forged, rows, burst_run = {}, None, {}, None
        if "flood" in args.only:
            floods["gate@1"] = flood_run(two, certs, "gate", args.cuts, args)
            if args.without_gate:
                floods["backlog@1"] = flood_run(two, certs, "backlog", 1, args)
                floods["none@1"] = flood_run(two, certs, "none", 1, args)
            many = sources_of_c(two, args.sources)
            floods[f"gate@{args.sources}"] = flood_run(two, certs, "gate", args.cuts, args, many)
        if "spoof" in args.only:
            forged = spoof_run(two, certs, args.cuts, args)
        if "trips" in args.only:
            rows = {
                "raw Zenoh get, plain TCP": raw_gets(two, args.rounds, None),
                "raw Zenoh get, mutual TLS": raw_gets(two, args.rounds, certs),
                "rr_actors dedup-hit call, plain TCP": rr_dedup(two, args.rounds, None),
                "rr_actors dedup-hit call, mutual TLS": rr_dedup(two, args.rounds, certs),
            }
        if "burst" in args.only:
            burst_run = burst(two, certs, args)
    if rows:
        report_trips(args.rounds, rows)
        print()
    if burst_run is not None:
        report_burst(args, *burst_run)
        print()
    if floods:
        report_flood(args, floods)
        print()
    if forged is not None:
        report_spoof(args, forged)
        print()
    print(
        "ratios move by a quarter between runs on a loaded machine; they are stable with "
        "every process on one CPU: taskset -c 0 python benchmarks/bench_zenoh_tls.py"
    )


if __name__ == "__main__":
    main()
