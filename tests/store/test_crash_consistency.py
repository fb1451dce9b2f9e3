"""Crash consistency: SIGKILL a provider and a consumer at random moments, check the backups.

A child process (forkserver context) runs a provider registrar `P` and a consumer `C`, both
with `save_on_modify=True`, and drives random loads, duplicate loads, nested loads and
unloads, reporting every acknowledged operation to the parent over a pipe. The parent
kills it after a random number of reports, then opens both backups afresh and checks:

* each catalog's invariants (`Catalog.check_invariants`);
* every acknowledged load whose unload was not started is in both catalogs;
* every acknowledged unload is in neither.

The next child restarts on the same backups (so restore, in-doubt settling and unloads of
ids issued before a crash are exercised too). The child's stores checkpoint their WAL
on a background thread every few statements, so kills also land in checkpoints (each
report carries how many had finished, and the test checks that they ran).
`run_kills` is shared with `benchmarks/stress_crash.py`, which runs 1,000 kills.
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import multiprocessing.context
import multiprocessing.forkserver
import os
import random
import signal
import uuid
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._catalog import Catalog
from rr_actors._store import checkpoints as checkpoint_module
from rr_actors._store.sqlite import SqliteStore
from rr_actors.testing import catalog_snapshot
from tests.support.durable_pair import pair_backups, start_pair

LEAVES = 8
NESTED = 4
MAX_HELD = 24

# -- the child -------------------------------------------------------------------------------


def worker(names: tuple[str, str], paths: tuple[str, str], seed: int, conn: Any) -> None:
    """Run P and C on the backups and drive random operations until killed."""
    rng = random.Random(seed)  # noqa: S311 - a reproducible workload, not crypto
    # background checkpoints (as with a save_interval) run, and are killed, often
    checkpoint_module.CHECKPOINT_EVERY = 4
    real_open = SqliteStore.open

    def open_in_background(path: Any, **options: Any) -> SqliteStore:
        return real_open(path, **{**options, "background_checkpoints": True})

    SqliteStore.open = open_in_background  # type: ignore[method-assign,assignment]
    checkpoints = 0  # finished in this run; sent with every report, so the parent sees them
    real_checkpoint = checkpoint_module.Checkpointer._checkpoint

    def counted(self: checkpoint_module.Checkpointer, db: Any) -> None:
        nonlocal checkpoints
        before = self.checkpoints
        real_checkpoint(self, db)
        checkpoints += self.checkpoints - before  # a failed one does not count

    checkpoint_module.Checkpointer._checkpoint = counted  # type: ignore[method-assign]
    p_name, _ = names
    _, consumer = start_pair(names, paths)
    held = [c.query.id for c in catalog_snapshot(consumer).clients if c.parent is None and c.loaded]
    while True:
        if held and (len(held) >= MAX_HELD or rng.random() < 0.45):
            query_id = held.pop(rng.randrange(len(held)))
            conn.send(("unload-start", query_id, checkpoints))
            with contextlib.suppress(rr.UnknownQueryError):  # released while a run died
                consumer.unload(query_id)
            conn.send(("unload", query_id, checkpoints))
        elif rng.random() < 0.3:
            query = consumer.call(p_name, "nested", rng.randrange(NESTED))
            held.append(query.id)
            conn.send(("load", query.id, checkpoints))
        else:
            query = consumer.call(p_name, "leaf", {"n": rng.randrange(LEAVES)})
            held.append(query.id)
            conn.send(("load", query.id, checkpoints))


# -- the parent ------------------------------------------------------------------------------


@dataclasses.dataclass
class Model:
    """What the child acknowledged, over all its runs."""

    loaded: set[str] = dataclasses.field(default_factory=set)
    unload_started: set[str] = dataclasses.field(default_factory=set)
    unloaded: set[str] = dataclasses.field(default_factory=set)
    checkpoints: int = 0
    """Background checkpoints the runs reported as finished before their last report."""
    _in_run: int = 0

    def record(self, event: str, query_id: str, checkpoints: int) -> None:
        {"load": self.loaded, "unload-start": self.unload_started, "unload": self.unloaded}[
            event
        ].add(query_id)
        self._in_run = max(self._in_run, checkpoints)

    def end_run(self) -> None:
        self.checkpoints += self._in_run
        self._in_run = 0


def restored(path: Path) -> Catalog:
    """Open a backup as a fresh registrar would, and check the catalog's invariants."""
    store = SqliteStore.open(path)
    try:
        rows = store.load()
    finally:
        store.close(erase=False)
    catalog = Catalog.restore(*rows) if rows is not None else Catalog()
    catalog.check_invariants()
    return catalog


