"""What writing a change's events in its transaction (the outbox) costs a durable manager.

A supervisor runs one manager process with a backup (`state_dir`: `save_on_modify`); a
consumer in the supervisor's process loads new resources back to back: `call` with a
new request, then `unload` (a load, a consumer added, released, and an unload: four
commits, three of them with their events in the outbox while someone listens). Two
settings, in alternating rounds so that noise from other programs spreads over both:

* listened: a subscription on the supervisor, so the manager builds, journals and
  forwards its events, and writes those of its commits in its backup's outbox;
* nobody listens: the manager builds no event (nor writes any in its outbox): the floor.

The table (Markdown) shows loads per second and the CPU time the manager process spent
per load (all its threads, from `/proc/<pid>/task/*/schedstat`: steadier than wall time
on a loaded machine), medians of the rounds, and the listened/floor CPU ratio; for the
before, run it against a tree without the outbox with `alternate.py` (a copy of this
script in that tree's `benchmarks/`).

    python benchmarks/bench_outbox.py                  # about a minute
    python benchmarks/bench_outbox.py --rounds 3 --loads 100
"""

from __future__ import annotations

import contextlib
import itertools
import sqlite3
import tempfile
import time
from pathlib import Path
from typing import Any

import _harness

import rr_actors as rr


def setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("dev", load=lambda r: r, unload=lambda _r, _s: None)


def cpu_ns(pid: int) -> int:
    """CPU time of every thread of process `pid` so far (ns; Linux schedstat)."""
    total = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError, ValueError, IndexError):  # a thread just ended
            total += int((task / "schedstat").read_text().split()[0])
    return total


def measured(app: rr.ResourceRegistrar, pid: int, n: int, requests: Any) -> tuple[float, float]:
    """Loads per second, and the manager's CPU microseconds per load, over `n` loads."""
    cpu, start = cpu_ns(pid), time.perf_counter()
    for _ in range(n):
        query = app.call("erm", "dev", {"device": next(requests)})
        app.unload(query.id)
    wall = time.perf_counter() - start
    return n / wall, (cpu_ns(pid) - cpu) / 1000 / n


def main(argv: list[str] | None = None) -> None:
    parser = _harness.options(__doc__, rounds=7)
    parser.add_argument("--loads", type=int, default=300, help="loads per round and setting")
    args = _harness.parse(parser, argv)
    if args.quick:
        args.loads = _harness.QUICK_BATCH
    print(
        _harness.header(
            f"SQLite {sqlite3.sqlite_version}, rr_actors from {Path(rr.__file__).parent}"
        )
    )
    heard = itertools.count()
    requests = itertools.count()
    rows: dict[str, list[tuple[float, float]]] = {
        "listened (events, outbox)": [],
        "nobody listens": [],
    }
    with tempfile.TemporaryDirectory() as state:
        erm = rr.ManagerSpec("erm", setup, isolation="process", heartbeat=None)  # (loaded CPUs)
        sup = rr.Supervisor([erm], state_dir=state)
        with sup:
            app = sup.registrar("app")
            pid = sup.child("erm").pid
            assert pid is not None
            measured(app, pid, 50, requests)  # (warm: the client, the caches)
            for _ in range(args.rounds):
                with sup.subscribe(lambda _e: next(heard)) as subscription:
                    rows["listened (events, outbox)"].append(
                        measured(app, pid, args.loads, requests)
                    )
                    subscription.wait_delivered(timeout=30)
                rows["nobody listens"].append(measured(app, pid, args.loads, requests))
    listened, floor = rows.values()
    cpu_ratio = _harness.median(a[1] / b[1] for a, b in zip(listened, floor, strict=True))
    table = []
    for label, values, ratio in (
        ("listened (events, outbox)", listened, cpu_ratio),
        ("nobody listens (the floor)", floor, 1.0),
    ):
        rate = _harness.median(v[0] for v in values)
        cpu = _harness.median(v[1] for v in values)
        table.append((label, f"{rate:.0f}", f"{cpu:.0f}", f"{ratio:.3f}x"))
    columns = ["durable manager process, call+unload of a new resource", "loads/s"]
    print("\n" + _harness.table([*columns, "manager CPU us/load", "CPU vs nobody listens"], table))
    print(f"\n(the ratio: median of the rounds' ratios; {next(heard)} events heard)")


if __name__ == "__main__":
    main()
