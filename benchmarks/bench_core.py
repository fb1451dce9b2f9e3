"""Core registrar latencies next to a raw pykka ask, measured in one run.

Every operation is measured in interleaved rounds (round 1 of every operation, then
round 2 of every operation, ...) so that noise from other processes spreads evenly over
all rows. Each sample is one operation, timed with `time.perf_counter_ns`. The table shows
the median and 90th percentile in microseconds and the ratio of each median to the
median of a raw pykka ask (`ActorRef.ask` to a `ThreadingActor` that echoes).

Usage:
    python benchmarks/bench_core.py [--rounds 20] [--batch 200] [--profile FILE] [--durable]

`--durable`: every registrar keeps a backup with `save_on_modify` (a temporary folder),
so each change is committed before it is answered.

Operations:
    pykka ask           raw `ref.ask(x)` round trip to an echoing ThreadingActor
    rr_actors ask       the same to rr_actors' actor type (SimpleQueue mailbox, one-shot
                        futures), which the registrars are built on
    dedup-hit call      `call` of a request already loaded (a consumer is added, no load)
    dedup-hit unload    `unload` of one of those ids (not the last consumer, no unload)
    ... 1 subscriber    the same two against a provider whose events one subscriber
                        receives (`ResourceRegistrar.subscribe`): the event stream's cost
    unique load+unload  `call` of a new request, then `unload` of its only id
    status delivery     `send_status` to one consumer; returns after its callback ran
"""

from __future__ import annotations

import cProfile
import importlib.metadata
import itertools
import sys
import tempfile
import uuid
from collections.abc import Callable
from typing import Any

import _harness
import pykka

import rr_actors as rr
from rr_actors._core.actor import Actor


class Echo(pykka.ThreadingActor):
    """The baseline: the cheapest useful pykka round trip."""

    def on_receive(self, message: Any) -> Any:
        return message


class ActorEcho(Actor):
    """The same echo on the actor type rr_actors' registrars use."""

    def on_receive(self, message: Any) -> Any:
        return message


class Bench:
    """The actors and registrars every operation uses, started once."""

    def __init__(self, *, durable: bool = False) -> None:
        suffix = uuid.uuid4().hex[:6]
        self.folder = tempfile.TemporaryDirectory() if durable else None
        self.echo = Echo.start()
        self.actor_echo = ActorEcho.start()
        self.provider = rr.ResourceRegistrar.start(self.config(f"bench-provider-{suffix}"))
        self.consumer = rr.ResourceRegistrar.start(self.config(f"bench-consumer-{suffix}"))
        self.provider.register_server("res", load=lambda request: request, unload=_noop)
        self.holder = self.consumer.call(self.provider.name, "res", "shared")
        self.watched = self.consumer.call(self.provider.name, "res", "watched", on_status=_noop)
        self._unique = itertools.count()
        self._dedup_ids: list[str] = []
        self.observed = rr.ResourceRegistrar.start(self.config(f"bench-observed-{suffix}"))
        self.observed.register_server("res", load=lambda request: request, unload=_noop)
        self.consumer.call(self.observed.name, "res", "shared")
        self.subscription = self.observed.subscribe(_noop)
        self._observed_ids: list[str] = []

    def stop(self) -> None:
        self.subscription.close()
        self.consumer.stop()
        self.observed.stop()
        self.provider.stop()
        self.echo.stop()
        self.actor_echo.stop()
        if self.folder is not None:
            self.folder.cleanup()

    def config(self, name: str) -> rr.RegistrarConfig:
        """`name`'s configuration: with `--durable`, a backup with `save_on_modify`."""
        if self.folder is None:
            return rr.RegistrarConfig(name=name)
        backup = f"{self.folder.name}/{name}.db"
        return rr.RegistrarConfig(name=name, backup_path=backup, save_on_modify=True)

    # -- operations (each does one operation) -----------------------------------------

    def pykka_ask(self) -> None:
        self.echo.ask("ping")

    def actor_ask(self) -> None:
        self.actor_echo.ask("ping")

    def dedup_call(self) -> None:
        query = self.consumer.call(self.provider.name, "res", "shared")
        self._dedup_ids.append(query.id)

    def dedup_unload(self) -> None:
        self.consumer.unload(self._dedup_ids.pop())

    def observed_call(self) -> None:
        query = self.consumer.call(self.observed.name, "res", "shared")
        self._observed_ids.append(query.id)

    def observed_unload(self) -> None:
        self.consumer.unload(self._observed_ids.pop())

    def unique_load_unload(self) -> None:
        query = self.consumer.call(self.provider.name, "res", ("unique", next(self._unique)))
        self.consumer.unload(query.id)

    def status_delivery(self) -> None:
        self.provider.send_status(self.watched.id, rr.Status.UPDATE, "tick")


def _noop(*_: object) -> None:
    return None


def run(rounds: int, batch: int, *, durable: bool = False) -> list[tuple[str, float, float]]:
    """Measure every operation; return (name, median us, p90 us) rows."""
    bench = Bench(durable=durable)
    try:
        ops: dict[str, Callable[[], None]] = {
            "pykka ask": bench.pykka_ask,
            "rr_actors ask": bench.actor_ask,
            "dedup-hit call": bench.dedup_call,
            "dedup-hit unload": bench.dedup_unload,
            "dedup-hit call, 1 subscriber": bench.observed_call,
            "dedup-hit unload, 1 subscriber": bench.observed_unload,
            "unique load+unload": bench.unique_load_unload,
            "status delivery": bench.status_delivery,
        }
        samples = _harness.alternate(
            {name: (lambda op=op: _harness.each(op, batch)) for name, op in ops.items()}, rounds
        )
        return [
            (name, _harness.median(s) * 1e6, _harness.percentile(s, 0.9) * 1e6)
            for name, s in samples.items()
        ]
    finally:
        bench.stop()


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, run, print the table."""
    parser = _harness.options(__doc__, rounds=20, batch=200)
    parser.add_argument("--profile", metavar="FILE", help="write cProfile stats of the run here")
    parser.add_argument("--durable", action="store_true", help="registrars with backups")
    args = _harness.parse(parser, argv)

    profiler = cProfile.Profile() if args.profile else None
    if profiler is not None:
        profiler.enable()
    rows = run(args.rounds, args.batch, durable=args.durable)
    if profiler is not None:
        profiler.disable()
        profiler.dump_stats(args.profile)

    base = rows[0][1]
    print(
        _harness.header(
            f"pykka {importlib.metadata.version('pykka')}, "
            f"{args.rounds} rounds x {args.batch} operations per row"
            f"{', durable registrars' if args.durable else ''}"
        )
    )
    print()
    print(
        _harness.table(
            ["operation", "median (us)", "p90 (us)", "median / pykka ask"],
            [(n, f"{m:.1f}", f"{p:.1f}", f"{m / base:.1f}x") for n, m, p in rows],
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
