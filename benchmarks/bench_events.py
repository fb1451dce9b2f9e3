"""What publishing an event costs the publishing thread, next to a bare function call.

A registrar publishes as `if publisher.active: publisher.publish(ResourceLoaded(...))`.
Each row runs that line (or its baseline) `--batch` times in a loop and reports the time per
iteration in ns, minus the time of an empty loop of the same length, and its ratio to a bare
Python function call measured in the same run. Rows are interleaved round by round so that
noise from other processes spreads evenly; the table shows the median over rounds. For scale,
the last column compares each row with an in-process dedup-hit `call` (one consumer
registrar calling a resource another one already serves), also measured in the same run.

Rows:
    bare function call          `noop(x)`: the baseline of the ratio column
    build one event             `ResourceLoaded(...)` alone (what `active` saves)
    nobody listening            the line above with no subscriber and INFO off: `active` only
    one subscriber              the line with one subscription (a no-op callback); the
                                publishing thread's time only
    one subscriber + delivery   the same until `wait_delivered()` returned: the subscriber
                                thread's work too (it competes for the GIL)
    forwarder                   the line with a `Forwarder` (a no-op `send`) as the only sink
    forwarder + send            the same until `wait_sent()` returned
    INFO log line               no subscriber, INFO on (a handler that discards the record):
                                `describe` plus a `LogRecord`
    build, numbered             `build one event` as a manager process does it: with its
                                `seq` (`number_events`), no tally
    build, numbered + journal   ... and the event appended to the journal (pickled,
                                `os.write`): what a manager process does now, so that a
                                SIGKILL loses no event it published
    hlc stamp                   `CLOCK.now()`: the hybrid logical clock stamp every event
                                takes (its part of `build one event`)
    at, CLOCK.wall()            the events' `at` now (the clock the stamp reads) ...
    at, time.time()             ... and what it was before
    message: header + frame     what the Zenoh carrier put in front of a frame before
                                (a 200-byte frame, as a small `Load`'s)
    message: stamp + envelope   what it does now: `CLOCK.send()` and the stamped envelope
    message: parse              the receiver's `parse` of an unstamped payload ...
    message: parse + receive    ... of a stamped one, and `CLOCK.receive(stamp)`
    dedup-hit call              `consumer.call(provider, "res", "shared")`, per call (for scale)

Pin it to one CPU for stable ratios (the subscriber thread then shares that CPU, as it
shares the GIL anyway):

    taskset -c 0 python benchmarks/bench_events.py [--rounds 20] [--batch 10000]
"""

from __future__ import annotations

import logging
import sys
import time
import uuid
from collections.abc import Callable
from typing import Any

import _harness

import rr_actors as rr
from rr_actors import events
from rr_actors._core.bus import Forwarder, Publisher
from rr_actors._core.hlc import CLOCK
from rr_actors._process.tally import Journal, Tally
from rr_actors._transport.zenoh import wire as zenoh_wire
from rr_actors.events import kinds

Row = Callable[[int], None]
"""Runs one operation `n` times in a loop."""

RID = str(uuid.uuid4())
QID = str(uuid.uuid4())
ZID = uuid.uuid4().hex
FRAME = (196).to_bytes(4, "big") + bytes(8) + bytes(188)  # length, token, a 188-byte pickle
PLAIN_PAYLOAD = zenoh_wire.header(zenoh_wire.MESSAGE, ZID) + FRAME
STAMPED_PAYLOAD = zenoh_wire.envelope(zenoh_wire.MESSAGE, ZID, FRAME, CLOCK.now())


def noop(_: object) -> None:
    return None


