"""What tracing (`rr_actors_lab.otel`) costs a cross-process dedup hit, spans exported to a file.

A consumer registrar in this process calls a resource a manager process already serves
(a dedup hit over AF_UNIX), `--batch` times per round; one `otel.trace(sup)` subscriber
of the tree (this process's events and the manager's, forwarded) makes the spans. The
table shows the median time per call over `--rounds` rounds, each row measured in every
round (interleaved, each round starting one row later: other processes' noise, and what
a row leaves running for the next, spread evenly), and its ratio to `untraced`, the same
call with nobody subscribed, measured in the same run.

Rows:
    untraced       nobody subscribed to the tree, no tracing
    tracing off    `otel.trace(sup)` with no `TracerProvider` (the API's proxy, none
                   installed): what "tracing on, no provider" costs
    subscribed, no provider
                   `sup.subscribe(otel.Tracing())`, no provider: a subscriber of the
                   tree that drops each event (the manager forwards its events; what
                   `tracing off` cost before it stopped subscribing)
    spans only     `otel.trace(sup, tracer_provider=...)`: an SDK provider sampling
                   everything (ALWAYS_ON) with no span processor: the spans made, not
                   exported (what the subscriber and the SDK's spans cost)
    on: <exporter> `otel.trace(sup, tracer_provider=...)`: an SDK provider sampling
                   everything (ALWAYS_ON), a `BatchSpanProcessor` (what a user runs, and
                   what `--trace` sets up) exporting to a file of its own, 2 spans a
                   call; one row per `--exporter`:
                     console    the SDK's `ConsoleSpanExporter`, one JSON line a span
                                (`ReadableSpan.to_json`)
                     otlp-file  OTLP protobuf (`opentelemetry-exporter-otlp-proto-common`'s
                                `encode_spans`, what the OTLP exporters send): each batch
                                one `ExportTraceServiceRequest`, its length before it
    sampled 10%    the first exporter's row with `ParentBased(TraceIdRatioBased(0.1))`
                   (`OTEL_TRACES_SAMPLER=parentbased_traceidratio`,
                   `OTEL_TRACES_SAMPLER_ARG=0.1`): a trace in ten exported
    traced         the first exporter's row with a span current in the caller: the
                   calls' spans are made under it, with the ids the calls carried

A round is timed until everything it caused is done: the manager's events forwarded
(`flush_events`), the subscription's queue taken (`wait_delivered`), every span written
(`force_flush`); the subscriber's and the exporter's threads compete for the GIL, so
their work counts. The held query ids are unloaded after each timed batch, untimed.
The CPU columns count the same rounds' CPU time of every thread of both processes
(`/proc/<pid>/task/*/schedstat`, Linux; a thread that ended meanwhile is missed): on a
loaded machine the wall-clock medians swing with the load, the CPU a call costs less.

    taskset -c 0 python benchmarks/bench_otel_cross.py [--rounds 15] [--batch 1000]
        [--exporter console,otlp-file]   (default: both, otlp-file where installed)
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import _harness
from opentelemetry.sdk.trace import TracerProvider
from opentelemetry.sdk.trace.export import (
    BatchSpanProcessor,
    ConsoleSpanExporter,
    SpanExporter,
    SpanExportResult,
)
from opentelemetry.sdk.trace.sampling import ALWAYS_ON, ParentBased, TraceIdRatioBased

import rr_actors as rr
from rr_actors_lab import otel

EXPORTERS = ("console", "otlp-file")


def cpu_seconds(pids: list[int]) -> float:
    """CPU seconds so far of the live threads of `pids` (0.0 where /proc has none)."""
    total = 0
    for pid in pids:
        with contextlib.suppress(OSError):
            for task in os.listdir(f"/proc/{pid}/task"):
                path = f"/proc/{pid}/task/{task}/schedstat"
                with contextlib.suppress(OSError), open(path) as stat:  # (one ended)
                    total += int(stat.read().split()[0])
    return total / 1e9


def serve(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("res", load=lambda r: r, unload=lambda _q, _r: None)


def line(span: Any) -> str:
    return str(span.to_json(indent=None)) + "\n"


class OtlpFile(SpanExporter):
    """OTLP protobuf to a file: each batch one `ExportTraceServiceRequest` (what the OTLP
    exporters send, encoded by their common package), its length (4 bytes) before it."""

    def __init__(self, out: Any) -> None:
        from opentelemetry.exporter.otlp.proto.common.trace_encoder import (  # noqa: PLC0415
            encode_spans,
        )

        self.encode, self.out = encode_spans, out

    def export(self, spans: Any) -> SpanExportResult:
        data = self.encode(spans).SerializeToString()
        self.out.write(len(data).to_bytes(4, "big") + data)
        return SpanExportResult.SUCCESS

    def force_flush(self, timeout_millis: int = 30_000) -> bool:
        self.out.flush()
        return True


class Counted(SpanExporter):
    """An exporter, and the spans it was given."""

    def __init__(self, inner: SpanExporter) -> None:
        self.inner, self.count = inner, 0

    def export(self, spans: Any) -> SpanExportResult:
        self.count += len(spans)
        return self.inner.export(spans)

    def force_flush(self, timeout_millis: int = 30_000) -> bool:
        return bool(self.inner.force_flush(timeout_millis))


def installed(exporter: str) -> bool:
    if exporter != "otlp-file":
        return True
    try:
        import opentelemetry.exporter.otlp.proto.common.trace_encoder  # noqa: F401, PLC0415
    except ImportError:
        return False
    return True


class Bench:
    def __init__(self, folder: Path, exporters: list[str]) -> None:
        tag = uuid.uuid4().hex[:6]
        self.name = f"bench-{tag}"
        spec = rr.ManagerSpec(self.name, serve, isolation="process", start_timeout=120.0)
        self.sup = rr.Supervisor([spec]).start()
        self.app = self.sup.registrar(f"app-{tag}")
        self.first = self.app.call(self.name, "res", "shared", timeout=60)
        self.rows = ["untraced", "tracing off", "subscribed, no provider", "spans only"]
        self.providers: dict[str, tuple[TracerProvider, BatchSpanProcessor, Counted]] = {}
        self.files: list[Any] = []
        for exporter in exporters:
            self.rows.append(f"on: {exporter}")
            self._provider(f"on: {exporter}", exporter, folder, ALWAYS_ON)
        first = exporters[0]
        self.rows += [f"sampled 10%: {first}", f"traced: {first}"]
        sampled = ParentBased(TraceIdRatioBased(0.1))
        self._provider(f"sampled 10%: {first}", first, folder, sampled)
        self.providers[f"traced: {first}"] = self.providers[f"on: {first}"]
        self.bare = TracerProvider(sampler=ALWAYS_ON)  # (no processor: nothing exported)
        self.caller = TracerProvider(sampler=ALWAYS_ON).get_tracer("bench")  # (no processor)
        self.written: dict[int, int] = {}
        self.per_call: dict[str, float] = {}
        self.cpu: dict[str, list[float]] = {row: [] for row in self.rows}  # seconds per call

    def _provider(self, row: str, exporter: str, folder: Path, sampler: Any) -> None:
        path = folder / f"{len(self.files)}-{exporter}"
        if exporter == "console":
            out = path.open("a", encoding="utf-8")
            inner: SpanExporter = ConsoleSpanExporter(out=out, formatter=line)
        else:
            out = path.open("ab")
            inner = OtlpFile(out)
        self.files.append(out)
        counted = Counted(inner)
        provider = TracerProvider(sampler=sampler)
        processor = BatchSpanProcessor(counted, max_queue_size=1 << 20)
        provider.add_span_processor(processor)
        self.providers[row] = (provider, processor, counted)

    def stop(self) -> None:
        self.sup.stop()
        for provider, _processor, _counted in self.providers.values():
            provider.shutdown()
        for out in self.files:
            out.close()

    def round(self, row: str, batch: int) -> float:
        """Seconds per call of one batch of dedup hits in `row`'s setting."""
        tracing, subscription = None, None
        exporting = self.providers.get(row)
        if row == "tracing off":
            tracing = otel.trace(self.sup, pair_within=60, max_pending=4 * batch + 100)
        elif row == "subscribed, no provider":
            subscription = self.sup.subscribe(otel.Tracing(pair_within=60))
        elif row == "spans only":
            tracing = otel.trace(
                self.sup, tracer_provider=self.bare, pair_within=60, max_pending=4 * batch + 100
            )
        elif exporting is not None:
            tracing = otel.trace(
                self.sup, tracer_provider=exporting[0], pair_within=60, max_pending=4 * batch + 100
            )
        call, name, app = self.app.call, self.name, self.app
        span = (
            self.caller.start_as_current_span("step")
            if row.startswith("traced")
            else contextlib.nullcontext()
        )
        if tracing is not None:
            subscription = tracing._subscription  # (None: not subscribed, tracing off)
        pids = [os.getpid(), self.sup.child(self.name).pid or 0]
        with span:
            cpu = cpu_seconds(pids)
            began = time.perf_counter()
            held = [call(name, "res", "shared", timeout=60).id for _ in range(batch)]
            app.client_queries(timeout=60)  # (a later turn: the last CallAnswered is out)
            assert self.sup.flush_events(timeout=60)
            if subscription is not None:
                assert subscription.wait_delivered(timeout=60)
            if exporting is not None:
                exporting[1].force_flush(timeout_millis=60_000)
            took = time.perf_counter() - began
            self.cpu[row].append((cpu_seconds(pids) - cpu) / batch)
        for query_id in held:
            app.unload(query_id, timeout=60)
        app.client_queries(timeout=60)
        if tracing is not None:
            assert self.sup.flush_events(timeout=60)
            tracing.close(timeout=60)
            assert tracing.dropped == 0
        elif subscription is not None:
            assert self.sup.flush_events(timeout=60)
            subscription.close(timeout=60)
        written = 0
        if exporting is not None:
            exporting[1].force_flush(timeout_millis=60_000)
            counted = exporting[2]
            written = counted.count - self.written.get(id(counted), 0)
            self.written[id(counted)] = counted.count
        self.per_call[row] = written / (2 * batch)  # a call and its unload
        return took / batch


