"""Restore without decoding, digests and older schemas (`_store/schema.py`)."""

from __future__ import annotations

import collections
import os
import pickle
import sqlite3
import subprocess
import sys
import traceback
import uuid
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr
from rr_actors._catalog import (
    DIGEST_SCHEME,
    Catalog,
    ResourceState,
    request_digest,
)
from rr_actors._core import wire
from rr_actors._store import schema
from rr_actors._store.restore import read_backup
from rr_actors._store.saver import SqliteStore
from rr_actors.testing import crash
from tests.support.durable_pair import (
    new_store,
    noop_unload,
    schema_2_database,
    start,
    written_schema,
)
from tests.support.persisting import (
    catalog_with_a_gone_class,
    consumer_ids,
    lazily_restored,
    reopen,
    stored_catalog,
    unique,
    write_v1_backup,
)


def test_a_restore_reads_a_served_resource_only_when_a_lookup_needs_it(tmp_path: Path) -> None:
    stored_catalog(tmp_path / "p.db", [{"n": n} for n in range(6)])
    store, catalog, waiting = lazily_restored(tmp_path / "p.db")
    try:
        in_memory = len(catalog.resources)
        found = catalog.find("leaf", {"n": 2})  # by digest, through the index
        by_consumer = catalog.resource_of("q4")  # by consumer id, through its index
        known = (catalog.has_consumer("q5"), catalog.has_consumer("q-never"))
        after = sorted(catalog.resources)
        of_server = [r.id for r in catalog.resources_of("leaf")]
        catalog.check_invariants()
    finally:
        store.close(erase=False)

    assert (True, 0, "r2", "r4", (True, False), ["r2", "r4", "r5"]) == (
        waiting,
        in_memory,
        found.id if found else None,
        by_consumer.id,
        known,
        after,
    )
    assert sorted(of_server) == [f"r{n}" for n in range(6)]


def test_a_consumer_id_holding_the_column_separator_is_restored_all_the_same(
    tmp_path: Path,
) -> None:
    store, catalog = new_store(tmp_path / "p.db")
    for n, query_id in enumerate(["plain", "with\x1funit separator", "with,comma"]):
        catalog.begin_load(f"r{n}", "leaf", n)
        catalog.finish_load(f"r{n}", n)
        catalog.add_consumer(f"r{n}", query_id, "C")
    store.write(catalog.drain_changes())
    store.close(erase=False)

    store, restored, _ = lazily_restored(tmp_path / "p.db")
    try:
        found = [restored.resource_of(q).id for q in ("with,comma", "with\x1funit separator")]
        missing = restored.has_consumer("with")
    finally:
        store.close(erase=False)

    assert (["r2", "r1"], False) == (found, missing)


def test_memory_wins_over_rows_not_written_yet_for_a_lazily_restored_catalog(
    tmp_path: Path,
) -> None:
    """A release or removal not flushed yet (save_interval) must not come back from disk."""
    stored_catalog(tmp_path / "p.db", [{"n": n} for n in range(4)])
    store, catalog, _ = lazily_restored(tmp_path / "p.db")
    try:
        resource = catalog.resource_of("q1")
        catalog.release("q1")
        catalog.begin_unload(resource.id)
        catalog.remove_resource(resource.id)
        pending = catalog.drain_changes()  # held back, as a save_interval registrar does
        seen = (
            catalog.has_consumer("q1"),
            catalog.find("leaf", {"n": 1}),
            "r1" in catalog.read_all(),
        )
        store.write(pending)
    finally:
        store.close(erase=False)

    assert ((False, None, False), ["r0", "r2", "r3"]) == (
        seen,
        sorted(r.id for r in read_backup(tmp_path / "p.db").resources),
    )


def test_consumers_from_an_origin_include_those_of_resources_still_on_disk(
    tmp_path: Path,
) -> None:
    store, catalog = new_store(tmp_path / "p.db")
    for n in range(6):
        catalog.begin_load(f"r{n}", "leaf", n)
        catalog.finish_load(f"r{n}", n)
        catalog.add_consumer(f"r{n}", f"a{n}", "A")
        if n % 2:
            catalog.add_consumer(f"r{n}", f"b{n}", "B")
    store.write(catalog.drain_changes())
    store.close(erase=False)

    store, restored, _ = lazily_restored(tmp_path / "p.db")
    try:
        from_b = restored.consumers_from("B")
        listed = [r.id for r in restored.read_all().values()]
    finally:
        store.close(erase=False)

    assert (["b1", "b3", "b5"], [f"r{n}" for n in range(6)]) == (sorted(from_b), listed)


