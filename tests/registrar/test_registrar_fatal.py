"""A resource its provider reported `FATAL` is dead: an equal request loads a new one (rule 1).

The dead resource stays in the catalog, held by its consumers under their ids, until each
released it (its `unload` then runs once, rule 7); its statuses reach its own consumers
only. The mark survives a SIGKILL of the provider and its restore (rules 14-15), and a
backup written before the mark existed (schema version 5) still opens.
"""

from __future__ import annotations

import shutil
import sqlite3
import sys
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._store import SCHEMA_VERSION
from rr_actors.testing import RemoteRegistrar, SharedObjects, crash, expect_restart
from tests.support.durable_pair import durable_config

pytestmark = pytest.mark.both_apis  # the rules, against the async API too (conftest)

OLD_BACKUP = Path(__file__).parent.parent / "store" / "data" / "schema-5-fatal.db"
"""A backup rr_actors c29caab wrote (schema version 5, no `failed` column): registrar
`old-erm` served `leaf` `"lidar"` to itself (query id `...0001`), reported it `FATAL`,
and died (`os._exit`) holding it. See `tests/store/test_schema.py` for the script."""


def fresh(request: Any) -> Any:
    """A response no other load gives: tells a new resource from the dead one."""
    return {"for": request, "load": uuid.uuid4().hex}


def test_an_equal_call_after_a_fatal_loads_a_new_resource_while_a_holder_keeps_the_dead_one(
    make_registrar, serve, inbox
):
    provider = make_registrar("provider")
    holder, other = make_registrar("holder"), make_registrar("other")
    leaf = serve(provider, "leaf", fresh)
    heard_by_holder, heard_by_other = inbox(), inbox()
    dead = holder.call(provider.name, "leaf", "lidar", on_status=heard_by_holder, timeout=10)
    provider.send_status(dead.id, rr.Status.FATAL, "the LiDAR process died", timeout=10)

    new = other.call(provider.name, "leaf", "lidar", on_status=heard_by_other, timeout=10)
    provider.send_status(dead.id, rr.Status.ERROR, "still dead", timeout=10)

    assert ["lidar", "lidar"] == leaf.loads
    assert dead.response != new.response
    assert {dead.id: dead.response, new.id: new.response} == {
        q.id: q.response for q in provider.server_queries("leaf")
    }
    assert [dead.id] == [q.id for q in holder.fetch_queries(provider.name, "leaf")]
    assert [(dead.id, rr.Status.FATAL), (dead.id, rr.Status.ERROR)] == [
        (u.query_id, u.status) for _, u in heard_by_holder.updates
    ]
    assert [] == list(heard_by_other.updates)  # the dead one's statuses are not its


def test_the_dead_resource_unloads_once_when_its_last_holder_releases_it(make_registrar, serve):
    provider = make_registrar("provider")
    holder, other = make_registrar("holder"), make_registrar("other")
    leaf = serve(provider, "leaf", fresh)
    dead = holder.call(provider.name, "leaf", "lidar", timeout=10)
    twice = holder.call(provider.name, "leaf", "lidar", timeout=10)  # one resource, two ids
    provider.send_status(dead.id, rr.Status.FATAL, "the LiDAR process died", timeout=10)
    new = other.call(provider.name, "leaf", "lidar", timeout=10)

    holder.unload(dead.id, timeout=10)
    kept = [q.id for q in provider.server_queries("leaf")]
    holder.unload(twice.id, timeout=10)
    assert leaf.unloaded.wait(5)

    assert (sorted([twice.id, new.id]), [("lidar", dead.response)]) == (sorted(kept), leaf.unloads)
    assert [new.id] == [q.id for q in provider.server_queries("leaf")]
    again = other.call(provider.name, "leaf", "lidar", timeout=10)  # the new one is shared
    assert (new.response, 2) == (again.response, len(leaf.loads))


class LaterLoadsGated:
    """A `respond` whose first load answers at once and whose later loads wait on `gate`."""

    def __init__(self, gate: Any, started: Any, counted: Any) -> None:
        self.gate, self.started, self.counted = gate, started, counted

    def __call__(self, request: Any) -> Any:
        self.counted.append(request)
        if len(self.counted) > 1:
            self.started.set()
            assert self.gate.wait(10), "the gate of a gated load never opened"
        return fresh(request)


def test_concurrent_equal_calls_after_a_fatal_load_one_new_resource(
    make_registrar, serve, gates, shared, arrived
):
    provider, holder = make_registrar("provider"), make_registrar("holder")
    consumers = [make_registrar(f"consumer{i}") for i in range(2)]
    gated = LaterLoadsGated(gates(), shared.event(), shared.list())
    leaf = serve(provider, "leaf", gated)
    dead = holder.call(provider.name, "leaf", {"lidar": 1}, timeout=10)
    provider.send_status(dead.id, rr.Status.FATAL, "the LiDAR process died", timeout=10)

    ids = [str(uuid.uuid4()) for _ in range(4)]
    with ThreadPoolExecutor(4) as pool:
        futures = [
            pool.submit(
                consumers[n % 2].call, provider.name, "leaf", {"lidar": 1}, query_id=qid, timeout=10
            )
            for n, qid in enumerate(ids)
        ]
        assert gated.started.wait(5), "no new load started after the FATAL"
        assert arrived(provider, ids)  # all four wait for the one new load
        gated.gate.set()
        responses = [f.result(timeout=10).response for f in futures]

    assert 2 == len(leaf.loads)
    assert 1 == len({str(r) for r in responses})
    assert dead.response != responses[0]


