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
import struct
from typing import Any

from bench_transport import paired_rows, paired_with_floors

_LENGTH = struct.Struct("!i")


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
    ours, theirs = socket.socketpair()
    provider = ctx.Process(target=_provider, args=(theirs,), daemon=True)
    provider.start()
    theirs.close()
    records: dict[str, Any] = {}

    def hit() -> None:
        query = pickle.dumps((os.urandom(16).hex(), "echo", {"cam": 1}, "main"), 5)
        ours.sendall(_LENGTH.pack(len(query)) + query)
        query_id, response = pickle.loads(_frame(ours.fileno()))
        records[query_id] = response

    try:
        medians = paired_with_floors(ctx, hit, args.rounds)
    finally:
        ours.close()
        provider.join(10)
    paired_rows(medians, "minimal Python dedup hit across processes, paired")


if __name__ == "__main__":
    main()
