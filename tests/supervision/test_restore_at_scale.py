"""A large catalog after a SIGKILL: every old id works, also those read after serving.

A restart serves before it has read its catalog (issue 34): consumer ids and served
resources are read through the backup's indexes when a call first needs them, and the
unheld resources and the registrars to reconcile with are swept after it serves, a
slice at a time. These tests kill a real manager process whose backup holds 20k
entries and check, from outside, what rule 15 promises of every one of them.
"""

from __future__ import annotations

import os
import queue
import signal
import uuid
from collections.abc import Callable
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors._catalog import Catalog
from rr_actors._store.restore import SWEEP_ROWS
from rr_actors._store.sqlite import SqliteStore

pytestmark = pytest.mark.usefixtures("process_helpers")  # the forkserver, before the leak check

ENTRIES = 20_000
"""Served resources in the backup: ten sweep slices (20k consumer ids besides)."""

UNHELD = (3 * SWEEP_ROWS + 5, 7 * SWEEP_ROWS + 5, ENTRIES - 2)
"""Entries whose last consumer left before the crash (their unload never began): each
in a slice that only the sweep after serving reaches."""

FORGOTTEN = ENTRIES - 1
"""An entry held by the test's consumer `app`, which does not hold it (any more)."""


def fill(path: Path) -> tuple[dict[int, str], str]:
    """Write `ENTRIES` loaded resources of server `res` (request `{"n": n}`, response
    `{"stored": n}`): one consumer id each, of registrar `gone` (never running), but
    none for `UNHELD` and one of `app` for `FORGOTTEN`. Returns their resource ids and
    the consumer id of `FORGOTTEN`."""
    store = SqliteStore.open(path)
    store.load()
    catalog = Catalog()
    ids = {}
    forgotten = str(uuid.uuid4())
    for n in range(ENTRIES):
        rid = ids[n] = str(uuid.uuid4())
        catalog.begin_load(rid, "res", {"n": n})
        catalog.finish_load(rid, {"stored": n})
        if n == FORGOTTEN:
            catalog.add_consumer(rid, forgotten, "app")
        elif n not in UNHELD:
            catalog.add_consumer(rid, str(uuid.uuid4()), "gone")
    store.write(catalog.drain_changes())
    store.close(erase=False)
    return ids, forgotten


def setup(registrar: rr.ResourceRegistrar) -> None:
    """Server `res` loads `{"loaded": request}`; loading `poke` sends a status to the
    consumers of the resource that consumer id `request` holds."""
    registrar.register_server("res", load=lambda r: {"loaded": r}, unload=lambda r, s: None)

    def poke(query_id: str) -> str:
        registrar.send_status(query_id, rr.Status.WARNING, "poked", timeout=30.0)
        return query_id

    registrar.register_server("poke", load=poke, unload=lambda r, s: None)


class Heard:
    """The tree's events that these tests wait for (put on queues by a subscriber thread)."""

    def __init__(self) -> None:
        self.unloaded: queue.SimpleQueue[str] = queue.SimpleQueue()
        self.released: queue.SimpleQueue[tuple[str, str]] = queue.SimpleQueue()

    def __call__(self, event: rr.events.Event) -> None:
        if isinstance(event, rr.events.ResourceUnloaded):
            self.unloaded.put(event.resource_id)
        elif isinstance(event, rr.events.ConsumerReleased):
            self.released.put((event.query_id, event.reason))

    def unloads(self, count: int) -> set[str]:
        return {self.unloaded.get(timeout=60.0) for _ in range(count)}


@pytest.mark.timeout(240)
def test_every_id_of_a_20k_catalog_works_after_a_sigkill_also_those_read_after_serving(
    supervisors: Callable[..., rr.Supervisor], uid: str, tmp_path: Path
) -> None:
    name = f"big-{uid}"
    ids, forgotten = fill(tmp_path / f"{name}.db")
    heard = Heard()
    # (no heartbeat: hang detection is not this test's; on a CPU shared by load 20+ the
    # 20k sweep after serving can miss a 0.75 s heartbeat, and the restart that follows
    # fails a call in flight with RegistrarUnavailableError)
    spec = rr.ManagerSpec(name, setup, isolation="process", start_timeout=120.0, heartbeat=None)
    sup = supervisors([spec], state_dir=tmp_path, max_restarts=5, period=600.0)
    statuses: queue.SimpleQueue[tuple[str, rr.Status]] = queue.SimpleQueue()

    def on_status(query: rr.Query, update: rr.StatusUpdate) -> None:
        statuses.put((query.id, update.status))

    with sup.subscribe(heard):
        sup.start()
        assert {ids[n] for n in UNHELD} == heard.unloads(len(UNHELD))
        app = sup.registrar("app")
        shared = app.call(name, "res", {"n": 5}, on_status=on_status, timeout=60.0)
        fresh = app.call(name, "res", {"n": "fresh"}, on_status=on_status, timeout=60.0)
        second = app.call(name, "res", {"n": "fresh"}, on_status=on_status, timeout=60.0)
        pid = sup.child(name).pid
        assert pid is not None

        os.kill(pid, signal.SIGKILL)
        sup.wait_restarted(name, timeout=120.0)
        # calls at once: each id's row is still in the backup (read when needed)
        equal = app.call(name, "res", {"n": 12_345}, timeout=60.0)  # a restored resource
        app.unload(shared.id)  # its resource keeps the id of `gone`: no unload
        poked = app.call(name, "poke", second.id, timeout=60.0)
        app.unload(fresh.id)
        app.unload(second.id)  # the last id: its unload runs
        # ... and the sweep after serving finds `app` in the last slice: it reconciles
        unloaded = heard.unloads(2)
        released = {heard.released.get(timeout=60.0) for _ in range(4)}
        heard_statuses = {statuses.get(timeout=60.0) for _ in range(2)}
        again = app.call(name, "res", {"n": 5}, timeout=60.0)  # still loaded, restored

    assert {"stored": 12_345} == equal.response  # a dedup hit, not a new load
    assert {"stored": 5} == again.response
    assert {(second.id, rr.Status.WARNING), (fresh.id, rr.Status.WARNING)} == heard_statuses
    assert second.id == poked.response
    assert fresh.response == second.response == {"loaded": {"n": "fresh"}}
    assert {
        (shared.id, "unload"),
        (fresh.id, "unload"),
        (second.id, "unload"),
        (forgotten, "reconcile"),
    } == released
    assert ids[FORGOTTEN] in unloaded
    assert 1 == len(unloaded - set(ids.values()))  # the fresh resource's