def fatal_provider_setup(loads: Any) -> Callable[[rr.ResourceRegistrar], None]:
    """A provider with a server "leaf" whose loads are recorded and answered `fresh`."""

    def setup(registrar: rr.ResourceRegistrar) -> None:
        def load(request: Any) -> Any:
            loads.append(request)
            return fresh(request)

        registrar.register_server("leaf", load=load, unload=lambda _r, _s: None)

    return setup


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
@pytest.mark.usefixtures("by_value")
def test_a_restored_provider_does_not_hand_out_a_resource_it_reported_fatal_before_a_sigkill(
    managers: Callable[..., RemoteRegistrar], tmp_path: Path, process_helpers: SharedObjects
) -> None:
    loads = process_helpers.list()
    config = durable_config("provider", tmp_path)
    provider = managers(config, fatal_provider_setup(loads))
    holder = managers(durable_config("holder", tmp_path), None)
    other = managers(durable_config("other", tmp_path), None)
    dead = holder.call(config.name, "leaf", "lidar", timeout=10)
    provider.send_status(dead.id, rr.Status.FATAL, "the LiDAR process died", timeout=10)
    with expect_restart(config.name):  # as its supervisor would: no death watch
        provider.kill()
    restarted = managers(config, fatal_provider_setup(loads))

    new = other.call(config.name, "leaf", "lidar", timeout=10)

    assert (["lidar", "lidar"], True) == (list(loads), dead.response != new.response)
    assert {dead.id: dead.response, new.id: new.response} == {
        q.id: q.response for q in restarted.server_queries("leaf")
    }


# -- a backup written before the mark existed ----------------------------------------------


def test_a_schema_5_backup_opens_and_its_resources_are_matched_until_reported_fatal(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    path = tmp_path / "old-erm.db"
    shutil.copyfile(OLD_BACKUP, path)
    loads: list[Any] = []

    def setup(registrar: rr.ResourceRegistrar) -> None:
        registrar.register_server(
            "leaf", load=lambda r: loads.append(r) or fresh(r), unload=lambda _r, _s: None
        )

    config = rr.RegistrarConfig(name="old-erm", backup_path=str(path), save_on_modify=True)
    erm = rr.ResourceRegistrar.start(config, setup=setup)
    started.append(erm)
    [old] = erm.server_queries("leaf")
    shared_old = erm.call("old-erm", "leaf", "lidar", timeout=10)  # no mark: the old one
    erm.send_status(old.id, rr.Status.FATAL, "the LiDAR process died", timeout=10)
    new = erm.call("old-erm", "leaf", "lidar", timeout=10)
    with expect_restart(config.name):
        crash(erm)
    restored = rr.ResourceRegistrar.start(config, setup=setup)
    started.append(restored)
    after = restored.call("old-erm", "leaf", "lidar", timeout=10)
    with sqlite3.connect(path) as db:
        version = db.execute("SELECT version FROM rr_actors_schema").fetchone()[0]

    assert (old.response, {"for": "lidar", "load": 1}) == (shared_old.response, old.response)
    assert (["lidar"], new.response) == (loads, after.response)
    assert SCHEMA_VERSION == version  # (migrated to the current version)


class SlowlyCompared:
    """A request without a digest whose `==` says it runs, then waits on `gate`."""

    def __init__(self, n: int, comparing: Any, gate: Any) -> None:
        self.n, self.comparing, self.gate = n, comparing, gate

    def __eq__(self, other: object) -> bool:
        self.comparing.set()
        assert self.gate.wait(10), "the gate of a slow comparison never opened"
        return isinstance(other, SlowlyCompared) and other.n == self.n

    def __hash__(self) -> int:
        return hash(self.n)


def test_a_resource_reported_fatal_while_a_request_is_compared_with_it_is_not_shared(
    make_registrar, serve, gates, shared
):
    provider, holder, other = (make_registrar(p) for p in ("provider", "holder", "other"))
    leaf = serve(provider, "leaf", fresh)
    comparing, gate = shared.event(), gates()
    dead = holder.call(provider.name, "leaf", SlowlyCompared(1, comparing, gate), timeout=10)

    with ThreadPoolExecutor(1) as pool:
        asked = pool.submit(
            other.call, provider.name, "leaf", SlowlyCompared(1, comparing, gate), timeout=15
        )
        assert comparing.wait(5), "the request was never compared"
        provider.send_status(dead.id, rr.Status.FATAL, "the LiDAR process died", timeout=10)
        gate.set()
        new = asked.result(timeout=15)

    assert (2, True) == (len(leaf.loads), dead.response != new.response)
