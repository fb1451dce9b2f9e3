"""Cost of durable catalogs: per-change cost and restore time vs catalog size, in one run.

For each catalog size N (resources, one consumer each) a backup is built, then:

* store change: one catalog change (add a consumer / release it) written by
  `SqliteStore.write` (one transaction, as with `save_on_modify`), also with the event
  that tells of it in the same transaction (the outbox of a manager process whose events
  someone hears: `ConsumerAdded`, `ConsumerReleased`), next to the same change
  with no store and a raw SQLite commit (one-row INSERT or DELETE in its own transaction,
  same pragmas); and batched: 50 changes per transaction, on a store that checkpoints in
  the background (as with a `save_interval`);
* registrar change: a dedup-hit `call` or its `unload` on a registrar restored from that
  backup, with `save_on_modify=True` vs with nothing written (`save_on_modify=False`,
  no `save_interval`): the difference is what persistence adds to a change;
* restore: `SqliteStore.open` + `load` + `Catalog.restore`, and `ResourceRegistrar.start`
  end to end, next to a raw `SELECT` of every row of the three tables.

`--holders 1,100,1000` measures instead a store write as a resource's holders grow: one
consumer id added to a resource of H holders and released, each change its own
`SqliteStore.write`, beside a raw one-row commit (autocommit, and `BEGIN IMMEDIATE`), the
store's own `INSERT` and `DELETE` run on a bare connection to a copy of the backup, and
the same catalog changes with no store (subtracted from the store's row); by this
thread's CPU clock (what a shared machine does not inflate) and by the wall clock.
`BENCH_DIR` names the directory to write in (default: the system's temporary one).

Per-change rows are measured in interleaved rounds (so noise spreads evenly); the tables
show medians in microseconds. Usage:

    python benchmarks/bench_persistence.py [--sizes 100,10000,100000] [--rounds 15]
        [--batch 100] [--durability process|power] [--holders 1,100,1000]
"""

from __future__ import annotations

import gc
import os
import shutil
import sqlite3
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import _harness

import rr_actors as rr
from rr_actors import events
from rr_actors._catalog import Catalog
from rr_actors._store import SqliteStore, gc_paused
from rr_actors._store.restore import read_backup

Sample = Callable[[], None]
Write = Callable[[int], None]  # the n-th sample of `--holders`: two writes (or two commits)
SYNCHRONOUS = {"process": "NORMAL", "power": "FULL"}
BATCHED = 100  # changes per sample in the batched (save_interval) rows