class Bench:
    """The publishers (and the registrars of the dedup-hit row), set up once."""

    def __init__(self, batch: int) -> None:
        quiet = logging.getLogger("rr_actors.bench.quiet")
        quiet.setLevel(logging.WARNING)
        loud = logging.getLogger("rr_actors.bench.loud")
        loud.setLevel(logging.INFO)
        loud.addHandler(logging.NullHandler())
        loud.propagate = False
        self.idle = events.publisher(quiet)
        self.subscribed = events.publisher(quiet)
        self.subscription = self.subscribed.subscribe(noop, maxsize=4 * batch, name="bench")
        self.forwarded = events.publisher(quiet)
        self.forwarder: Forwarder[events.Event] = Forwarder(noop, maxsize=4 * batch)
        self.forwarded.add_sink(self.forwarder)
        self.logged = events.publisher(loud)
        suffix = uuid.uuid4().hex[:6]
        self.provider = rr.ResourceRegistrar.start(f"bench-provider-{suffix}")
        self.consumer = rr.ResourceRegistrar.start(f"bench-consumer-{suffix}")
        self.provider.register_server("res", load=lambda request: request, unload=unload_noop)
        self.consumer.call(self.provider.name, "res", "shared")
        self.held: list[str] = []
        self.tally = Tally.create()
        assert self.tally is not None
        journal = Journal.open(self.tally.path)
        assert journal is not None
        self.journal = journal

    def stop(self) -> None:
        assert self.tally is not None
        self.tally.close()

        self.subscription.close()
        self.forwarded.remove_sink(self.forwarder)
        self.forwarder.close()
        self.consumer.stop()
        self.provider.stop()

    # -- rows: each runs its line n times -----------------------------------------------

    def empty(self, n: int) -> None:
        for _ in range(n):
            pass

    def bare_call(self, n: int) -> None:
        f = noop
        for _ in range(n):
            f(None)

    def build(self, n: int) -> None:
        for _ in range(n):
            events.ResourceLoaded("erm", "res", RID, QID, 0.001)

    def numbered(self, n: int) -> None:
        kinds.number_events()
        try:
            self.build(n)
        finally:
            kinds._numbering, kinds._mark = False, None

    def journaled(self, n: int) -> None:
        kinds.number_events()
        journal = self.journal
        try:
            for _ in range(n):
                journal(events.ResourceLoaded("erm", "res", RID, QID, 0.001))
        finally:
            kinds._numbering = False
        journal.sent()

    def stamp(self, n: int) -> None:
        now = CLOCK.now
        for _ in range(n):
            now()

    def wall(self, n: int) -> None:
        wall = CLOCK.wall
        for _ in range(n):
            wall()

    def time_time(self, n: int) -> None:
        clock = time.time
        for _ in range(n):
            clock()

    def framed(self, n: int) -> None:
        header, frame = zenoh_wire.header, FRAME
        for _ in range(n):
            header(zenoh_wire.MESSAGE, ZID) + frame

    def enveloped(self, n: int) -> None:
        envelope, send, frame = zenoh_wire.envelope, CLOCK.send, FRAME
        for _ in range(n):
            envelope(zenoh_wire.MESSAGE, ZID, frame, send())

    def parsed(self, n: int) -> None:
        parse, data = zenoh_wire.parse, PLAIN_PAYLOAD
        for _ in range(n):
            parse(data)

    def received(self, n: int) -> None:
        parse, receive, data = zenoh_wire.parse, CLOCK.receive, STAMPED_PAYLOAD
        for _ in range(n):
            head = parse(data)
            if head is not None and head.stamp is not None:
                receive(head.stamp)

    def nobody(self, n: int) -> None:
        publisher = self.idle
        for _ in range(n):
            if publisher.active:
                publisher.publish(events.ResourceLoaded("erm", "res", RID, QID, 0.001))

    def one_subscriber(self, n: int) -> None:
        self._publish(self.subscribed, n)

    def one_subscriber_delivered(self, n: int) -> None:
        self._publish(self.subscribed, n)
        assert self.subscription.wait_delivered(timeout=60.0)

    def forwarder_only(self, n: int) -> None:
        self._publish(self.forwarded, n)

    def forwarder_sent(self, n: int) -> None:
        self._publish(self.forwarded, n)
        assert self.forwarder.wait_sent(timeout=60.0)

    def info_line(self, n: int) -> None:
        self._publish(self.logged, n)

    def dedup_hit(self, n: int) -> None:
        call, provider = self.consumer.call, self.provider.name
        for _ in range(n):
            self.held.append(call(provider, "res", "shared").id)

    def settle(self) -> None:
        """Untimed: let the consumers catch up and give the dedup-hit ids back."""
        assert self.subscription.wait_delivered(timeout=60.0)
        assert self.forwarder.wait_sent(timeout=60.0)
        while self.held:
            self.consumer.unload(self.held.pop())

    @staticmethod
    def _publish(publisher: Publisher[Any], n: int) -> None:
        for _ in range(n):
            if publisher.active:
                publisher.publish(events.ResourceLoaded("erm", "res", RID, QID, 0.001))