def main(argv: list[str] | None = None) -> int:
    parser = _harness.options(__doc__, rounds=15, batch=1000)
    parser.add_argument(
        "--exporter",
        default=",".join(e for e in EXPORTERS if installed(e)),
        help=f"comma-separated, of {', '.join(EXPORTERS)} (default: those installed)",
    )
    args = _harness.parse(parser, argv)
    exporters = [e.strip() for e in args.exporter.split(",") if e.strip()]
    for exporter in exporters:
        if exporter not in EXPORTERS:
            parser.error(f"--exporter {exporter!r}: one of {', '.join(EXPORTERS)}")
        if not installed(exporter):
            parser.error(
                f"--exporter {exporter}: pip install opentelemetry-exporter-otlp-proto-common"
            )
    if not exporters:
        parser.error("--exporter: at least one")

    with tempfile.TemporaryDirectory() as folder:
        bench = Bench(Path(folder), exporters)
        rows = bench.rows
        try:  # (each round starts one row later: none always pays for what the last left)
            times = _harness.alternate(
                {row: (lambda row=row: bench.round(row, args.batch)) for row in rows},
                args.rounds,
                rotate=True,
            )
        finally:
            bench.stop()

    print(_harness.header(f"{args.rounds} rounds x {args.batch} cross-process dedup hits"))
    untraced = _harness.median(times["untraced"])
    cpu_untraced = _harness.median(bench.cpu["untraced"][-args.rounds :])
    table = []
    for row in rows:
        median = _harness.median(times[row])
        cpu = _harness.median(bench.cpu[row][-args.rounds :])  # (not the warm-up's)
        table.append(
            (
                row,
                f"{median * 1e6:.1f}",
                f"{median / untraced:.3f}x",
                f"{cpu * 1e6:.1f}",
                f"{cpu / cpu_untraced:.3f}x",
                f"{bench.per_call[row]:.1f}",
            )
        )
    print(
        _harness.table(
            ["row", "µs/call", "vs untraced", "CPU µs/call", "vs untraced", "spans/op"], table
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
