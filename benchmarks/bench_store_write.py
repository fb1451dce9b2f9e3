"""A store write against a raw one-row SQLite commit, as a resource's holders grow (issue 52).

For each holder count H a backup holds one resource with H consumers; a sample adds one
consumer id to it and releases it again, each change written by `SqliteStore.write` (one
transaction each, as with `save_on_modify`). Beside it, in
the same rounds and the same directory (so the same file system):

* raw one-row commit: a bare SQLite connection (same pragmas: WAL, `synchronous`)
  inserting one row into a one-row table and deleting it, each statement its own
  transaction: the floor of a commit;
* the same, as `BEGIN IMMEDIATE` / statement / `COMMIT` (the form of
  `bench_persistence.py`'s raw rows);
* the store's own statements, raw: the `INSERT` and `DELETE` a write makes, run on a
  bare connection to a copy of the backup (what the SQL itself costs: the consumers
  table has two indexes).

Samples are measured in interleaved rounds (so noise spreads evenly), a batch of them
at a time, by this thread's CPU clock (what a machine shared with other work does not
inflate: the time the process waits for a CPU is not in it, nor for an fsync) and by the
wall clock. The tables show medians of the batches in microseconds a write, and each
row's ratio to the raw one-row commit. The store's row is less the same catalog changes
made without a store (measured beside it). Checkpoints (once every thousand or so log
pages) are in the batches, as they are in a registrar's writes. Pin it to one CPU for
stable ratios (`taskset -c 0`); `BENCH_DIR` names the directory to write in (default:
the system's temporary directory). Usage:

    python benchmarks/bench_store_write.py [--holders 1,100,1000] [--rounds 15]
        [--batch 500] [--durability process|power]
"""

from __future__ import annotations

import gc
import os
import shutil
import sqlite3
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import _harness

from rr_actors._catalog import Catalog
from rr_actors._store import SqliteStore

Sample = Callable[[int], None]  # the n-th sample: two writes (or two commits)
SYNCHRONOUS = {"process": "NORMAL", "power": "FULL"}


def raw_connection(path: Path, durability: str) -> sqlite3.Connection:
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("PRAGMA journal_mode = WAL")
    db.execute(f"PRAGMA synchronous = {SYNCHRONOUS[durability]}")
    return db


def samples(directory: Path, holders: int, durability: Any) -> tuple[dict[str, Sample], Any]:
    """The samples at `holders`, and a function that closes what they opened."""
    path = directory / f"store-{holders}.db"
    store = SqliteStore.open(path, durability=durability)
    store.load()
    catalog = Catalog()
    catalog.begin_load("r", "leaf", {"cmd": ["driver", "--id", "1"]})
    catalog.finish_load("r", {"pid": 1000})
    for n in range(holders):
        catalog.add_consumer("r", f"holder-{n}", "app")
    store.write(catalog.drain_changes())
    (row,) = store._db.execute("SELECT seq FROM resources WHERE id = 'r'").fetchone()
    plain = Catalog()  # the same catalog changes, written nowhere (subtracted)
    plain.begin_load("r", "leaf", {"cmd": ["driver", "--id", "1"]})
    plain.finish_load("r", {"pid": 1000})
    for n in range(holders):
        plain.add_consumer("r", f"holder-{n}", "app")

    def store_write(n: int) -> None:
        qid = f"q{n}"
        catalog.add_consumer("r", qid, "app")
        store.write(catalog.drain_changes())
        catalog.release(qid)
        store.write(catalog.drain_changes())

    def no_store(n: int) -> None:
        qid = f"q{n}"
        plain.add_consumer("r", qid, "app")
        plain.drain_changes()
        plain.release(qid)
        plain.drain_changes()

    raw = raw_connection(directory / f"raw-{holders}.db", durability)
    raw.execute("CREATE TABLE t (seq INTEGER PRIMARY KEY, query_id TEXT)")

    def raw_commit(n: int) -> None:
        cursor = raw.execute("INSERT INTO t (query_id) VALUES (?)", (f"q{n}",))
        raw.execute("DELETE FROM t WHERE seq = ?", (cursor.lastrowid,))

    def raw_begin_commit(n: int) -> None:
        raw.execute("BEGIN IMMEDIATE")
        cursor = raw.execute("INSERT INTO t (query_id) VALUES (?)", (f"q{n}",))
        raw.execute("COMMIT")
        raw.execute("BEGIN IMMEDIATE")
        raw.execute("DELETE FROM t WHERE seq = ?", (cursor.lastrowid,))
        raw.execute("COMMIT")

    copy = directory / f"copy-{holders}.db"
    shutil.copyfile(path, copy)
    same = raw_connection(copy, durability)

    def store_statements(n: int) -> None:
        key = 10**9 + n
        same.execute(
            "INSERT INTO consumers (resource, seq, query_id, origin_rr) VALUES (?, ?, ?, ?)",
            (row, key, f"q{n}", "app"),
        )
        same.execute("DELETE FROM consumers WHERE resource = ? AND seq = ?", (row, key))

    def close() -> None:
        store.close(erase=True)
        raw.close()
        same.close()

    return (
        {
            "store write": store_write,
            "no store (the catalog changes alone)": no_store,
            "raw one-row commit": raw_commit,
            "raw one-row commit, BEGIN/COMMIT": raw_begin_commit,
            "the store's statements, raw": store_statements,
        },
        close,
    )


