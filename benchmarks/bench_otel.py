"""What tracing with OpenTelemetry (`rr_actors_lab.otel`) costs, next to the same untraced.

`--where call` (default): an in-process dedup-hit call, `--batch` a round. Rows: `no
extra` (no trace look-up at all: `traces.begin` replaced; the floor), `without` (the
extra installed, no span current), `caller's span` (a span current: each call carries a
traceparent), `no-op subscriber`, `tracing off` (`otel.Tracing()`, no provider), `tracing
on` (an SDK provider, ALWAYS_ON, `InMemorySpanExporter`), `tracing on, traced` (and a span
current in the caller).

`--where cross`: a cross-process dedup hit (a manager process), one `otel.trace(sup)` of
the tree. Rows: `untraced` (the floor), `tracing off` (no provider), `subscribed, no
provider`, `spans only` (an SDK provider, no processor), `on: <exporter>` (a
`BatchSpanProcessor` to a file: `console` JSON lines, `otlp-file` OTLP protobuf),
`sampled 10%` and `traced` (the first exporter's). The CPU columns are every thread of
both processes (`/proc/<pid>/task/*/schedstat`); rounds rotate (`_harness.alternate`).

`--where mission`: `rr-actors demo --fast --quiet` once a round per row: `untraced`, `not
sampled` (`--trace`, `always_off`), `traced` (`--trace`, `always_on`, console to a file);
the report's mission time and the command's wall time, ratios to `untraced`.

A round is timed until its events are delivered and its spans written; the held ids are
unloaded after each timed batch, untimed.

    taskset -c 0 python benchmarks/bench_otel.py [--where call|cross|mission] [--rounds N]
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import _harness
from opentelemetry.sdk.trace import TracerProvider
from opentelemetry.sdk.trace.export import (
    BatchSpanProcessor,
    ConsoleSpanExporter,
    SimpleSpanProcessor,
    SpanExporter,
    SpanExportResult,
)
from opentelemetry.sdk.trace.export.in_memory_span_exporter import InMemorySpanExporter
from opentelemetry.sdk.trace.sampling import ALWAYS_ON, ParentBased, TraceIdRatioBased

import rr_actors as rr
from rr_actors import events
from rr_actors._core import traces
from rr_actors_lab import otel

EXPORTERS = ("console", "otlp-file")
DEFAULTS = {"call": (15, 2000), "cross": (15, 1000), "mission": (5, 1)}
"""`--where`: its default rounds and batch."""


def noop(_: events.Event) -> None:
    return None


def nothing() -> None:
    return None


class InProcess:
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


class Cross:
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
            cpu = _harness.cpu_seconds(pids)
            began = time.perf_counter()
            held = [call(name, "res", "shared", timeout=60).id for _ in range(batch)]
            app.client_queries(timeout=60)  # (a later turn: the last CallAnswered is out)
            assert self.sup.flush_events(timeout=60)
            if subscription is not None:
                assert subscription.wait_delivered(timeout=60)
            if exporting is not None:
                exporting[1].force_flush(timeout_millis=60_000)
            took = time.perf_counter() - began
            self.cpu[row].append((_harness.cpu_seconds(pids) - cpu) / batch)
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


MISSION = {
    "untraced": ([], {}),
    "not sampled": (["--trace"], {"OTEL_TRACES_SAMPLER": "always_off"}),
    "traced": (["--trace"], {"OTEL_TRACES_SAMPLER": "always_on"}),
}


def run(row: str, folder: Path, extra: list[str]) -> tuple[float, float, int]:
    """(mission time, wall time, spans written) of one `demo` run in `row`'s setting."""
    flags, env = MISSION[row]
    out = folder / row.replace(" ", "-")
    spans = folder / "spans.txt"
    command = [sys.executable, "-m", "rr_actors_lab", "demo", "--fast", "--quiet", *extra, *flags]
    began = time.perf_counter()
    with spans.open("w", encoding="utf-8") as written:
        subprocess.run(
            [*command, "--out", str(out)],
            stdout=written,
            stderr=subprocess.DEVNULL,
            env={**os.environ, "OTEL_TRACES_EXPORTER": "console", **env},
            check=True,
            timeout=600,
        )
    wall = time.perf_counter() - began
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    count = spans.read_text(encoding="utf-8").count('"kind": "SpanKind.')  # (one a span)
    return float(report["mission_time_s"]), wall, count


