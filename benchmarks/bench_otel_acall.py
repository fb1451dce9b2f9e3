"""10,000 traced `acall`s with coroutine loads: is every span's parent the expected one?

The figure of issue 55: "10,000 `acall`s with coroutine loads: every span's parent is the
caller's span, 0 context errors". One event loop makes `--count` steps, `--batch` at a
time under `asyncio.gather`; each step opens its own span (`step <n>`), awaits, makes one
`acall` (a request of its own: no dedup hit) and `aunload`s it. The provider's `load` and
`unload` are coroutines; the load awaits, opens a span of its own (`inside the load`),
awaits again. `otel.Tracing` subscribers of both registrars make the CLIENT, SERVER and
callback spans from the events; everything is exported to an `InMemorySpanExporter`.

Counted afterwards, per kind of span (a wrong parent: a parent that is not the expected
span of the same step; missing: a span of a step not exported):

    step                   a root (no parent)
    CLIENT (call)          its step's span
    SERVER (load)          the CLIENT span of its query id
    cam.load               the SERVER span of its query id
    inside the load        the SERVER span of its step's query id (the load's context)
    CLIENT (unload)        its step's span
    SERVER (release)       the CLIENT span of its unload

and the context errors: exceptions a step raised (a `ValueError` "was created in a
different Context" from `contextvars`, any other), the event loop's unhandled exceptions
(its exception handler), and warnings or errors OpenTelemetry logged (its context's
"Failed to detach context", ...). The time per step is printed beside, with the same
steps untraced (no subscriber, no caller span) in the same run as the floor.

    taskset -c 0 python benchmarks/bench_otel_acall.py [--count 10000] [--batch 500]
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import logging
import os
import platform
import sys
import time
import uuid
from typing import Any

from opentelemetry import trace as api
from opentelemetry.sdk.trace import ReadableSpan, TracerProvider
from opentelemetry.sdk.trace.export import SimpleSpanProcessor
from opentelemetry.sdk.trace.export.in_memory_span_exporter import InMemorySpanExporter

import rr_actors as rr
from rr_actors_lab import otel


class _Logged(logging.Handler):
    """Counts the warnings and errors OpenTelemetry logs (its detach failures among them)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def _run(count: int, batch: int, *, traced: bool, paced: bool = True) -> dict[str, Any]:
    """`count` steps, `batch` at a time; the spans exported and the errors seen."""
    exporter = InMemorySpanExporter()
    provider = TracerProvider()
    provider.add_span_processor(SimpleSpanProcessor(exporter))
    tracer = provider.get_tracer("the application")
    uid = uuid.uuid4().hex[:8]
    erm = rr.ResourceRegistrar.start(f"erm-{uid}")
    app = rr.ResourceRegistrar.start(f"app-{uid}")

    async def load(request: int) -> int:
        await asyncio.sleep(0)
        if traced:
            with tracer.start_as_current_span("inside the load", attributes={"step": request}):
                await asyncio.sleep(0)
        return request

    async def unload(_request: int, _response: int) -> None:
        await asyncio.sleep(0)

    erm.register_server("cam", load=load, unload=unload)
    caller_of: dict[str, tuple[int, int]] = {}  # query id: (step, the step's span id)
    raised: list[BaseException] = []
    unhandled: list[dict[str, Any]] = []

    async def step(n: int) -> None:
        if not traced:
            query = await app.acall(erm.name, "cam", n, timeout=60)
            await app.aunload(query.id, timeout=60)
            return
        with tracer.start_as_current_span(f"step {n}", attributes={"step": n}) as span:
            await asyncio.sleep(0)
            query = await app.acall(erm.name, "cam", n, timeout=60)
            caller_of[query.id] = (n, span.get_span_context().span_id)
            await asyncio.sleep(0)
            await app.aunload(query.id, timeout=60)

    async def steps() -> float:
        asyncio.get_running_loop().set_exception_handler(lambda _loop, c: unhandled.append(c))
        began = time.perf_counter()
        for first in range(0, count, batch):
            done = await asyncio.gather(
                *(step(n) for n in range(first, min(count, first + batch))),
                return_exceptions=True,
            )
            raised.extend(e for e in done if isinstance(e, BaseException))
            if paced and tracings:  # the subscribers catch up: no event dropped
                await asyncio.to_thread(_delivered)
        return time.perf_counter() - began

    def _delivered() -> None:
        for tracing in tracings:
            tracing._subscription.wait_delivered(timeout=120)

    tracings: list[otel.Tracing] = []
    tracings = (
        [
            otel.trace(r, tracer_provider=provider, pair_within=120, max_pending=4 * batch + 100)
            for r in (app, erm)
        ]
        if traced
        else []
    )
    try:
        seconds = asyncio.run(steps())
        app.client_queries(timeout=60)  # (a later turn: the events of the last are out)
        erm.client_queries(timeout=60)
        for tracing in tracings:
            tracing.close(timeout=120)
    finally:
        app.stop(timeout=30)
        erm.stop(timeout=30)
    return {
        "seconds": seconds,
        "spans": exporter.get_finished_spans(),
        "caller_of": caller_of,
        "raised": raised,
        "unhandled": unhandled,
        "dropped": sum(t.dropped for t in tracings),
    }


