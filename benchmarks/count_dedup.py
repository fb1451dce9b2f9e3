"""A fixed number of in-process dedup-hit calls, to count their instructions under callgrind.

Wall-clock timings on a shared machine are noise; instruction counts are not. Run this
twice under `valgrind --tool=callgrind` with two numbers of calls; the difference of the
two totals over the difference of the calls is the instructions one operation costs, on
every thread (the caller, the provider's actor, the consumer's actor):

    for n in 100 1100; do PYTHONHASHSEED=0 valgrind --tool=callgrind \\
        --callgrind-out-file=/tmp/cg.$n python benchmarks/count_dedup.py --calls $n; done
    # then (totals of /tmp/cg.1100 - totals of /tmp/cg.100) / 1000, from their "summary:" line

Operations (`--what`): `call`, a dedup-hit call with a plain request (a string);
`user`, the same with a request of a user class (its `repr`, `==` and `hash` are user
code); `pykka`, a raw pykka ask to an echoing actor (the baseline); `actor`, the
same ask to rr_actors' own actor type. With `--profile`
it prints each Python function called at least once per operation, with the thread
that called it (a cheap way to see what an operation does).

Usage:
    python benchmarks/count_dedup.py [--calls 1000] [--what call|user|pykka] [--profile]
"""

from __future__ import annotations

import argparse
import collections
import os
import resource
import sys
import threading
from types import FrameType
from typing import Any

import pykka

import rr_actors as rr
from rr_actors._core.actor import Actor


class Echo(pykka.ThreadingActor):
    def on_receive(self, message: Any) -> Any:
        return message


class ActorEcho(Actor):
    """The same echo on rr_actors' own actor type (the registrars are built on it)."""

    def on_receive(self, message: Any) -> Any:
        return message


class Camera:
    """A request of a user class."""

    def __init__(self, index: int) -> None:
        self.index = index

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Camera) and other.index == self.index

    def __hash__(self) -> int:
        return hash(self.index)

    def __repr__(self) -> str:
        return f"Camera({self.index})"


def _noop(*_: object) -> None:
    return None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=1000, help="operations (default 1000)")
    parser.add_argument("--what", choices=["call", "user", "pykka", "actor"], default="call")
    parser.add_argument("--profile", action="store_true", help="print Python calls per op")
    args = parser.parse_args()
    counts: collections.Counter[tuple[str, str, str]] = collections.Counter()
    counting = threading.Event()

    def tracer(frame: FrameType, event: str, _: Any) -> None:
        if event == "call" and counting.is_set():
            code = frame.f_code
            where = f"{os.path.basename(code.co_filename)}:{code.co_firstlineno}"
            counts[(threading.current_thread().name[:16], where, code.co_name)] += 1

    if args.profile:  # (before the actors start: their threads inherit it)
        threading.setprofile(tracer)
        sys.setprofile(tracer)
    echo = Echo.start() if args.what != "actor" else ActorEcho.start()
    provider = rr.ResourceRegistrar.start("count-provider")
    consumer = rr.ResourceRegistrar.start("count-consumer")
    try:
        provider.register_server("res", load=lambda request: request, unload=_noop)
        request: Any = Camera(1) if args.what == "user" else "shared"
        consumer.call(provider.name, "res", request)  # loaded: every call after is a hit
        for query_id in [consumer.call(provider.name, "res", request).id for _ in range(50)]:
            consumer.unload(query_id)  # (warm-up)
        ids: list[str] = []
        counting.set()
        before = resource.getrusage(resource.RUSAGE_SELF)
        for _ in range(args.calls):
            if args.what in ("pykka", "actor"):
                echo.ask("ping")
            else:
                ids.append(consumer.call(provider.name, "res", request).id)
        consumer.client_queries()  # (after the consumer recorded every answer)
        after = resource.getrusage(resource.RUSAGE_SELF)
        counting.clear()
        for query_id in ids:
            consumer.unload(query_id)
    finally:
        sys.setprofile(None)
        threading.setprofile(None)  # type: ignore[arg-type]
        consumer.stop()
        provider.stop()
        echo.stop()
    print(f"{args.calls} x {args.what}")
    cpu = (after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime) * 1e6
    switches = after.ru_nvcsw + after.ru_nivcsw - before.ru_nvcsw - before.ru_nivcsw
    print(
        f"per operation: {cpu / args.calls:.1f} us of CPU (every thread), "
        f"{switches / args.calls:.2f} context switches"
    )
    for (thread, where, name), count in sorted(counts.items(), key=lambda kv: -kv[1]):
        if count >= args.calls:
            print(f"{count / args.calls:5.1f}  {thread:16} {where:20} {name}")
    if counts:
        print(f"Python calls per operation: {sum(counts.values()) / args.calls:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
