"""A restored registrar serves before it has swept its catalog (issue 34).

What needs every restored row (the resources no consumer holds, to unload them; the
registrars holding ids, to reconcile) is swept after the registrar serves, one slice per
turn of its mailbox: a call is answered between two slices, from rows still in the file.
"""

from __future__ import annotations

import threading
import uuid
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors._catalog import Catalog
from rr_actors._store import restore
from rr_actors._store.sqlite import SqliteStore
from rr_actors.testing import intercept
from tests.support.waiting import wait_for

ENTRIES = 10_000
"""Restored resources: 5,000 slices of 2 (what a call may come between)."""


def fill(path: Path) -> str:
    """Loaded resources of server `res` (request `{"n": n}`, response `{"stored": n}`), each
    held by registrar `gone` (never running) but the last; returns the last one's id."""
    store = SqliteStore.open(path)
    store.load()
    catalog = Catalog()
    rid = ""
    for n in range(ENTRIES):
        rid = str(uuid.uuid4())
        catalog.begin_load(rid, "res", {"n": n})
        catalog.finish_load(rid, {"stored": n})
        if n < ENTRIES - 1:
            catalog.add_consumer(rid, str(uuid.uuid4()), "gone")
    store.write(catalog.drain_changes())
    store.close(erase=False)
    return rid


def serve(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("res", load=lambda r: {"loaded": r}, unload=lambda r, s: None)


@pytest.mark.timeout(120)
def test_a_call_is_answered_from_the_backup_before_the_sweep_after_the_restore_ends(
    tmp_path: Path, uid: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(restore, "SWEEP_ROWS", 2)
    unheld = fill(tmp_path / "p.db")
    config = rr.RegistrarConfig(name=f"swept-{uid}", backup_path=str(tmp_path / "p.db"))
    order: list[object] = []
    lock = threading.Lock()

    def seen(what: object) -> None:
        with lock:
            order.append(what)

    provider = rr.ResourceRegistrar.start(config, setup=serve)
    app = rr.ResourceRegistrar.start(f"app-{uid}")
    try:
        with (
            intercept(provider, "load", before=lambda _load: seen("load")),
            intercept(provider, "unload_resource", before=lambda r: seen(("unload", r.id))),
        ):
            equal = app.call(config.name, "res", {"n": 7}, timeout=30.0)
            assert wait_for(lambda: ("unload", unheld) in order, timeout=60.0)
    finally:
        app.stop()
        provider.stop()

    assert {"stored": 7} == equal.response  # a dedup hit on a row still in the file
    assert order.index("load") < order.index(("unload", unheld))
