"""What tracing (`rr_actors.otel`) costs a cross-process dedup hit, spans exported to a file.

A consumer registrar in this process calls a resource a manager process already serves
(a dedup hit over AF_UNIX), `--batch` times per round; one `otel.trace(sup)` subscriber
of the tree (this process's events and the manager's, forwarded) makes the spans. The
table shows the median time per call over `--rounds` rounds, each row measured in every
round (interleaved: other processes' noise spreads evenly), and its ratio to `tracing
off`, measured in the same run (the issue's goal for `tracing on`: at most 1.10x).

Rows:
    floor          nobody subscribed to the tree
    tracing off    `otel.trace(sup)` with no `TracerProvider` (the API's no-op one): the
                   subscription (the manager forwards its events) and one look-up an
                   event, no span made
    spans only     `otel.trace(sup, tracer_provider=...)`: an SDK provider sampling
                   everything (ALWAYS_ON) with no span processor: the spans made, not
                   exported (what the subscriber and the SDK's spans cost)
    tracing on     `otel.trace(sup, tracer_provider=...)`: an SDK provider sampling
                   everything (ALWAYS_ON), a `BatchSpanProcessor` exporting to a file
                   (`ConsoleSpanExporter`, one JSON line a span), 2 spans a call
    traced         `tracing on` with a span current in the caller: the calls' spans are
                   made under it, with the ids the calls carried

A round is timed until everything it caused is done: the manager's events forwarded
(`flush_events`), the subscription's queue taken (`wait_delivered`), every span written
(`force_flush`); the subscriber's and the exporter's threads compete for the GIL, so
their work counts. The held query ids are unloaded after each timed batch, untimed.
The CPU columns count the same rounds' CPU time of every thread of both processes
(`/proc/<pid>/task/*/schedstat`, Linux; a thread that ended meanwhile is missed): on a
loaded machine the wall-clock medians swing with the load, the CPU a call costs less.

    taskset -c 0 python benchmarks/bench_otel_cross.py [--rounds 15] [--batch 1000]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import statistics
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

from opentelemetry.sdk.trace import TracerProvider
from opentelemetry.sdk.trace.export import BatchSpanProcessor, ConsoleSpanExporter
from opentelemetry.sdk.trace.sampling import ALWAYS_ON

import rr_actors as rr
from rr_actors import otel


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


ROWS = ("floor", "tracing off", "spans only", "tracing on", "traced")


def serve(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("res", load=lambda r: r, unload=lambda _q, _r: None)


def line(span: Any) -> str:
    return str(span.to_json(indent=None)) + "\n"


class Bench:
    def __init__(self, spans: Path) -> None:
        tag = uuid.uuid4().hex[:6]
        self.name = f"bench-{tag}"
        spec = rr.ManagerSpec(self.name, serve, isolation="process", start_timeout=120.0)
        self.sup = rr.Supervisor([spec]).start()
        self.app = self.sup.registrar(f"app-{tag}")
        self.first = self.app.call(self.name, "res", "shared", timeout=60)
        self.out = spans.open("a", encoding="utf-8")
        self.provider = TracerProvider(sampler=ALWAYS_ON)
        self.processor = BatchSpanProcessor(
            ConsoleSpanExporter(out=self.out, formatter=line), max_queue_size=1 << 20
        )
        self.provider.add_span_processor(self.processor)
        self.bare = TracerProvider(sampler=ALWAYS_ON)  # (no processor: nothing exported)
        self.caller = TracerProvider(sampler=ALWAYS_ON).get_tracer("bench")  # (no processor)
        self.spans = spans
        self.written = 0
        self.per_call: dict[str, float] = {}
        self.cpu: dict[str, list[float]] = {row: [] for row in ROWS}  # seconds per call

    def stop(self) -> None:
        self.sup.stop()
        self.provider.shutdown()
        self.out.close()

    def round(self, row: str, batch: int) -> float:
        """Seconds per call of one batch of dedup hits in `row`'s setting."""
        tracing = None
        if row == "tracing off":
            tracing = otel.trace(self.sup, pair_within=60, max_pending=4 * batch + 100)
        elif row == "spans only":
            tracing = otel.trace(
                self.sup, tracer_provider=self.bare, pair_within=60, max_pending=4 * batch + 100
            )
        elif row in ("tracing on", "traced"):
            tracing = otel.trace(
                self.sup, tracer_provider=self.provider, pair_within=60, max_pending=4 * batch + 100
            )
        call, name, app = self.app.call, self.name, self.app
        span = (
            self.caller.start_as_current_span("step")
            if row == "traced"
            else contextlib.nullcontext()
        )
        pids = [os.getpid(), self.sup.child(self.name).pid or 0]
        with span:
            cpu = cpu_seconds(pids)
            began = time.perf_counter()
            held = [call(name, "res", "shared", timeout=60).id for _ in range(batch)]
            app.client_queries(timeout=60)  # (a later turn: the last CallAnswered is out)
            assert self.sup.flush_events(timeout=60)
            if tracing is not None:
                assert tracing._subscription.wait_delivered(timeout=60)
                self.processor.force_flush(timeout_millis=60_000)
            took = time.perf_counter() - began
            self.cpu[row].append((cpu_seconds(pids) - cpu) / batch)
        for query_id in held:
            app.unload(query_id, timeout=60)
        app.client_queries(timeout=60)
        if tracing is not None:
            assert self.sup.flush_events(timeout=60)
            tracing.close(timeout=60)
            assert tracing.dropped == 0
            self.processor.force_flush(timeout_millis=60_000)
        written = sum(1 for _ in self.spans.open(encoding="utf-8"))
        self.per_call[row] = (written - self.written) / (2 * batch)  # a call and its unload
        self.written = written
        return took / batch


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--batch", type=int, default=1000)
    args = parser.parse_args(argv)

    times: dict[str, list[float]] = {row: [] for row in ROWS}
    with tempfile.TemporaryDirectory() as folder:
        bench = Bench(Path(folder) / "spans.jsonl")
        try:
            for row in ROWS:  # warm-up, untimed
                bench.round(row, max(1, args.batch // 10))
            for _ in range(args.rounds):
                for row in ROWS:
                    times[row].append(bench.round(row, args.batch))
        finally:
            bench.stop()

    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "?"
    print(
        f"python {platform.python_version()} on {platform.machine()}, CPUs {cpus}, "
        f"load {os.getloadavg()[0]:.2f}; {args.rounds} rounds x {args.batch} "
        "cross-process dedup hits"
    )
    off = statistics.median(times["tracing off"])
    floor = statistics.median(times["floor"])
    cpu_off = statistics.median(bench.cpu["tracing off"][-args.rounds :])
    print(
        f"{'row':<12} {'us/call':>9} {'vs floor':>9} {'vs off':>8} {'cpu us':>8} {'vs off':>8}"
        f" {'spans/op':>9}"
    )
    for row in ROWS:
        median = statistics.median(times[row])
        cpu = statistics.median(bench.cpu[row][-args.rounds :])  # (not the warm-up's)
        print(
            f"{row:<12} {median * 1e6:>9.1f} {median / floor:>8.3f}x {median / off:>7.3f}x"
            f" {cpu * 1e6:>8.1f} {cpu / cpu_off:>7.3f}x {bench.per_call[row]:>9.1f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