def unload_noop(*_: object) -> None:
    return None


def run(rounds: int, batch: int, dedup_batch: int) -> tuple[list[tuple[str, float]], int]:
    """Median ns per operation of every row (empty loop subtracted), and events dropped."""
    bench = Bench(batch)
    try:
        rows: dict[str, tuple[Row, int]] = {
            "bare function call": (bench.bare_call, batch),
            "build one event": (bench.build, batch),
            "nobody listening (`active` only)": (bench.nobody, batch),
            "one subscriber": (bench.one_subscriber, batch),
            "one subscriber + delivery": (bench.one_subscriber_delivered, batch),
            "forwarder": (bench.forwarder_only, batch),
            "forwarder + send": (bench.forwarder_sent, batch),
            "INFO log line": (bench.info_line, batch),
            "build, numbered": (bench.numbered, batch),
            "build, numbered + journal": (bench.journaled, batch),
            "hlc stamp (`CLOCK.now()`)": (bench.stamp, batch),
            "at, `CLOCK.wall()` (now)": (bench.wall, batch),
            "at, `time.time()` (before)": (bench.time_time, batch),
            "message: header + frame (before)": (bench.framed, batch),
            "message: stamp + envelope (now)": (bench.enveloped, batch),
            "message: parse, unstamped": (bench.parsed, batch),
            "message: parse + receive, stamped": (bench.received, batch),
            "dedup-hit call": (bench.dedup_hit, dedup_batch),
        }
        for row, n in rows.values():  # warm-up
            row(min(n, 1000))
            bench.settle()

        def sample(row: Row, n: int) -> float:  # ns per iteration, less an empty loop's
            loop = _harness.per_op(lambda: bench.empty(n), 1)
            took = _harness.per_op(lambda: row(n), 1)
            bench.settle()
            return 1e9 * (took - loop) / n

        samples = _harness.alternate(
            {name: (lambda r=row, n=n: sample(r, n)) for name, (row, n) in rows.items()},
            rounds,
            warm_up=False,
        )
        dropped = bench.subscription.dropped + bench.forwarder.dropped
        return [(name, _harness.median(s)) for name, s in samples.items()], dropped
    finally:
        bench.stop()


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, run, print the table."""
    parser = _harness.options(__doc__, rounds=20, batch=10_000)
    parser.add_argument(
        "--dedup-batch", type=int, default=200, help="dedup-hit calls per round (default 200)"
    )
    args = _harness.parse(parser, argv)
    if args.quick:
        args.dedup_batch = _harness.QUICK_BATCH

    rows, dropped = run(args.rounds, args.batch, args.dedup_batch)
    base = rows[0][1]
    dedup = rows[-1][1]
    print(
        _harness.header(
            f"{args.rounds} rounds x {args.batch} publishes per row (dedup hits: "
            f"{args.dedup_batch}); events dropped: {dropped}"
        )
    )
    print()
    print(
        _harness.table(
            ["operation", "ns per event", "/ bare call", "% of a dedup hit"],
            [(n, f"{ns:.0f}", f"{ns / base:.1f}x", f"{100 * ns / dedup:.2f}%") for n, ns in rows],
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