def check(paths: tuple[Path, Path], model: Model) -> None:
    """The invariants and the acknowledged operations, on the backups just left behind."""
    provider, consumer = restored(paths[0]), restored(paths[1])
    served = {q for r in provider.resources.values() for q in r.consumers}
    held = {q for q, record in consumer.clients.items() if record.loaded}
    present = model.loaded - model.unload_started
    assert set() == present - served, "an acknowledged load is missing at the provider"
    assert set() == present - held, "an acknowledged load is missing at the consumer"
    assert set() == model.unloaded & served, "an acknowledged unload is back at the provider"
    assert set() == model.unloaded & set(consumer.clients), "an acknowledged unload is back"


def run_kills(
    context: multiprocessing.context.BaseContext,
    directory: Path,
    *,
    kills: int,
    seed: int,
    max_reports: int = 30,
) -> Model:
    """Start, drive and SIGKILL the worker `kills` times on one pair of backups.

    Returns the model of what was acknowledged (the checks ran after every kill).
    """
    rng = random.Random(seed)  # noqa: S311 - reproducible kill moments
    names, paths = pair_backups(directory)
    model = Model()
    for _ in range(kills):
        parent_end, child_end = context.Pipe(duplex=False)
        process = context.Process(
            target=worker,
            args=(names, tuple(map(str, paths)), rng.randrange(2**32), child_end),
            daemon=True,
        )
        process.start()
        child_end.close()
        try:
            for _ in range(rng.randrange(max_reports + 1)):
                if not parent_end.poll(20):
                    break
                model.record(*parent_end.recv())
        finally:
            assert process.pid is not None
            with contextlib.suppress(ProcessLookupError):
                os.kill(process.pid, signal.SIGKILL)
            process.join(10)
        with contextlib.suppress(EOFError, OSError):
            while parent_end.poll(0):  # sent before the kill: acknowledged too
                model.record(*parent_end.recv())
        parent_end.close()
        model.end_run()
        assert process.exitcode == -signal.SIGKILL, f"the worker ended with {process.exitcode}"
        check(paths, model)
    return model


@pytest.mark.timeout(300)  # (a hang ceiling: 4-5 s quiet; once over the suite's 60 s at load 20+)
def test_fifty_random_kills_never_tear_a_catalog_nor_lose_an_acknowledged_operation(
    tmp_path: Path, context: multiprocessing.context.ForkServerContext
) -> None:
    model = run_kills(context, tmp_path, kills=50, seed=20240613)

    assert model.loaded, "the workload acknowledged no load at all"
    assert model.checkpoints >= 10, "the kills never met background checkpoints"


def test_a_fresh_registrar_restores_the_backups_left_by_random_kills(
    tmp_path: Path, context: multiprocessing.context.ForkServerContext
) -> None:
    model = run_kills(context, tmp_path, kills=5, seed=7)
    provider = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=f"P-{uuid.uuid4().hex[:8]}", backup_path=tmp_path / "p.db")
    )
    try:
        view = catalog_snapshot(provider)
    finally:
        provider.stop()

    served = {q for r in view.resources for q in r.consumers}
    assert set() == (model.loaded - model.unload_started) - served
