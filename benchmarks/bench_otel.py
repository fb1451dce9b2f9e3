"""What tracing with OpenTelemetry (`rr_actors_lab.otel`) costs an in-process dedup-hit call.

One consumer registrar calls a resource another one already serves (a dedup hit), `--batch`
times per round; the table shows the median time per call over `--rounds` rounds, each row
measured in every round (interleaved, so that other processes' noise spreads evenly), and its
ratio to the first row, measured in the same run:

Rows:
    no extra                no subscriber, and a call that looks for no trace context at
                            all (`rr_actors._core.traces.begin` replaced by a function
                            returning `None`): the floor
    without                 no subscriber, the extra installed, no span current in the
                            caller: what an untraced call pays for looking (goal: 1.01x)
    caller's span           no subscriber, a span current in the caller (an SDK provider
                            with no processor): each call draws a CLIENT span id and
                            carries its traceparent (`Load.trace`)
    no-op subscriber        one subscriber (a no-op callback) of both registrars: what any
                            subscription costs (the floor of the next rows)
    tracing off             `otel.Tracing()` subscribed to both by hand, the extra installed
                            but no `TracerProvider` (the API's no-op one): no span is made
                            (`otel.trace` with no provider subscribes nothing: `without`)
    tracing on              `otel.Tracing(tracer_provider=...)`: an SDK provider sampling
                            everything (ALWAYS_ON) into an `InMemorySpanExporter` through a
                            `SimpleSpanProcessor` (2 spans per call and per unload: client, server)
    tracing on, traced      `tracing on` with a span current in the caller: the spans are
                            made with the ids the calls carried, under the caller's span

A round's time runs until the subscriptions delivered every event of the batch
(`wait_delivered`): the subscriber thread's work competes for the GIL, so it is counted.
The held query ids are unloaded after each timed batch, untimed.

Pin it to one CPU for stable ratios:

    taskset -c 0 python benchmarks/bench_otel.py [--rounds 15] [--batch 2000]

The ratios of the rows to `no extra` are printed beside those to `without`.
"""

from __future__ import annotations

import contextlib
import sys
import time
import uuid
from collections.abc import Callable
from typing import Any

import _harness
from opentelemetry.sdk.trace import TracerProvider
from opentelemetry.sdk.trace.export import SimpleSpanProcessor
from opentelemetry.sdk.trace.export.in_memory_span_exporter import InMemorySpanExporter
from opentelemetry.sdk.trace.sampling import ALWAYS_ON

import rr_actors as rr
from rr_actors import events, otel
from rr_actors._core import traces


def noop(_: events.Event) -> None:
    return None


def nothing() -> None:
    return None


class Bench:
    def __init__(self) -> None:
        suffix = uuid.uuid4().hex[:6]
        self.provider = rr.ResourceRegistrar.start(f"bench-provider-{suffix}")
        self.consumer = rr.ResourceRegistrar.start(f"bench-consumer-{suffix}")
        self.provider.register_server("res", load=lambda r: r, unload=lambda _q, _r: None)
        self.first = self.consumer.call(self.provider.name, "res", "shared")
        self.exporter = InMemorySpanExporter()
        tracer_provider = TracerProvider(sampler=ALWAYS_ON)
        tracer_provider.add_span_processor(SimpleSpanProcessor(self.exporter))
        tracing_on = otel.Tracing(tracer_provider=tracer_provider, pair_within=60)
        self.subscribers: dict[str, Callable[[events.Event], object] | None] = {
            "no extra": None,
            "without": None,
            "caller's span": None,
            "no-op subscriber": noop,
            "tracing off": otel.Tracing(),
            "tracing on": tracing_on,
            "tracing on, traced": tracing_on,
        }
        self.caller = TracerProvider(sampler=ALWAYS_ON).get_tracer("bench")  # (no processor)
        self.spans: dict[str, float] = {}  # spans per operation (a call or an unload)

    def stop(self) -> None:
        self.consumer.stop()
        self.provider.stop()

    def round(self, row: str, batch: int) -> float:
        """Seconds per call of one batch of dedup hits with `row`'s subscriber."""
        subscriber = self.subscribers[row]
        subscriptions: list[Any] = []
        if subscriber is not None:
            subscriptions = [
                r.subscribe(subscriber, maxsize=16 * batch) for r in (self.provider, self.consumer)
            ]
        call = self.consumer.call
        name = self.provider.name
        begin = traces.begin
        if row == "no extra":
            traces.begin = nothing  # (no look-up at all)
        span = (
            self.caller.start_as_current_span("step")
            if row in ("caller's span", "tracing on, traced")
            else contextlib.nullcontext()
        )
        try:
            with span:
                began = time.perf_counter()
                held = [call(name, "res", "shared").id for _ in range(batch)]
                for subscription in subscriptions:
                    assert subscription.wait_delivered(timeout=60)
                took = time.perf_counter() - began
        finally:
            traces.begin = begin
        for query_id in held:
            self.consumer.unload(query_id)
        for subscription in subscriptions:
            assert subscription.wait_delivered(timeout=60)
            assert subscription.dropped == 0
            subscription.close()
        if isinstance(subscriber, otel.Tracing):
            subscriber.flush()
        self.spans[row] = len(self.exporter.get_finished_spans()) / (2 * batch)
        self.exporter.clear()
        return took / batch


def main(argv: list[str] | None = None) -> int:
    args = _harness.parse(_harness.options(__doc__, rounds=15, batch=2000), argv)

    bench = Bench()
    try:
        times = _harness.alternate(
            {row: (lambda row=row: bench.round(row, args.batch)) for row in bench.subscribers},
            args.rounds,
        )
    finally:
        bench.stop()

    print(_harness.header(f"{args.rounds} rounds x {args.batch} dedup hits"))
    floor = _harness.median(times["without"])
    bare = _harness.median(times["no extra"])
    print(
        _harness.table(
            ["row", "us/call", "vs no extra", "vs without", "spans/op"],
            [
                (
                    row,
                    f"{_harness.median(t) * 1e6:.1f}",
                    f"{_harness.median(t) / bare:.3f}x",
                    f"{_harness.median(t) / floor:.3f}x",
                    f"{bench.spans[row]:.1f}",
                )
                for row, t in times.items()
            ],
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
