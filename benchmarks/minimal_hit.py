"""The least a cross-process dedup hit can cost in Python, beside the Pipe floors.

A yardstick for `bench_transport.py`'s cross-process dedup hit (issue 34 item 5): what
the same exchange costs with nothing of rr_actors around it. The caller pickles
`(query id, server, request, origin)` and writes it on a socket; the provider, one
thread in a process of its own, reads it, unpickles it, finds the resource by a digest
of the request (BLAKE2b of its pickled items), adds the consumer id to a set, pickles
the answer and writes it back; the caller reads it, unpickles it and records the answer
in a dict. No actors, futures, timeouts, deaths, events, texts or catalogs: not a design,
a lower bound. Measured paired with a raw `multiprocessing.Pipe` round trip of bytes and
one of objects (rounds of each in turn, their order alternating), as `bench_transport.py
--only paired` measures the real call, so the ratios of the two scripts compare.

Run: `taskset -c 0 python benchmarks/minimal_hit.py [--rounds 20]`.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import multiprocessing
import multiprocessing.connection
import os
import pickle
import socket
import statistics
import struct
from typing import Any

from bench_transport import _echo, timed

_LENGTH = struct.Struct("!i")
BATCH = 100
"""Timed round trips of each kind in one round."""


def _frame(fd: int) -> bytes:
    """One frame from `fd` (a small one: one read for its header, one for its body)."""
    header = os.read(fd, _LENGTH.size)
    if not header:
        raise EOFError
    (size,) = _LENGTH.unpack(header)
    return os.read(fd, size)


def _provider(sock: socket.socket) -> None:
    """Serve dedup hits on `sock` until it closes: look up, add the consumer, answer."""
    served: dict[tuple[str, bytes], tuple[Any, set[str]]] = {}
    with contextlib.suppress(EOFError, OSError):
        while True:
            query_id, server, request, _origin = pickle.loads(_frame(sock.fileno()))
            items = pickle.dumps(sorted(request.items()))
            key = (server, hashlib.blake2b(items, digest_size=8).digest())
            entry = served.get(key)
            if entry is None:
                entry = served[key] = ({"resource": request}, set())
            entry[1].add(query_id)
            answer = pickle.dumps((query_id, entry[0]), pickle.HIGHEST_PROTOCOL)
            sock.sendall(_LENGTH.pack(len(answer)) + answer)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=20, help="rounds of each kind in turn")
    args = parser.parse_args()
    ctx = multiprocessing.get_context("forkserver")
    children, pipes = [], []
    for objects in (False, True):
        parent, far = ctx.Pipe()
        children.append(ctx.Process(target=_echo, args=(far, objects), daemon=True))
        children[-1].start()
        far.close()
        pipes.append(parent)
    ours, theirs = socket.socketpair()
    children.append(ctx.Process(target=_provider, args=(theirs,), daemon=True))
    children[-1].start()
    theirs.close()
    records: dict[str, Any] = {}
    payload, message = b"x" * 200, ("0f3b7b2c-1111-2222-3333-444455556666", "echo", {"cam": 1})

    def raw_bytes() -> None:
        pipes[0].send_bytes(payload)
        pipes[0].recv_bytes()

    def raw_objects() -> None:
        pipes[1].send(message)
        pipes[1].recv()

    def hit() -> None:
        query = pickle.dumps((os.urandom(16).hex(), "echo", {"cam": 1}, "main"), 5)
        ours.sendall(_LENGTH.pack(len(query)) + query)
        query_id, response = pickle.loads(_frame(ours.fileno()))
        records[query_id] = response

    kinds = [("bytes", raw_bytes), ("objects", raw_objects), ("hit", hit)]
    medians: dict[str, list[float]] = {name: [] for name, _ in kinds}
    try:
        for number in range(args.rounds):
            for name, fn in kinds if number % 2 == 0 else kinds[::-1]:
                medians[name].append(statistics.median(timed(fn, BATCH, warmup=10)))
    finally:
        for pipe in pipes:
            pipe.close()
        ours.close()
        for child in children:
            child.join(10)
    ratios = {
        floor: statistics.median(h / f for h, f in zip(medians["hit"], medians[floor], strict=True))
        for floor in ("bytes", "objects")
    }
    print(f"{args.rounds} rounds of {BATCH} round trips of each kind, in turn")
    print()
    print("| measurement | median us | ratio to bytes | ratio to objects |")
    print("|---|---:|---:|---:|")
    floor_bytes, floor_objects = (statistics.median(medians[k]) * 1e6 for k in ("bytes", "objects"))
    hit_us = statistics.median(medians["hit"]) * 1e6
    print(f"| raw Pipe round trip, send_bytes | {floor_bytes:.1f} | 1.00x | |")
    print(f"| raw Pipe round trip, send/recv objects | {floor_objects:.1f} | | 1.00x |")
    print(
        f"| minimal Python dedup hit across processes | {hit_us:.1f} | "
        f"{ratios['bytes']:.2f}x | {ratios['objects']:.2f}x |"
    )


if __name__ == "__main__":
    main()