def _check(count: int, run: dict[str, Any]) -> dict[str, tuple[int, int, int]]:
    """Per kind of span: (exported, wrong parent, missing)."""
    spans: tuple[ReadableSpan, ...] = run["spans"]
    caller_of: dict[str, tuple[int, int]] = run["caller_of"]
    by_id = {s.context.span_id: s for s in spans}
    of_query: dict[tuple[str, api.SpanKind, str], ReadableSpan] = {}
    for s in spans:
        if s.kind in (api.SpanKind.CLIENT, api.SpanKind.SERVER):
            outcome = str(s.attributes.get("rr_actors.outcome", ""))
            verb = "call" if outcome in ("answered", "loaded") else "unload"
            of_query[(str(s.attributes["rr_actors.query_id"]), s.kind, verb)] = s
    step_query = {n: q for q, (n, _) in caller_of.items()}
    table: dict[str, list[int]] = collections.defaultdict(lambda: [0, 0, 0])

    def check(kind: str, span: ReadableSpan | None, expected: int | None) -> None:
        row = table[kind]
        if span is None:
            row[2] += 1
            return
        row[0] += 1
        parent = span.parent.span_id if span.parent is not None else None
        if parent != expected or (expected is not None and expected not in by_id):
            row[1] += 1

    steps = {int(s.attributes["step"]): s for s in spans if s.name.startswith("step ")}
    insides = {int(s.attributes["step"]): s for s in spans if s.name == "inside the load"}
    loads = {s.attributes.get("rr_actors.resource_id"): s for s in spans if s.name == "cam.load"}
    for n in range(count):
        check("step", steps.get(n), None)
        query = step_query.get(n)
        if query is None:
            for kind in ("CLIENT (call)", "SERVER (load)", "cam.load", "inside the load"):
                table[kind][2] += 1
            continue
        span_id = caller_of[query][1]
        client = of_query.get((query, api.SpanKind.CLIENT, "call"))
        server = of_query.get((query, api.SpanKind.SERVER, "call"))
        check("CLIENT (call)", client, span_id)
        check("SERVER (load)", server, client.context.span_id if client else -1)
        resource = server.attributes.get("rr_actors.resource_id") if server else None
        check("cam.load", loads.get(resource), server.context.span_id if server else -1)
        check("inside the load", insides.get(n), server.context.span_id if server else -1)
        unload = of_query.get((query, api.SpanKind.CLIENT, "unload"))
        release = of_query.get((query, api.SpanKind.SERVER, "unload"))
        check("CLIENT (unload)", unload, span_id)
        check("SERVER (release)", release, unload.context.span_id if unload else -1)
    orphans = sum(1 for s in spans if s.parent is not None and s.parent.span_id not in by_id)
    table["(any span) orphan"] = [len(spans), orphans, 0]
    return {kind: (row[0], row[1], row[2]) for kind, row in table.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=10_000, help="steps (acalls)")
    parser.add_argument("--batch", type=int, default=500, help="steps under one gather")
    parser.add_argument(
        "--unpaced",
        action="store_true",
        help="do not wait for the subscribers after each gather (their queues may overflow)",
    )
    args = parser.parse_args(argv)
    if args.count < 1 or args.batch < 1:
        parser.error("--count and --batch must be at least 1")
    logged = _Logged()
    logging.getLogger("opentelemetry").addHandler(logged)
    floor = _run(args.count, args.batch, traced=False)
    run = _run(args.count, args.batch, traced=True, paced=not args.unpaced)
    table = _check(args.count, run)
    print(
        f"# {args.count} acalls with coroutine loads, {args.batch} per gather"
        f"{' (unpaced)' if args.unpaced else ', the subscribers caught up after each'}; "
        f"python {platform.python_version()}, load {os.getloadavg()[0]:.1f}"
    )
    print(f"{'span':<20} {'exported':>9} {'wrong parent':>13} {'missing':>8}")
    for kind, (exported, wrong, missing) in table.items():
        print(f"{kind:<20} {exported:>9} {wrong:>13} {missing:>8}")
    contexts = [e for e in run["raised"] if "different Context" in str(e)]
    print(
        f"{'context errors':<20} {len(contexts):>9}  (ValueError: created in a different Context)"
    )
    print(f"{'other exceptions':<20} {len(run['raised']) - len(contexts):>9}")
    print(f"{'loop unhandled':<20} {len(run['unhandled']):>9}")
    print(f"{'events dropped':<20} {run['dropped']:>9}  (the subscribers' queues overflowed)")
    print(f"{'otel logged':<20} {len(logged.records):>9}  (warnings, errors: detach failures)")
    for error in run["raised"][:3]:
        print(f"  raised: {type(error).__name__}: {error}")
    for record in logged.records[:3]:
        print(f"  logged: {record.getMessage()}")
    per = 1e6 / args.count
    print(
        f"time per step: untraced {floor['seconds'] * per:.0f} us, traced "
        f"{run['seconds'] * per:.0f} us ({run['seconds'] / floor['seconds']:.2f}x; paced: "
        "with the subscribers' work)"
    )
    wrong = sum(w + m for kind, (_, w, m) in table.items())
    errors = len(run["raised"]) + len(run["unhandled"]) + len(logged.records) + len(floor["raised"])
    return 1 if wrong or errors else 0


if __name__ == "__main__":
    sys.exit(main())