def build_backup(path: Path, size: int) -> list[str]:
    """A backup with `size` loaded resources of server `leaf`; returns their request keys."""
    store = SqliteStore.open(path)
    store.load()
    catalog = Catalog()
    with gc_paused():
        for n in range(size):
            rid = str(uuid.uuid4())
            catalog.begin_load(rid, "leaf", {"cmd": ["driver", "--id", str(n)]})
            catalog.finish_load(rid, {"pid": 1000 + n})
            catalog.add_consumer(rid, str(uuid.uuid4()), "app")
        store.write(catalog.drain_changes())
    store.close(erase=False)
    return [str(n) for n in range(0, size, max(1, size // 50))]


def opened(path: Path, durability: Any, *, background: bool) -> tuple[SqliteStore, Catalog]:
    """A store on `path` and the catalog it holds (read whole)."""
    store = SqliteStore.open(path, durability=durability, background_checkpoints=background)
    rows = store.load()
    assert rows is not None
    return store, Catalog.restore(*rows)


def read_whole(path: Path) -> Catalog:
    """The catalog in the backup at `path`, read without opening a store on it."""
    on_disk = read_backup(path)
    return Catalog.restore(on_disk.resources, on_disk.clients)


def raw_rows(path: Path, durability: Any) -> tuple[sqlite3.Connection, Sample]:
    """The floor: a bare SQLite commit to a one-row table (same pragmas), and its connection."""
    raw = raw_connection(path, durability)
    raw.execute("CREATE TABLE IF NOT EXISTS t (seq INTEGER PRIMARY KEY, query_id TEXT)")

    def raw_commit() -> None:
        raw.execute("BEGIN IMMEDIATE")
        cursor = raw.execute("INSERT INTO t (query_id) VALUES ('q')")
        raw.execute("COMMIT")
        raw.execute("BEGIN IMMEDIATE")
        raw.execute("DELETE FROM t WHERE seq = ?", (cursor.lastrowid,))
        raw.execute("COMMIT")

    return raw, raw_commit


def store_rows(path: Path, durability: Any) -> tuple[dict[str, Sample], Sample, Sample]:
    """Per-change samples on the store alone, on a restored copy of the catalog.

    Also returns `settle()`, which waits until the batched store's background checkpoint
    (started by a sample) is done, so that it does not slow the sample measured next,
    and `close()`, which closes what the samples opened.
    """
    store, catalog = opened(path, durability, background=False)  # as with save_on_modify
    # changes go to resources spread over the whole catalog (rows all over the file)
    rids = list(catalog.resources)
    plain = read_whole(path)  # (the same catalog: no second store, one store a file)
    # the batched rows write a copy, opened as with a save_interval (background checkpoints)
    copy = path.with_name(f"{path.stem}-batched.db")
    copy.write_bytes(path.read_bytes())
    batch_store, batch_catalog = opened(copy, durability, background=True)
    ids = iter(range(10**9))

    def persisted() -> None:
        n = next(ids)
        qid = f"q{n}"
        catalog.add_consumer(rids[n * 7919 % len(rids)], qid, "app")
        store.write(catalog.drain_changes())
        catalog.release(qid)
        store.write(catalog.drain_changes())

    def persisted_told() -> None:  # the same, each change with its event (the outbox)
        n = next(ids)
        qid = f"q{n}"
        rid = rids[n * 7919 % len(rids)]
        catalog.add_consumer(rid, qid, "app")
        store.write(catalog.drain_changes(), (events.ConsumerAdded("b", rid, qid, "app", seq=n),))
        catalog.release(qid)
        store.write(
            catalog.drain_changes(), (events.ConsumerReleased("b", rid, qid, "app", seq=n),)
        )

    def memory_only() -> None:
        n = next(ids)
        qid = f"q{n}"
        plain.add_consumer(rids[n * 7919 % len(rids)], qid, "app")
        plain.drain_changes()
        plain.release(qid)
        plain.drain_changes()

    def persisted_batch() -> None:  # a save_interval flush: many changes, one transaction
        qids = [f"q{next(ids)}" for _ in range(BATCHED // 2)]
        for n, qid in enumerate(qids):
            batch_catalog.add_consumer(rids[(hash(qid) + n) % len(rids)], qid, "app")
        batch_store.write(batch_catalog.drain_changes())
        for qid in qids:
            batch_catalog.release(qid)
        batch_store.write(batch_catalog.drain_changes())

    def memory_only_batch() -> None:
        qids = [f"q{next(ids)}" for _ in range(BATCHED // 2)]
        for n, qid in enumerate(qids):
            plain.add_consumer(rids[(hash(qid) + n) % len(rids)], qid, "app")
        plain.drain_changes()
        for qid in qids:
            plain.release(qid)
        plain.drain_changes()

    raw, raw_commit = raw_rows(path.with_suffix(".raw"), durability)

    def settle() -> None:
        if batch_store._checkpointer is not None:
            batch_store._checkpointer.wait_idle(30.0)

    def close() -> None:
        store.close(erase=False)
        batch_store.close(erase=False)
        raw.close()

    return (
        {
            "store write (2 changes)": persisted,
            "store write + their events, outbox (2 changes)": persisted_told,
            "no store (2 changes)": memory_only,
            "raw SQLite (2 commits)": raw_commit,
            f"store write, batched ({BATCHED} changes, 2 commits)": persisted_batch,
            f"no store ({BATCHED} changes)": memory_only_batch,
        },
        settle,
        close,
    )


def registrar_rows(path: Path, durability: Any, keys: list[str]) -> tuple[dict[str, Sample], Any]:
    """Dedup-hit call + unload on registrars restored from `path`, durable and not."""
    registrars = []
    samples = {}
    for label, durable in (("registrar, save_on_modify", True), ("registrar, no writes", False)):
        copy = path.with_name(f"{path.stem}-{int(durable)}.db")
        copy.write_bytes(path.read_bytes())
        registrar = rr.ResourceRegistrar.start(
            rr.RegistrarConfig(
                name=f"bench-{uuid.uuid4().hex[:8]}",
                backup_path=copy,
                save_on_modify=durable,
                save_interval=None,
                durability=durability,
            )
        )
        registrar.register_server("leaf", load=lambda r: r, unload=lambda r, s: None)
        registrars.append(registrar)
        request = {"cmd": ["driver", "--id", keys[len(keys) // 2]]}

        def call_unload(
            registrar: rr.ResourceRegistrar = registrar, request: Any = request
        ) -> None:
            query = registrar.call(registrar.name, "leaf", request)
            registrar.unload(query.id)

        samples[f"{label} (call+unload, 4 changes)"] = call_unload
    return samples, registrars


def restore_rows(path: Path, rounds: int) -> dict[str, float]:
    """Median milliseconds to restore `path`, three ways."""

    def store_load() -> None:
        store = SqliteStore.open(path)
        rows = store.load()
        assert rows is not None
        with gc_paused():
            Catalog.restore(*rows)
        store.close(erase=False)

    def store_restore() -> None:
        store = SqliteStore.open(path)
        restored = store.restore()
        assert restored is not None
        with gc_paused():
            Catalog.restore(restored.resources, restored.clients, restored.unread)
        store.close(erase=False)

    def registrar_start() -> None:
        registrar = rr.ResourceRegistrar.start(
            rr.RegistrarConfig(name=f"restore-{uuid.uuid4().hex[:8]}", backup_path=path)
        )
        registrar.stop()

    def raw_select() -> None:
        db = sqlite3.connect(path)
        for table in ("resources", "consumers", "clients"):
            db.execute(f"SELECT * FROM {table} ORDER BY seq").fetchall()  # noqa: S608 - fixed names
        db.close()

    runs = {
        "raw SELECT *": raw_select,
        "store restore (what start does)": store_restore,
        "store load (every row) + restore": store_load,
        "ResourceRegistrar.start+stop": registrar_start,
    }

    def once(run: Callable[[], None]) -> float:
        gc.collect()
        return _harness.per_op(run, 1) * 1000

    results = _harness.alternate(
        {label: (lambda run=run: once(run)) for label, run in runs.items()}, rounds, warm_up=False
    )
    return {label: _harness.median(values) for label, values in results.items()}


# -- by holders (`--holders`) --------------------------------------------------------------


def raw_connection(path: Path, durability: str) -> sqlite3.Connection:
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("PRAGMA journal_mode = WAL")
    db.execute(f"PRAGMA synchronous = {SYNCHRONOUS[durability]}")
    return db


def holder_samples(directory: Path, holders: int, durability: Any) -> tuple[dict[str, Write], Any]:
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


def holder_measure(
    made: dict[str, Write], rounds: int, batch: int
) -> dict[str, tuple[float, float]]:
    """Each sample's (CPU, wall) microseconds a write, medians of `rounds` alternated
    batches of `batch` samples (two writes each)."""
    n = iter(range(1, 1 << 62))

    def row(sample: Write) -> list[float]:
        cpu = time.thread_time()
        wall = _harness.per_op(lambda: sample(next(n)), batch) / 2 * 1e6
        return [(time.thread_time() - cpu) / batch / 2 * 1e6, wall]

    got = _harness.alternate(
        {k: (lambda s=s: row(s)) for k, s in made.items()}, rounds, warm_up=False
    )
    return {k: (_harness.median(v[0::2]), _harness.median(v[1::2])) for k, v in got.items()}


def by_holders(args: Any) -> None:
    """`--holders`: the store write by holder count, against a raw one-row commit."""
    counts = [1, 10] if args.quick else [int(h) for h in args.holders.split(",")]
    print(_harness.header(f"SQLite {sqlite3.sqlite_version}, durability={args.durability}"))
    table: dict[str, dict[int, tuple[float, float]]] = {}
    with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_DIR")) as name:
        for holders in counts:
            made, close = holder_samples(Path(name), holders, args.durability)
            gc.collect()
            try:
                for label, figures in holder_measure(made, args.rounds, args.batch).items():
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


def by_sizes(args: Any) -> None:
    """Per change and restore by catalog size (the default)."""
    sizes = [100] if args.quick else [int(s) for s in args.sizes.split(",")]
    print(_harness.header(f"SQLite {sqlite3.sqlite_version}, durability={args.durability}"))
    change_table: dict[str, dict[int, float]] = {}
    restore_table: dict[str, dict[int, float]] = {}
    with tempfile.TemporaryDirectory() as directory:
        for size in sizes:
            path = Path(directory) / f"catalog-{size}.db"
            built = time.perf_counter()
            keys = build_backup(path, size)
            print(
                f"built a backup of {size} resources in {time.perf_counter() - built:.1f} s "
                f"({path.stat().st_size / 1e6:.1f} MB)",
                file=sys.stderr,
            )
            samples, settle, close = store_rows(path, args.durability)
            more, registrars = registrar_rows(path, args.durability, keys)
            samples.update(more)
            os.sync()  # the copies just written must not be written back while we measure
            gc.collect()
            gc.freeze()  # the catalogs built for the run are not rescanned by every collection

            def row(sample: Sample, settle: Sample = settle) -> float:  # us per call
                took = _harness.per_op(sample, args.batch) * 1e6
                settle()  # a row's background work must not slow the next row
                return took

            try:
                measured = _harness.alternate(
                    {label: (lambda s=s: row(s)) for label, s in samples.items()},
                    args.rounds,
                    warm_up=False,
                )
            finally:
                for registrar in registrars:
                    registrar.stop()
                close()
            for label, values in measured.items():
                change_table.setdefault(label, {})[size] = _harness.median(values)
            for label, ms in restore_rows(path, max(3, args.rounds // 5)).items():
                restore_table.setdefault(label, {})[size] = ms

    head = "".join(f"{f'N={s}':>12}" for s in sizes)
    print(f"\nper operation, median us{'':<28}{head}{'100k/100':>10}")
    for label, row in change_table.items():
        ratio = row[sizes[-1]] / row[sizes[0]]
        print(f"{label:<52}{''.join(f'{row[s]:12.1f}' for s in sizes)}{ratio:10.2f}")
    store_cost = {
        s: change_table["store write (2 changes)"][s] - change_table["no store (2 changes)"][s]
        for s in sizes
    }
    registrar_cost = {
        s: change_table["registrar, save_on_modify (call+unload, 4 changes)"][s]
        - change_table["registrar, no writes (call+unload, 4 changes)"][s]
        for s in sizes
    }
    print(f"{'=> store cost per change':<52}{''.join(f'{store_cost[s] / 2:12.1f}' for s in sizes)}")
    outbox = {
        s: change_table["store write + their events, outbox (2 changes)"][s]
        - change_table["store write (2 changes)"][s]
        for s in sizes
    }
    per_change = "".join(f"{outbox[s] / 2:12.1f}" for s in sizes)
    print(f"{'=> its event in the outbox, per change':<52}{per_change}")
    batched = {
        s: change_table[f"store write, batched ({BATCHED} changes, 2 commits)"][s]
        - change_table[f"no store ({BATCHED} changes)"][s]
        for s in sizes
    }
    print(
        f"{'=> store cost per change, batched (save_interval)':<52}"
        f"{''.join(f'{batched[s] / BATCHED:12.1f}' for s in sizes)}"
    )
    raw_row = change_table["raw SQLite (2 commits)"]
    print(f"{'=> raw SQLite commit':<52}{''.join(f'{raw_row[s] / 2:12.1f}' for s in sizes)}")
    print(
        f"{'=> registrar: persistence per change':<52}"
        f"{''.join(f'{registrar_cost[s] / 4:12.1f}' for s in sizes)}"
    )
    print(f"\nrestore, median ms{'':<34}{head}")
    for label, row in restore_table.items():
        print(f"{label:<52}{''.join(f'{row[s]:12.1f}' for s in sizes)}")


def main() -> None:
    parser = _harness.options(__doc__, rounds=15, batch=100)
    parser.add_argument("--sizes", default="100,10000,100000")
    parser.add_argument("--durability", default="process", choices=["process", "power"])
    parser.add_argument("--holders", help="H,...: a store write by holders instead")
    args = _harness.parse(parser, None)
    if args.holders:
        by_holders(args)
    else:
        by_sizes(args)


if __name__ == "__main__":
    main()