def test_a_restore_leaves_requests_and_responses_encoded_until_first_used(tmp_path: Path) -> None:
    stored_catalog(tmp_path / "p.db", [{"n": n} for n in range(5)])
    store = SqliteStore.open(tmp_path / "p.db")
    rows = store.load()
    store.close(erase=False)
    assert rows is not None

    catalog = Catalog.restore(*rows)
    found = catalog.find("leaf", {"n": 3})

    assert found is not None
    decoded = [sorted({"request", "response"} & set(vars(r))) for r in catalog.resources.values()]
    assert [[], [], [], ["request"], []] == decoded
    assert ({"n": 3}, {"pid": 3}) == (found.request, found.response)


def test_a_stored_value_whose_class_is_gone_raises_catalog_corrupt_error_when_first_used(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    catalog_with_a_gone_class(tmp_path / "p.db", monkeypatch)

    catalog = reopen(tmp_path / "p.db")
    with pytest.raises(rr.CatalogCorruptError) as raised:
        _ = catalog.resources["r1"].response

    assert (str(tmp_path / "p.db"), True, {"pid": 0}) == (
        raised.value.path,
        "response of resource r1 cannot be read" in raised.value.cause,
        catalog.resources["r0"].response,
    )


def test_a_new_response_for_a_restored_resource_reaches_the_file(tmp_path: Path) -> None:
    stored_catalog(tmp_path / "p.db", ["a", "b"])
    store = SqliteStore.open(tmp_path / "p.db")
    rows = store.load()
    assert rows is not None
    catalog = Catalog.restore(*rows)
    _ = catalog.resources["r0"].response  # decoded: not a change
    catalog.set_response("r0", "old one decoded, then kept")
    catalog.set_response("r1", "replaced without a look")
    catalog.set_response("r0", catalog.resources["r0"].response)
    store.write(catalog.drain_changes())
    store.close(erase=False)

    assert ["old one decoded, then kept", "replaced without a look"] == [
        r.response for r in reopen(tmp_path / "p.db").resources.values()
    ]


def test_the_stored_digest_is_the_same_in_a_process_with_another_string_hash_seed(
    tmp_path: Path,
) -> None:
    request = {
        "cmd": ["driver", "--id", "7"],
        "on": True,
        "rate": 2.5,
        "mode": ResourceState.LOADED,
    }
    stored_catalog(tmp_path / "p.db", [request])
    code = (
        "from rr_actors._catalog import ResourceState, request_digest; "
        "print(request_digest({'rate': 2.5, 'on': 1, 'cmd': ['driver', '--id', '7'], "
        "'mode': ResourceState.LOADED}))"
    )
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    ).stdout
    db = sqlite3.connect(tmp_path / "p.db")
    try:
        [(stored,)] = db.execute("SELECT digest FROM resources").fetchall()
    finally:
        db.close()

    assert int(out) == stored


def test_digests_written_under_another_scheme_are_recomputed_when_the_file_is_opened(
    tmp_path: Path,
) -> None:
    stored_catalog(tmp_path / "p.db", [{"n": 1}, ["x"]])
    db = sqlite3.connect(tmp_path / "p.db")
    db.execute("UPDATE resources SET digest = 42")
    db.execute("UPDATE rr_actors_schema SET digest_scheme = 'another-python'")
    db.commit()
    db.close()

    catalog = reopen(tmp_path / "p.db")

    assert ("r0", "r1") == (catalog.find("leaf", {"n": 1.0}).id, catalog.find("leaf", ["x"]).id)


def test_a_version_1_backup_is_migrated_to_digests_integer_states_and_consumer_rows(
    tmp_path: Path,
) -> None:
    write_v1_backup(tmp_path / "p.db")

    catalog = reopen(tmp_path / "p.db")

    db = sqlite3.connect(tmp_path / "p.db")
    try:
        stored = db.execute("SELECT version, digest_scheme FROM rr_actors_schema").fetchall()
        digests = db.execute("SELECT digest, state FROM resources ORDER BY seq").fetchall()
        consumers = db.execute("SELECT query_id, resource FROM consumers").fetchall()
    finally:
        db.close()
    assert [(schema.SCHEMA_VERSION, DIGEST_SCHEME)] == stored
    assert [(request_digest({"n": 0}), 1), (request_digest("x"), 0)] == digests
    assert [("q0", 1)] == consumers
    assert (
        "r0",
        ["q0"],
        ResourceState.LOADING,
        ["d0"],
    ) == (
        catalog.find("leaf", {"n": 0}).id,
        list(catalog.resources["r0"].consumers),
        catalog.resources["r1"].state,
        [c.query.id for c in catalog.dependencies("r0")],
    )


