"""A system-wide event subscriber's memory under a flood of big event batches from one member.

Issue 40: 40 batches of 14.3 MiB from one member (each under the 16 MiB a batch may have)
raised a `ZenohNetwork.subscribe_events` subscriber's memory from 45 to 632 MiB, still
there a minute later, with no WARNING. Now what a subscriber holds is bounded
(`rr_actors_lab.observe._feed.HELD_BYTES`, `QUEUED_BYTES`); what is past the
bounds is dropped, counted in an `EventsDropped` and warned of.

Each row runs in a fresh Python process (its memory is its own): a `ZenohNetwork` on its
Unix socket only (the process is the router), a raw Zenoh session attached through it
(the flooding member) putting `--batches` batches of `--mib` MiB of valid event lines
(`--kind small`: 250-byte events, some 60,000 a batch; `big`: 1 MiB events, 14 a batch),
then one sentinel event. Its resident set size (psutil) is read before the flood, every
10 ms during it (the peak), once the sentinel was handled, and `--settle` s later.

Rows:
    Zenoh alone (floor)     a plain Zenoh subscriber on the router's session that takes each
                            sample's bytes and drops them: what Zenoh's own buffers cost
    subscribe_events        `net.subscribe_events(callback, window=0.5)`, a callback that
                            counts: the subscriber's bounds at work

The last column is the peak's rise over the floor's rise: what the subscriber holds on
top of what Zenoh itself holds. To compare with another tree (main before the fix):

    PYTHONPATH=/path/to/other/tree python benchmarks/bench_events_flood.py

    python benchmarks/bench_events_flood.py [--batches 40] [--mib 14.3] [--kind small]
"""

from __future__ import annotations

import argparse
import gc
import json
import subprocess
import sys
import threading
import time
import uuid
from typing import Any

import _harness

MIB = 1024 * 1024

ROWS = {"floor": "Zenoh alone (floor)", "subscriber": "subscribe_events"}


def _line(query_id: str, stamp: int) -> bytes:
    from rr_actors import events  # noqa: PLC0415 - in the row's process only

    event = events.InDoubt("erm", query_id, at=1.0, pid=1, host="x", hlc=stamp << 12)
    return json.dumps(events.to_dict(event)).encode()


class Memory:
    """This process's resident set size (psutil), in MiB: read now, and its peak while
    sampled every 10 ms on a thread of its own."""

    def __init__(self) -> None:
        import psutil  # noqa: PLC0415 - a dev dependency

        self._process = psutil.Process()
        self.peak = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def now(self) -> float:
        gc.collect()
        return float(self._process.memory_info().rss) / MIB

    def _sample(self) -> None:
        while not self._stop.wait(0.01):
            self.peak = max(self.peak, self._process.memory_info().rss / MIB)

    def __enter__(self) -> Memory:
        self.peak = self.now()
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join()


def _sink(net: Any, row: str, handled: dict[str, int], done: threading.Event) -> Any:
    """What takes the flood in row `row`; returns its close."""
    from rr_actors import events  # noqa: PLC0415

    def counted(event: events.Event) -> None:
        if isinstance(event, events.EventsDropped):
            handled["dropped"] += event.count
        elif getattr(event, "query_id", "") == "sentinel":
            done.set()
        else:
            handled["events"] += 1

    def taken(sample: Any) -> None:
        if b"sentinel" in sample.payload.to_bytes()[-200:]:
            done.set()

    if row == "floor":
        return net.services().session.declare_subscriber(f"rr/{net.system}/ev/*", taken).undeclare
    return net.subscribe_events(counted, window=0.5).close


def _row(row: str, batches: int, mib: float, kind: str, settle: float) -> dict[str, Any]:
    """One row, in this process: the flood and the memory it took."""
    import zenoh  # noqa: PLC0415

    import rr_actors as rr  # noqa: PLC0415

    net = rr.ZenohNetwork(system=f"flood-{uuid.uuid4().hex[:8]}", tls=None)
    handled = {"events": 0, "dropped": 0}
    done = threading.Event()
    close = _sink(net, row, handled, done)
    config = zenoh.Config.from_json5(
        '{"mode": "client", "scouting": {"multicast": {"enabled": false}}, '
        f'"connect": {{"endpoints": ["unixsock-stream/{net.address.socket_path}"]}}}}'
    )
    raw = zenoh.open(config)
    publisher = raw.declare_publisher(
        f"rr/{net.system}/ev/{raw.zid()}", congestion_control=zenoh.CongestionControl.BLOCK
    )
    deadline = time.monotonic() + 10
    while not publisher.matching_status.matching and time.monotonic() < deadline:
        time.sleep(0.01)  # (a benchmark's setup: Zenoh's matching status has no wait)
    one = _line("q" * (100 if kind == "small" else MIB), 5)
    count = max(1, int(mib * MIB) // (len(one) + 1))
    batch = b"\n".join([one] * count)
    with Memory() as memory:
        before = memory.peak
        started = time.monotonic()
        for _ in range(batches):
            publisher.put(batch)
        publisher.put(_line("sentinel", 6))
        finished = done.wait(600)
        took = time.monotonic() - started
        after = memory.now()
        time.sleep(settle)  # (what is still held `settle` s later)
        later = memory.now()
    close()
    raw.close()  # type: ignore[no-untyped-call]
    net.close()
    return {
        "row": row,
        "before": before,
        "peak": memory.peak,
        "after": after,
        "later": later,
        "seconds": took,
        "finished": finished,
        "sent": batches * count,
        "batch": len(batch) / MIB,
        **handled,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--batches", type=int, default=40)
    parser.add_argument("--mib", type=float, default=14.3, help="MiB of each batch")
    parser.add_argument("--kind", choices=["small", "big"], default="small")
    parser.add_argument("--settle", type=float, default=5.0, help="seconds before `later`")
    parser.add_argument("--row", choices=sorted(ROWS), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.row:
        print(json.dumps(_row(args.row, args.batches, args.mib, args.kind, args.settle)))
        return
    results = []
    for row in ROWS:
        done = subprocess.run(
            [sys.executable, __file__, *sys.argv[1:], "--row", row],
            capture_output=True,
            text=True,
            check=True,
        )
        results.append(json.loads(done.stdout.strip().splitlines()[-1]))
    floor = results[0]["peak"] - results[0]["before"]
    first = results[0]
    rows = []
    for result in results:
        floor_row = result["row"] == "floor"
        rows.append(
            (
                ROWS[result["row"]],
                *(f"{result[k]:.0f}" for k in ("before", "peak", "after", "later")),
                "-" if floor_row else result["events"], "-" if floor_row else result["dropped"],
                f"{result['seconds']:.1f}",
                f"{result['peak'] - result['before'] - floor:+.0f}"
                + ("" if result["finished"] else " (sentinel never came)"),
            )
        )  # fmt: skip
    _harness.print_table(
        f"{args.batches} batches of {first['batch']:.1f} MiB ({args.kind} events, "
        f"{first['sent']} in all) from one member, then a sentinel; RSS in MiB",
        ("row", "before", "peak", "after", "later", "handled", "dropped", "s", "over floor"),
        rows,
    )


if __name__ == "__main__":
    main()