def measure(made: dict[str, Sample], rounds: int, batch: int) -> dict[str, tuple[float, float]]:
    """Each sample's (CPU, wall) microseconds a write, medians of `rounds` alternated
    batches of `batch` samples (two writes each)."""
    n = iter(range(1, 1 << 62))

    def row(sample: Sample) -> list[float]:
        cpu = time.thread_time()
        wall = _harness.per_op(lambda: sample(next(n)), batch) / 2 * 1e6
        return [(time.thread_time() - cpu) / batch / 2 * 1e6, wall]

    got = _harness.alternate(
        {k: (lambda s=s: row(s)) for k, s in made.items()}, rounds, warm_up=False
    )
    return {k: (_harness.median(v[0::2]), _harness.median(v[1::2])) for k, v in got.items()}


def main() -> None:
    parser = _harness.options(__doc__, rounds=15, batch=500)
    parser.add_argument("--holders", default="1,100,1000")
    parser.add_argument("--durability", default="process", choices=["process", "power"])
    args = _harness.parse(parser, None)
    counts = [1, 10] if args.quick else [int(h) for h in args.holders.split(",")]
    print(_harness.header(f"SQLite {sqlite3.sqlite_version}, durability={args.durability}"))
    table: dict[str, dict[int, tuple[float, float]]] = {}
    with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_DIR")) as name:
        for holders in counts:
            made, close = samples(Path(name), holders, args.durability)
            gc.collect()
            try:
                for label, figures in measure(made, args.rounds, args.batch).items():
                    table.setdefault(label, {})[holders] = figures
            finally:
                close()
    catalog_only = table.pop("no store (the catalog changes alone)")
    table["store write"] = {
        h: (cpu - catalog_only[h][0], wall - catalog_only[h][1])
        for h, (cpu, wall) in table["store write"].items()
    }
    floor = table["raw one-row commit"]
    for kind, at in (("CPU", 0), ("wall", 1)):
        head = "".join(f" {f'H={h}':>6} |" for h in counts)
        print(f"\n| per write, {kind} us (median) |{head}{head.replace('H=', 'x H=')}")
        print(f"|---|{'---:|' * (2 * len(counts))}")
        for label, row in table.items():
            cells = "".join(f" {row[h][at]:6.1f} |" for h in counts)
            against = "".join(f" {row[h][at] / floor[h][at]:5.2f}x |" for h in counts)
            print(f"| {label} |{cells}{against}")
    print(
        "\n(store write: less the catalog changes alone, "
        f"{', '.join(f'{catalog_only[h][0]:.1f}' for h in counts)} us CPU; "
        f"load {os.getloadavg()[0]:.1f} at the end)"
    )


if __name__ == "__main__":
    main()
