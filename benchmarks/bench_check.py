"""How fast `rr-actors check` gives a verdict: events per second, next to reading JSON alone.

A synthetic clean history of N events is written to an `events.jsonl` first: a chain
`edge -> api -> db` of manager processes (numbered events, a backup each) serving four
clients; `--live` client ids held at once (each load of edge loads at api and db, a
repeated key is a dedup hit), a status from db climbing to the clients every
`--status-every` events, a provider killed and restored (its whole catalog in one
`CatalogRestored`) every `--restart-every` events, everything released and stopped at the
end. The checker must find it `held` (the script fails otherwise). Rows, per size:

    json.loads (floor)     every line parsed as JSON, nothing else: what any reader pays
    read                   the lines to events (`check.read_runs`: JSON, `from_dict`)
    rules                  `check.check` on the events read (every rule)
    rr-actors check -q     the whole command, in this process (read, rules, print)

and the events per second of the whole command (of wall time, and of its CPU time: on a
loaded machine the second is the steadier), and its multiple of the floor. Pin it to one
CPU for the figure the docs state (a million events under a minute on one core):

    taskset -c 0 python benchmarks/bench_check.py --sizes 100000,1000000
    python benchmarks/bench_check.py --sizes 20000 --profile /tmp/check.prof
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import io
import json
import random
import resource
import sys
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TypeVar

import _harness

from rr_actors import events
from rr_actors._core import hlc
from rr_actors._types import Status
from rr_actors.events.lines import json_lines
from rr_actors_lab.__main__ import main
from rr_actors_lab.experiments import check

CHAIN = ("edge", "api", "db")
"""The providers, each loading from the next one (edge's loads load at api, and so on)."""

CLIENTS = tuple(f"client-{i}" for i in range(4))
CLIENT_PID = 1000  # the clients' process (a supervisor's: its events are not numbered)

T = TypeVar("T")


class Synthetic:
    """A clean history, built by simulating the registrars' catalogs (seeded)."""

    def __init__(self, seed: int, live: int, status_every: int, restart_every: int) -> None:
        self.rng = random.Random(seed)  # noqa: S311 - a reproducible history, not a secret
        self.live = live
        self.status_every = status_every
        self.restart_every = restart_every
        self.stamp = hlc.from_seconds(1.8e9)
        self.pids = {name: 1001 + i for i, name in enumerate(CHAIN)}
        self.seqs = dict.fromkeys(self.pids.values(), 0)
        # provider -> key -> [resource id, {query id: consumer}, dependency query id]
        self.res: dict[str, dict[int, list]] = {name: {} for name in CHAIN}  # type: ignore[type-arg]
        self.key_of: dict[str, dict[str, int]] = {name: {} for name in CHAIN}
        self.held: dict[str, tuple[str, int]] = {}  # a client's query id -> (client, key)
        self.built = 0

    def ids(self) -> str:
        return str(uuid.UUID(int=self.rng.getrandbits(128), version=4))

    def emit(self, cls: type, *args: object, pid: int, numbered: bool = True) -> events.Event:
        self.stamp += 1 + self.rng.getrandbits(6)
        seq = 0
        if numbered:
            self.seqs[pid] += 1
            seq = self.seqs[pid]
        self.built += 1
        at = hlc.seconds(self.stamp)
        event: events.Event = cls(*args, at=at, pid=pid, seq=seq, host="bench", hlc=self.stamp)
        return event

    def child(self, cls: type, *args: object) -> events.Event:
        """A supervisor's event about a child (its own fields name the child's pid)."""
        self.stamp += 1 + self.rng.getrandbits(6)
        self.built += 1
        event: events.Event = cls(*args, at=hlc.seconds(self.stamp), host="bench", hlc=self.stamp)
        return event

    def on(self, name: str, cls: type, *args: object) -> events.Event:
        return self.emit(cls, name, *args, pid=self.pids[name])

    def client(self, cls: type, *args: object) -> events.Event:
        return self.emit(cls, *args, pid=CLIENT_PID, numbered=False)

    # -- what the registrars do -----------------------------------------------------------

    def start(self) -> Iterator[events.Event]:
        for name in CHAIN:
            yield self.on(name, events.CatalogRestored, (), (), ())

    def acquire(self, name: str, key: int, query: str, consumer: str) -> Iterator[events.Event]:
        """`consumer`'s `query` for `key` at `name`: a load (and its dependency's) or a hit."""
        found = self.res[name].get(key)
        if found is None:
            rid = self.ids()
            below = CHAIN.index(name) + 1
            dep = ""
            if below < len(CHAIN):
                dep = self.ids()
                yield from self.acquire(CHAIN[below], key, dep, name)
                yield self.on(name, events.CallAnswered, dep, CHAIN[below], "resource", rid)
            yield self.on(
                name, events.ResourceLoaded, "resource", rid, query, 0.002, key, f"k{key}"
            )
            found = self.res[name][key] = [rid, {}, dep]
        yield self.on(name, events.ConsumerAdded, found[0], query, consumer)
        found[1][query] = consumer
        self.key_of[name][query] = key

    def release(self, name: str, query: str) -> Iterator[events.Event]:
        key = self.key_of[name].pop(query)
        rid, holders, dep = self.res[name][key]
        consumer = holders.pop(query)
        yield self.on(name, events.ConsumerReleased, rid, query, consumer, "unload")
        if not holders:
            if dep:
                below = CHAIN[CHAIN.index(name) + 1]
                yield from self.release(below, dep)
                yield self.on(name, events.QueryForgotten, dep, below, "dependency")
            yield self.on(name, events.ResourceUnloaded, "resource", rid)
            del self.res[name][key]

    def call(self) -> Iterator[events.Event]:
        who = self.rng.choice(CLIENTS)
        key = self.rng.randrange(2 * self.live)  # about half the calls are dedup hits
        query = self.ids()
        yield from self.acquire(CHAIN[0], key, query, who)
        yield self.client(events.CallAnswered, who, query, CHAIN[0], "resource")
        self.held[query] = (who, key)

    def unload(self) -> Iterator[events.Event]:
        query = self.rng.choice(list(self.held)) if len(self.held) < 64 else self.any_held()
        who, _ = self.held.pop(query)
        yield from self.release(CHAIN[0], query)
        yield self.client(events.QueryForgotten, who, query, CHAIN[0], "unload")

    def any_held(self) -> str:
        # (dicts keep insertion order: the oldest holds go first, as holds that run out)
        return next(iter(self.held))

    def status(self) -> Iterator[events.Event]:
        """A status from db about one of its resources, climbing every path to the clients."""
        served = self.res[CHAIN[-1]]
        if not served:
            return
        rid, holders, _ = served[self.rng.choice(list(served))]
        sid = self.ids()
        yield self.on(CHAIN[-1], events.StatusSent, next(iter(holders)), Status.WARNING, "hot", sid)
        yield from self.deliver(CHAIN[-1], rid, holders, 1, sid)

    def deliver(
        self, name: str, rid: str, holders: dict[str, str], hop: int, sid: str
    ) -> Iterator[events.Event]:
        for query, consumer in list(holders.items()):
            if consumer in self.pids:
                yield self.on(
                    consumer, events.StatusDelivered, query, Status.WARNING, hop, 0.001, sid
                )
                key = self.key_of[name][query]
                above = self.res[consumer][key]
                yield from self.deliver(consumer, above[0], above[1], hop + 1, sid)
            else:
                yield self.client(
                    events.StatusDelivered, consumer, query, Status.WARNING, hop, 0.001, sid
                )

    def restart(self) -> Iterator[events.Event]:
        """A provider killed (after its last event was sent) and restored from its backup."""
        name = self.rng.choice(CHAIN)
        old = self.pids[name]
        yield self.child(events.ChildExited, "sup", name, old, "killed")
        self.pids[name] = new = old + 10
        self.seqs[new] = 0
        served = self.res[name]
        resources = tuple((r[0], "resource", "loaded", str(k), "") for k, r in served.items())
        consumers = tuple((q, r[0], c) for r in served.values() for q, c in r[1].items())
        below = CHAIN.index(name) + 1
        clients = tuple((r[2], CHAIN[below], "resource", r[0]) for r in served.values() if r[2])
        counts = (len(resources), len(consumers), len(clients))
        yield self.on(name, events.CatalogRestored, resources, consumers, clients, counts)
        yield self.child(events.ChildRestarted, "sup", name, new, 0.1)

    def stop(self) -> Iterator[events.Event]:
        while self.held:
            yield from self.unload()
        for who in CLIENTS:
            yield self.client(events.RegistrarStopped, who, (), (), ())
        for name in CHAIN:
            yield self.on(name, events.RegistrarStopped, (), (), ())

    def history(self, size: int) -> Iterator[events.Event]:
        """About `size` events (a few more: the last calls are released, all stop)."""
        yield from self.start()
        next_status, next_restart = self.status_every, self.restart_every
        while self.built + 4 * len(self.held) < size:
            if self.built >= next_status:
                next_status += self.status_every
                yield from self.status()
            elif self.built >= next_restart:
                next_restart += self.restart_every
                yield from self.restart()
            elif len(self.held) < self.live:
                yield from self.call()
            else:
                yield from self.unload()
        yield from self.stop()


def write_history(path: Path, size: int, args: argparse.Namespace) -> int:
    """Write about `size` events to `path`; how many were written."""
    written = 0
    synthetic = Synthetic(args.seed, args.live, args.status_every, args.restart_every)
    with path.open("w") as file:
        for event in synthetic.history(size):
            data = events.to_dict(event)
            data["run"] = 1
            file.write(json.dumps(data) + "\n")
            written += 1
    return written


def timed(fn: Callable[[], T]) -> tuple[float, float, T]:
    """Wall and CPU seconds of `fn()`, and what it returned (on a loaded machine the CPU
    time is the steadier figure)."""
    cpu, wall = time.process_time(), time.perf_counter()
    value = fn()
    return time.perf_counter() - wall, time.process_time() - cpu, value


def measure(path: Path, profile: str | None) -> dict[str, float]:
    """Seconds of each row for the history at `path` (exits if it is not `held`)."""
    floor, _, _ = timed(lambda: sum(1 for _ in json_lines(path)))
    with path.open() as lines:
        read, _, runs = timed(lambda: check.read_runs(lines))
    profiler = cProfile.Profile() if profile else None
    if profiler is not None:
        profiler.enable()
    rules, _, verdict = timed(lambda: check.check(runs[1]))
    if profiler is not None and profile is not None:
        profiler.disable()
        profiler.dump_stats(profile)
    if verdict.verdict != "held":
        shown = check.format_verdict(1, verdict)
        sys.exit("the synthetic history is not clean:\n" + "\n".join(shown[:20]))
    runs.clear()  # (its memory back before the command reads the file again)
    out = io.StringIO()
    with contextlib.redirect_stderr(io.StringIO()):
        command, cpu, code = timed(lambda: main(["check", str(path), "-q"], out))
    assert code == 0, out.getvalue()
    return {"floor": floor, "read": read, "rules": rules, "command": command, "cpu": cpu}


def main_bench() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", default="10000,100000,1000000", help="events per history")
    parser.add_argument("--live", type=int, default=1000, help="client ids held at once")
    parser.add_argument("--status-every", type=int, default=200, help="events per status")
    parser.add_argument("--restart-every", type=int, default=100_000, help="events per restart")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--min-rate", type=float, default=0.0, help="exit 1 below this many events/s of CPU"
    )
    parser.add_argument("--profile", help="write a cProfile of the rules (largest size) here")
    parser.add_argument("--dir", help="where to write the histories (default: a temp dir)")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    _harness.head(
        _harness.header(
            f"rr-actors check; {args.live} ids held at once, a status every "
            f"{args.status_every} events, a restart every {args.restart_every}\n"
        ),
        (
            "events", "MB", "json.loads (floor) s", "read s", "rules s", "rr-actors check -q s",
            "its CPU s", "events/s", "events/s of CPU", "/ floor",
        ),
        right=0,
    )  # fmt: skip
    slow = []
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        for size in sizes:
            path = Path(tmp) / f"events-{size}.jsonl"
            written = write_history(path, size, args)
            profile = args.profile if size == sizes[-1] else None
            t = measure(path, profile)
            rate = written / t["command"]
            print(
                f"| {written:,} | {path.stat().st_size / 1e6:,.0f} | {t['floor']:.2f} "
                f"| {t['read']:.2f} | {t['rules']:.2f} | {t['command']:.2f} | {t['cpu']:.2f} "
                f"| {rate:,.0f} | {written / t['cpu']:,.0f} "
                f"| {t['command'] / t['floor']:.1f}x |",
                flush=True,
            )
            if written / t["cpu"] < args.min_rate:
                slow.append(f"{written:,} events: {written / t['cpu']:,.0f} events/s of CPU")
            path.unlink()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # (KiB on Linux)
    print(f"\npeak memory of this process (its largest history read): {peak:,.0f} MiB")
    if slow:
        sys.exit(f"below {args.min_rate:,.0f} events/s: " + "; ".join(slow))


if __name__ == "__main__":
    main_bench()