def alternated(bench: InProcess | Cross, rows: list[str], args: Any) -> dict[str, list[float]]:
    """`rows` of `bench` over `args.rounds` alternated rounds, the bench stopped after."""
    try:
        return _harness.alternate(
            {row: (lambda row=row: bench.round(row, args.batch)) for row in rows},
            args.rounds,
            rotate=isinstance(bench, Cross),  # (none always pays for what the last left)
        )
    finally:
        bench.stop()


def in_process(args: Any) -> None:
    bench = InProcess()
    times = alternated(bench, list(bench.subscribers), args)
    print(_harness.header(f"{args.rounds} rounds x {args.batch} dedup hits"))
    floor, bare = _harness.median(times["without"]), _harness.median(times["no extra"])
    rows = []
    for row, samples in times.items():
        took = _harness.median(samples)
        spans = f"{bench.spans[row]:.1f}"
        rows.append(
            (row, f"{took * 1e6:.1f}", f"{took / bare:.3f}x", f"{took / floor:.3f}x", spans)
        )
    print(_harness.table(["row", "us/call", "vs no extra", "vs without", "spans/op"], rows))


def cross_process(args: Any, exporters: list[str]) -> None:
    with tempfile.TemporaryDirectory() as folder:
        bench = Cross(Path(folder), exporters)
        times = alternated(bench, bench.rows, args)
    print(_harness.header(f"{args.rounds} rounds x {args.batch} cross-process dedup hits"))
    untraced = _harness.median(times["untraced"])
    cpu_untraced = _harness.median(bench.cpu["untraced"][-args.rounds :])
    rows = []
    for row in bench.rows:
        took = _harness.median(times[row])
        cpu = _harness.median(bench.cpu[row][-args.rounds :])  # (not the warm-up's)
        ratios = (f"{took / untraced:.3f}x", f"{cpu * 1e6:.1f}", f"{cpu / cpu_untraced:.3f}x")
        rows.append((row, f"{took * 1e6:.1f}", *ratios, f"{bench.per_call[row]:.1f}"))
    columns = ["row", "us/call", "vs untraced", "CPU us/call", "vs untraced", "spans/op"]
    print(_harness.table(columns, rows))


def mission(args: Any) -> None:
    extra = ["--faults", args.faults] if args.faults else []
    extra += ["--distance", args.distance] if args.distance else []
    runs: dict[str, list[tuple[float, float, int]]] = {row: [] for row in MISSION}
    with tempfile.TemporaryDirectory() as folder:

        def once(row: str) -> float:
            runs[row].append(run(row, Path(folder), extra))
            return runs[row][-1][1]

        _harness.alternate(
            {row: (lambda row=row: once(row)) for row in MISSION}, args.rounds, warm_up=False
        )
    print(_harness.header(f"{args.rounds} rounds of `demo --fast {' '.join(extra)}`"))
    floor = [_harness.median(r[i] for r in runs["untraced"]) for i in (0, 1)]
    rows = []
    for row, done in runs.items():
        took, whole = (_harness.median(r[i] for r in done) for i in (0, 1))
        ratios = (f"{took / floor[0]:.3f}x", f"{whole:.2f}", f"{whole / floor[1]:.3f}x")
        rows.append((row, f"{took:.3f}", *ratios, done[-1][2]))
    print(_harness.table(["row", "mission s", "ratio", "wall s", "ratio", "spans"], rows))


def main(argv: list[str] | None = None) -> int:
    parser = _harness.options(__doc__, rounds=0, batch=0)
    parser.add_argument("--where", choices=list(DEFAULTS), default="call", help="what is traced")
    parser.add_argument(
        "--exporter",
        default=",".join(e for e in EXPORTERS if installed(e)),
        help=f"cross: comma-separated, of {', '.join(EXPORTERS)} (default: those installed)",
    )
    parser.add_argument("--faults", default="", help="mission: demo's --faults (default: all)")
    parser.add_argument("--distance", default="", help="mission: demo's --distance")
    args = _harness.parse(parser, argv)
    args.rounds = args.rounds or DEFAULTS[args.where][0]
    args.batch = args.batch or DEFAULTS[args.where][1]
    exporters = [e.strip() for e in args.exporter.split(",") if e.strip()]
    wrong = [e for e in exporters if e not in EXPORTERS or not installed(e)]
    if wrong or not exporters:
        parser.error(f"--exporter {args.exporter!r}: of {', '.join(EXPORTERS)}, installed")
    if args.where == "call":
        in_process(args)
    elif args.where == "cross":
        cross_process(args, exporters)
    else:
        mission(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