def test_a_request_without_a_digest_is_restored_and_found_by_equality(tmp_path: Path) -> None:
    stored_catalog(tmp_path / "p.db", [ResourceState.LOADED, ("tuple", ResourceState.LOADING)])

    catalog = reopen(tmp_path / "p.db")

    assert ("r0", "r1") == (
        catalog.find("leaf", ResourceState.LOADED).id,
        catalog.find("leaf", ("tuple", ResourceState.LOADING)).id,
    )


def test_a_call_that_meets_an_unreadable_restored_value_fails_and_the_registrar_keeps_serving(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    catalog_with_a_gone_class(tmp_path / "p.db", monkeypatch)
    name = f"p-{uuid.uuid4().hex[:8]}"
    provider = rr.ResourceRegistrar.start(rr.RegistrarConfig(name, backup_path=tmp_path / "p.db"))
    consumer = rr.ResourceRegistrar.start(f"c-{uuid.uuid4().hex[:8]}")
    try:
        provider.register_server("leaf", load=lambda r: r, unload=lambda r, s: None)
        with pytest.raises(rr.CatalogCorruptError):
            consumer.call(name, "leaf", "other", timeout=5)
        served = consumer.call(name, "leaf", "plain", timeout=5)

        assert ({"pid": 0}, True) == (served.response, provider.is_alive())
    finally:
        consumer.stop()
        provider.stop()


# -- the `failed` mark (schema version 6) ------------------------------------------------------

SCHEMA_5_BACKUP = Path(__file__).parent / "data" / "schema-5-fatal.db"
"""A backup written by rr_actors c29caab (schema version 5), with this script run with
that tree first on `PYTHONPATH` (then `PRAGMA wal_checkpoint(TRUNCATE)` folded its log
in; its `-commits` file was left out)::

    import os, sys
    import rr_actors as rr
    reg = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name="old-erm", backup_path=sys.argv[1], save_on_modify=True)
    )
    reg.register_server("leaf", load=lambda r: {"for": r, "load": 1}, unload=lambda r, s: None)
    q = reg.call("old-erm", "leaf", "lidar", query_id="00000000-0000-4000-8000-000000000001")
    reg.send_status(q.id, rr.Status.FATAL, "the LiDAR process died")  # no mark kept then
    os._exit(0)  # as a SIGKILL: no stop, the held id stays in the backup
"""


def test_a_failed_mark_is_written_and_read_back_at_once_and_lazily(tmp_path: Path) -> None:
    path = tmp_path / "p.db"
    stored_catalog(path, [{"n": 0}, {"n": 1}])
    store = SqliteStore.open(path)
    rows = store.load()
    assert rows is not None
    catalog = Catalog.restore(*rows)
    catalog.mark_failed("r1")
    store.write(catalog.drain_changes())
    store.close(erase=False)

    at_once = reopen(path)  # (checks that the lazy restore reads the same)
    store, lazily, _ = lazily_restored(path)
    try:
        found = [lazily.find("leaf", {"n": n}) for n in (0, 1)]
        marks = {rid: r.failed for rid, r in lazily.read_all().items()}
    finally:
        store.close(erase=False)

    assert {"r0": False, "r1": True} == {rid: r.failed for rid, r in at_once.resources.items()}
    assert (["r0", None], {"r0": False, "r1": True}) == (
        [r.id if r else None for r in found],
        marks,
    )


def test_a_schema_5_backup_is_migrated_with_no_resource_marked_failed(tmp_path: Path) -> None:
    path = tmp_path / "old.db"
    path.write_bytes(SCHEMA_5_BACKUP.read_bytes())

    catalog = reopen(path)

    db = sqlite3.connect(path)
    try:
        version = db.execute("SELECT version FROM rr_actors_schema").fetchone()[0]
        failed = db.execute("SELECT failed FROM resources").fetchall()
    finally:
        db.close()
    [resource] = catalog.resources.values()
    assert (schema.SCHEMA_VERSION, [(0,)]) == (version, failed)
    assert (resource, ["00000000-0000-4000-8000-000000000001"]) == (
        catalog.find("leaf", "lidar"),
        list(resource.consumers),
    )
    assert (False, {"for": "lidar", "load": 1}) == (resource.failed, resource.response)


# -- store: explicit migrations ---------------------------------------------------------------


def write_v2_backup(path: Path) -> None:
    """A schema-2 backup (rowid consumers, no indexes): r0 loaded with consumer q0."""
    db = schema_2_database(path)
    dumps = schema.dumps
    db.execute(
        "INSERT INTO resources VALUES (1, 'r0', 'leaf', 1, ?, ?, ?)",
        (request_digest({"n": 0}), dumps({"n": 0}), dumps({"pid": 0})),
    )
    db.execute("INSERT INTO consumers VALUES (2, 'q0', 1, 'C')")
    db.execute("PRAGMA journal_mode = WAL")
    db.close()


def test_a_version_2_backup_is_brought_to_the_current_schema_with_its_indexes(
    tmp_path: Path,
) -> None:
    path = tmp_path / "p.db"
    write_v2_backup(path)

    SqliteStore.open(path).close(erase=False)

    db = sqlite3.connect(path)
    try:
        version = db.execute("SELECT version FROM rr_actors_schema").fetchone()[0]
        indexes = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='index'")}
        consumers_pk = [r[1] for r in db.execute("PRAGMA table_info(consumers)") if r[5]]
    finally:
        db.close()
    assert (schema.SCHEMA_VERSION, True, ["resource", "seq"]) == (
        version,
        set(schema.INDEXES) <= indexes,
        consumers_pk,
    )


def test_a_migration_step_that_fails_leaves_the_file_at_its_old_version(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "p.db"
    SqliteStore.open(path).close(erase=False)

    def half_done(db: sqlite3.Connection) -> None:
        db.execute("ALTER TABLE resources ADD COLUMN note TEXT")
        raise sqlite3.OperationalError("disk I/O error (simulated)")

    monkeypatch.setattr(schema, "MIGRATIONS", (*schema.MIGRATIONS, half_done))
    monkeypatch.setattr(schema, "SCHEMA_VERSION", schema.SCHEMA_VERSION + 1)
    with pytest.raises((rr.CatalogCorruptError, sqlite3.Error)):
        SqliteStore.open(path)
    monkeypatch.undo()

    version, columns = written_schema(path)
    assert (schema.SCHEMA_VERSION, False) == (version, "note" in columns)


def test_a_new_file_is_made_with_exactly_the_objects_the_migrations_make_and_needs_none(
    tmp_path: Path,
) -> None:
    """`CREATE` (one transaction) and `MIGRATIONS` (one each) make the same schema: a file
    made new passes the check every migrated file passes, and migrating it does nothing."""
    made = sqlite3.connect(tmp_path / "made.db", isolation_level=None)
    try:
        schema.create(made)
        objects = made.execute("SELECT type, name, tbl_name, sql FROM sqlite_master").fetchall()
        version = schema.schema_version(made, "made.db")
        scheme = made.execute("SELECT digest_scheme FROM rr_actors_schema").fetchone()[0]
        changes = made.total_changes
        schema.migrate(made, version)
        schema.refresh_digests(made, "made.db")
        unchanged = made.total_changes == changes
    finally:
        made.close()

    found = frozenset((k, n, t, schema._normal(sql)) for k, n, t, sql in objects)
    assert (schema.expected_objects(), schema.SCHEMA_VERSION, DIGEST_SCHEME, True) == (
        found,
        version,
        scheme,
        unchanged,
    )


def test_the_empty_image_a_new_backup_is_written_from_is_the_file_sqlite_makes_in_wal_mode(
    tmp_path: Path,
) -> None:
    """`empty_image()` (made in memory, its header set to WAL) written to a file reads as
    the file SQLite builds with `create` and `PRAGMA journal_mode = WAL`: the same objects,
    version, digest scheme, application id and page size, WAL, whole; and it takes a commit."""

    def read(path: Path) -> tuple[Any, ...]:
        db = sqlite3.connect(path, isolation_level=None)
        try:
            pragmas = [
                db.execute(f"PRAGMA {name}").fetchone()[0]
                for name in ("journal_mode", "integrity_check", "application_id", "page_size")
            ]
            objects = db.execute("SELECT type, name, tbl_name, sql FROM sqlite_master").fetchall()
            row = db.execute("SELECT * FROM rr_actors_schema").fetchall()
            db.execute("INSERT INTO outbox (pid, seq, event) VALUES (1, 1, 'e')")
            return (*pragmas, sorted(objects), row)
        finally:
            db.close()

    built = sqlite3.connect(tmp_path / "built.db", isolation_level=None)
    try:
        schema.create(built)
        built.execute("PRAGMA journal_mode = WAL")
    finally:
        built.close()
    (tmp_path / "image.db").write_bytes(schema.empty_image())

    made = read(tmp_path / "image.db")
    assert (read(tmp_path / "built.db"), "wal") == (made, made[0])


def test_the_empty_image_follows_the_schema_version_a_new_migration_brings(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One image a schema version: a migration step added (as a release adds one) makes a
    new image, of that version, not the one made before it."""
    before = schema.empty_image()

    def add_note(db: sqlite3.Connection) -> None:
        db.execute("ALTER TABLE resources ADD COLUMN note TEXT")

    monkeypatch.setattr(schema, "MIGRATIONS", (*schema.MIGRATIONS, add_note))
    monkeypatch.setattr(schema, "SCHEMA_VERSION", schema.SCHEMA_VERSION + 1)
    after = schema.empty_image()
    (tmp_path / "after.db").write_bytes(after)
    version, columns = written_schema(tmp_path / "after.db")
    assert (False, schema.SCHEMA_VERSION, True) == (before == after, version, "note" in columns)


# -- a row's values (encoded, decoded) -------------------------------------------------------------
# How stored values are encoded and decoded (`dumps`, `decode`): a request stored
# with cloudpickle comes back (its code with its file's name), and one without a digest is
# found again (issue 3's contract).
# -- requests are stored with cloudpickle ---------------------------------------------------------


def test_a_request_holding_a_function_defined_here_is_stored_and_restored(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    path = tmp_path / "p.db"
    name = unique("P")
    offset = 40

    def local_callback(value: int) -> int:  # not importable by name: plain pickle refuses it
        return value + offset

    provider = start(started, name, path, save_on_modify=True)
    provider.register_server("leaf", load=lambda r: r["f"](2), unload=noop_unload)
    query = provider.call(name, "leaf", {"f": local_callback})

    [resource] = read_backup(path).resources
    assert (42, 42, {query.id}) == (query.response, resource.request["f"](2), consumer_ids(path))


def test_a_function_in_a_restored_request_keeps_its_file_so_a_traceback_shows_file_and_line(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    # cloudpickle 3.1.3 names code it pickles by value "<dynamic-code>": stored as it,
    # a restored request's function raised with no file and no source line
    path = tmp_path / "p.db"
    name = unique("P")

    def local_divide(value: int) -> float:  # pickled by value: a closure
        return 1 / value  # the line a traceback must show

    provider = start(started, name, path, save_on_modify=True)
    provider.register_server("leaf", load=lambda r: r["f"](2), unload=noop_unload)
    provider.call(name, "leaf", {"f": local_divide})

    [resource] = read_backup(path).resources
    with pytest.raises(ZeroDivisionError) as info:
        resource.request["f"](0)

    [*_, raised] = traceback.extract_tb(info.value.__traceback__)
    assert (__file__, "local_divide") == (raised.filename, raised.name)
    assert "return 1 / value  # the line a traceback must show" == raised.line


@pytest.mark.parametrize(
    "value",
    ["shared-2", {"server": "edge/resource", "request": "unique-0-7"}, ("a", 1, None, b"x")],
)
def test_small_builtin_data_is_stored_as_cloudpickle_would_store_it_without_cloudpickle(
    value: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    expected = cloudpickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
    monkeypatch.setattr(wire, "Pickler", None)  # (a pickler built: a TypeError)
    assert schema.dumps(value) == expected


def test_an_unhashable_request_without_a_digest_is_found_again_after_a_restart(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    # Counter has its own __eq__ (so no stored digest) and is unhashable: after a restore
    # only `==` against the restored request can find it
    path = tmp_path / "p.db"
    name = unique("P")
    loads: list[Any] = []

    def load(request: Any) -> Any:
        loads.append(request)
        return {"pid": len(loads)}

    provider = start(started, name, path, save_on_modify=True)
    provider.register_server("leaf", load=load, unload=noop_unload)
    first = provider.call(name, "leaf", collections.Counter({"cam": 2, "lidar": 1}))
    crash(provider)  # a clean stop would give back the id this registrar holds itself

    provider = start(started, name, path, save_on_modify=True)
    provider.register_server("leaf", load=load, unload=noop_unload)
    again = provider.call(name, "leaf", collections.Counter({"lidar": 1, "cam": 2}))

    assert (1, {"pid": 1}, {first.id, again.id}) == (len(loads), again.response, consumer_ids(path))
