"""Where a backup lives (`rr_actors._store.files`): its path, its file, and what is wrong.

- Bad backups: files that are not ours, damaged, unreadable, read-only, or with rows that
  cannot be right, each a clear error naming the file (rule 15; `files.py`, `restore.py`).
- The backup at real limits: names too long, a file deleted under a running registrar, a
  full disk, who may read the files (issue 16: 6, 7, 8 and the file modes). Full disks are
  real: a small tmpfs mounted for the test (`small_disk`; CI runs as root), filled with a
  file until `ENOSPC`. Crashes are real too: a manager process is SIGKILLed and its
  registrar restarted on the same backup.
"""

from __future__ import annotations

import contextlib
import errno
import gc
import logging
import os
import pickle
import sqlite3
import stat
import struct
import subprocess
import sys
import textwrap
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr
from rr_actors._catalog import Catalog, Changes
from rr_actors._platform import PLATFORM
from rr_actors._store import Saver, schema
from rr_actors._store.files import CommitCount, quarantine_backup
from rr_actors._store.restore import read_backup
from rr_actors._store.saver import SqliteStore
from rr_actors.testing import RemoteRegistrar, SharedObjects, System
from tests.support import selecting
from tests.support.durable_pair import noop_unload, start
from tests.support.persisting import (
    consumer_ids,
    digest,
    duplicate_client,
    duplicate_consumer,
    duplicate_resource,
    make_bad_row,
    make_empty,
    make_foreign,
    make_garbage,
    make_newer,
    make_truncated,
    state_minus_one,
    state_text,
    state_three,
    unique,
    write_valid_backup,
    written_once,
)
from tests.support.powercut import flush_points, logged_disk, mounted_image
from tests.support.small_disk import fill, mounted, remount_read_only


@pytest.mark.parametrize(
    ("make", "cause"),
    [
        (make_garbage, "not an SQLite database"),
        (make_truncated, "truncated"),
        (make_empty, "empty"),
        (make_foreign, "not an rr_actors catalog"),
        (make_newer, "schema version 99 is newer"),
    ],
)
def test_a_bad_backup_raises_catalog_corrupt_error_naming_the_file_and_is_left_untouched(
    tmp_path: Path, make: Callable[[Path], None], cause: str
) -> None:
    path = tmp_path / "p.db"
    make(path)
    before = digest(path)
    name = unique("P")

    with pytest.raises(rr.CatalogCorruptError) as raised:
        rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name, backup_path=path))

    assert (str(path), True, before, sorted(os.listdir(tmp_path))) == (
        raised.value.path,
        cause in raised.value.cause,
        digest(path),
        ["p.db"],
    )


def test_a_damaged_resource_row_raises_catalog_corrupt_error_when_first_used_and_only_then(
    tmp_path: Path,
) -> None:
    """A restore reads served resources on first use: a damaged one fails that use alone."""
    path = tmp_path / "p.db"
    make_bad_row(path)  # r7's request is not a pickle; r0 .. r299 are fine
    registrar = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=unique("P"), backup_path=path, save_interval=None)
    )
    try:
        registrar.register_server("leaf", load=lambda r: r, unload=noop_unload)
        seventh, eighth = ({"n": n, "pad": "x" * 200} for n in (7, 8))
        with pytest.raises(rr.CatalogCorruptError) as damaged:
            registrar.call(registrar.name, "leaf", seventh)
        with pytest.raises(rr.CatalogCorruptError) as again:
            registrar.call(registrar.name, "leaf", seventh)
        neighbour = registrar.call(registrar.name, "leaf", eighth)  # r8, restored: a dedup hit
        registrar.unload(neighbour.id)
    finally:
        registrar.stop()

    assert (str(path), True, True, 8) == (
        damaged.value.path,
        "resource r7 is not a pickle" in damaged.value.cause,
        "resource r7 is not a pickle" in again.value.cause,
        neighbour.response,
    )
    with sqlite3.connect(path) as db:  # r7's row is kept as it was
        assert db.execute("SELECT request FROM resources WHERE id = 'r7'").fetchone() == (
            b"\x00\xff\x00",
        )


def test_a_backup_that_failed_to_open_leaves_the_registrar_name_free(tmp_path: Path) -> None:
    make_garbage(tmp_path / "p.db")
    name = unique("P")
    with pytest.raises(rr.CatalogCorruptError):
        rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name, backup_path=tmp_path / "p.db"))

    registrar = rr.ResourceRegistrar.start(name)

    registrar.stop()


@pytest.mark.parametrize(
    ("where", "cause"),
    [
        (lambda tmp: tmp / "missing" / "p.db", "does not exist"),
        (lambda tmp: tmp, "is a directory"),
        (lambda _tmp: Path("/sys/rr_actors_test.db"), "cannot be created"),
    ],
)
def test_an_unusable_backup_path_raises_config_error_naming_it(
    tmp_path: Path, where: Callable[[Path], Path], cause: str
) -> None:
    path = where(tmp_path)
    if path.parent == Path("/sys"):
        try:
            path.touch()
        except OSError:
            pass
        else:
            path.unlink()
            pytest.skip("/sys is writable here")

    with pytest.raises(rr.ConfigError) as raised:
        rr.ResourceRegistrar.start(rr.RegistrarConfig(name=unique("P"), backup_path=path))

    assert (True, True) == (str(path) in str(raised.value), cause in str(raised.value))


def test_a_backup_path_that_is_a_dangling_symlink_raises_config_error_naming_it(
    tmp_path: Path,
) -> None:
    path = tmp_path / "p.db"
    path.symlink_to(tmp_path / "missing" / "p.db")  # (a state directory moved away)

    with pytest.raises(rr.ConfigError) as raised:
        rr.ResourceRegistrar.start(rr.RegistrarConfig(name=unique("P"), backup_path=path))

    assert str(path) in str(raised.value)


def test_a_read_only_backup_raises_config_error(tmp_path: Path) -> None:
    if os.geteuid() == 0:
        where = tmp_path / "ro"
        with mounted(where, "1m"):
            write_valid_backup(where / "p.db")
            remount_read_only(where)
            with pytest.raises(rr.ConfigError, match="not readable and writable") as raised:
                SqliteStore.open(where / "p.db")
    else:
        where = tmp_path
        write_valid_backup(where / "p.db")
        (where / "p.db").chmod(0o444)
        with pytest.raises(rr.ConfigError, match="not readable and writable") as raised:
            SqliteStore.open(where / "p.db")

    assert str(where / "p.db") in str(raised.value)


def test_a_backup_in_a_read_only_location_raises_config_error(tmp_path: Path) -> None:
    where = tmp_path / "ro"
    with mounted(where, "1m"):  # (skipped unless root: root ignores directory modes too)
        remount_read_only(where)
        with pytest.raises(rr.ConfigError, match="is not writable") as raised:
            SqliteStore.open(where / "p.db")

    assert str(where / "p.db") in str(raised.value)


def test_quarantine_moves_a_corrupt_backup_aside_so_a_registrar_starts_empty(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    make_garbage(tmp_path / "p.db")
    before = digest(tmp_path / "p.db")

    moved = quarantine_backup(tmp_path / "p.db")
    registrar = start(started, unique("P"), tmp_path / "p.db")

    assert (before, True, False) == (
        digest(moved),
        moved.name.startswith("p.db.corrupt-"),
        registrar.restored,
    )


def test_quarantine_without_a_file_raises_config_error(tmp_path: Path) -> None:
    with pytest.raises(rr.ConfigError, match="no catalog backup"):
        quarantine_backup(tmp_path / "p.db")


@pytest.mark.parametrize(
    ("damage", "cause"),
    [
        (duplicate_resource, "index resources_by_id is missing"),
        (duplicate_consumer, "index consumers_by_query is missing"),
        (duplicate_client, "client query id d1 is stored twice"),
        (state_minus_one, "unknown state -1"),
        (state_three, "unknown state 3"),
        (state_text, "unknown state 'loaded'"),
    ],
)
def test_a_duplicate_id_or_unknown_state_in_a_backup_raises_catalog_corrupt_error(
    tmp_path: Path, damage: Callable[[sqlite3.Connection], None], cause: str
) -> None:
    path = tmp_path / "p.db"
    written_once(path)
    db = sqlite3.connect(path)
    damage(db)
    db.commit()
    db.close()

    with pytest.raises(rr.CatalogCorruptError) as restored:  # as a registrar restores
        SqliteStore.open(path).restore()
    with pytest.raises(rr.CatalogCorruptError) as loaded:
        SqliteStore.open(path).load()
    with pytest.raises(rr.CatalogCorruptError) as inspected:
        read_backup(path)

    assert [(str(path), True)] * 3 == [
        (e.value.path, cause in e.value.cause) for e in (restored, loaded, inspected)
    ]


# -- store: a database of another program ------------------------------------------------------


def test_a_database_of_another_program_with_a_schema_table_is_refused_by_application_id(
    tmp_path: Path,
) -> None:
    path = tmp_path / "p.db"
    SqliteStore.open(path).close(erase=False)  # an rr_actors layout ...
    db = sqlite3.connect(path)
    db.execute("PRAGMA application_id = 1234")  # ... stamped by another program
    db.commit()
    db.close()
    before = path.read_bytes()

    with pytest.raises(rr.CatalogCorruptError) as raised:
        rr.ResourceRegistrar.start(rr.RegistrarConfig(name=unique("P"), backup_path=path))

    assert (str(path), True, before) == (
        raised.value.path,
        "not an rr_actors catalog" in raised.value.cause,
        path.read_bytes(),
    )


# -- bad locations (the suite runs as root, where permissions do not refuse anything) -----------


def test_a_read_only_directory_raises_config_error_naming_the_path(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real_access = os.access
    directory = str(tmp_path)

    def access(path: Any, mode: int, **kwargs: Any) -> bool:
        if os.fspath(path) == directory and mode & os.W_OK:
            return False  # what a non-root user sees for a read-only directory
        return real_access(path, mode, **kwargs)

    monkeypatch.setattr(os, "access", access)
    with pytest.raises(rr.ConfigError) as raised:
        rr.ResourceRegistrar.start(
            rr.RegistrarConfig(name=unique("P"), backup_path=tmp_path / "p.db")
        )

    assert (True, True, []) == (
        str(tmp_path / "p.db") in str(raised.value),
        "is not writable" in str(raised.value),
        list(tmp_path.iterdir()),
    )


def test_a_read_only_backup_file_raises_config_error_and_is_left_as_it_was(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "p.db"
    SqliteStore.open(path).close(erase=False)
    before = path.read_bytes()
    real_access = os.access

    def access(where: Any, mode: int, **kwargs: Any) -> bool:
        if os.fspath(where) == str(path) and mode & os.W_OK:
            return False
        return real_access(where, mode, **kwargs)

    monkeypatch.setattr(os, "access", access)
    with pytest.raises(rr.ConfigError) as raised:
        rr.ResourceRegistrar.start(rr.RegistrarConfig(name=unique("P"), backup_path=path))

    assert (True, True, before) == (
        str(path) in str(raised.value),
        "not readable and writable" in str(raised.value),
        path.read_bytes(),
    )


# -- quarantine_backup -------------------------------------------------------------------------


def test_quarantine_moves_the_wal_and_shm_files_with_the_backup(tmp_path: Path) -> None:
    live, crashed = tmp_path / "live", tmp_path / "crashed"
    live.mkdir()
    crashed.mkdir()
    store = SqliteStore.open(live / "p.db")
    try:
        store.load()
        catalog = Catalog()
        catalog.begin_load("r1", "leaf", 1)
        catalog.finish_load("r1", 1)
        catalog.add_consumer("r1", "q1", "C")
        store.write(catalog.drain_changes())  # in the -wal only: no checkpoint yet
        for suffix in ("", "-wal", "-shm"):  # the files a killed registrar leaves
            (crashed / f"p.db{suffix}").write_bytes((live / f"p.db{suffix}").read_bytes())
    finally:
        store.close(erase=False)

    moved = quarantine_backup(crashed / "p.db")

    assert (["p.db", "p.db-shm", "p.db-wal"], {"q1"}) == (
        sorted(p.name.replace(moved.name, "p.db") for p in crashed.iterdir()),
        consumer_ids(moved),
    )


def test_quarantining_twice_keeps_both_files(tmp_path: Path) -> None:
    path = tmp_path / "p.db"
    path.write_bytes(b"first garbage" * 100)
    first = quarantine_backup(path)
    path.write_bytes(b"second garbage" * 100)
    second = quarantine_backup(path)

    assert (True, b"first garbage" * 100, b"second garbage" * 100) == (
        first != second,
        first.read_bytes(),
        second.read_bytes(),
    )


def consumers_on_disk(path: Path) -> dict[str, list[str]]:
    """What a process started now would restore: each resource's consumer ids."""
    return {r.id: list(r.consumers) for r in read_backup(path).resources}


def loaded(catalog: Catalog, rid: str, *query_ids: str, size: int = 16) -> Changes:
    """Load resource `rid` (a request of about `size` bytes) for `query_ids`; its changes."""
    catalog.begin_load(rid, "leaf", {"rid": rid, "pad": "x" * size})
    catalog.finish_load(rid, {"pid": 1})
    for query_id in query_ids:
        catalog.add_consumer(rid, query_id, "C")
    return catalog.drain_changes()


@pytest.fixture
def store_at() -> Iterator[Callable[..., SqliteStore]]:
    """Open stores (`store_at(path, **options)`), loaded; closed at teardown."""
    opened: list[SqliteStore] = []

    def store_at(path: Path, **options: Any) -> SqliteStore:
        store = SqliteStore.open(path, **options)
        store.load()
        opened.append(store)
        return store

    yield store_at
    for store in opened:
        store.close(erase=False)


@pytest.fixture
def disk(tmp_path: Path) -> Iterator[Path]:
    """A 1 MiB tmpfs of its own (skipped unless this process may mount one)."""
    with mounted(tmp_path / "disk", "1m") as where:
        yield where


# -- 6. a path that cannot hold a backup is a ConfigError naming it ---------------------------


def deep_path(tmp_path: Path) -> Path:
    """A path longer than SQLite opens (504 bytes and its suffixes) of short names."""
    where = tmp_path
    while len(os.fsencode(os.path.abspath(where))) < 520:
        where = where / ("d" * 60)
    where.mkdir(parents=True)
    return where / "p.db"


@pytest.mark.parametrize(
    ("where", "cause"),
    [
        (lambda tmp: tmp / ("a" * 300 + ".db"), "the file name is 303 bytes long"),
        (lambda tmp: tmp / ("a" * 250 + ".db"), "the file name is 253 bytes long"),
        (deep_path, "SQLite opens at most 504"),
        (lambda tmp: tmp / "a-file" / "p.db", "is a file, not a directory"),
        (lambda tmp: tmp / "a-file" / "sub" / "p.db", "does not exist"),
        (lambda tmp: tmp / "missing" / "p.db", "does not exist"),
    ],
    ids=[
        "name-over-255",
        "name-without-room-for-journal",
        "path-over-504",
        "dir-is-file",
        "dir-under-file",
        "dir-missing",
    ],
)
def test_a_backup_path_that_cannot_hold_a_file_raises_config_error_naming_it(
    tmp_path: Path, where: Callable[[Path], Path], cause: str
) -> None:
    (tmp_path / "a-file").write_text("not a directory")
    path = where(tmp_path)

    with pytest.raises(rr.ConfigError) as raised:
        rr.ResourceRegistrar.start(rr.RegistrarConfig(name=unique("P"), backup_path=path))

    assert (True, True) == (str(path) in str(raised.value), cause in str(raised.value))


@pytest.mark.parametrize("act", [read_backup, quarantine_backup], ids=["read", "quarantine"])
def test_reading_or_quarantining_a_backup_named_too_long_raises_config_error(
    tmp_path: Path, act: Callable[[Path], Any]
) -> None:
    path = tmp_path / ("a" * 300 + ".db")

    with pytest.raises(rr.ConfigError, match="no catalog backup"):
        act(path)


# -- file modes: 0600 whatever the umask -------------------------------------------------------


@pytest.fixture(params=[0o000, 0o022, 0o277], ids=["umask-000", "umask-022", "umask-277"])
def umask(request: pytest.FixtureRequest) -> Iterator[int]:
    old = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(old)


def modes(directory: Path) -> dict[str, int]:
    return {p.name: stat.S_IMODE(p.stat().st_mode) for p in sorted(directory.iterdir())}


def test_a_new_backup_and_its_wal_and_shm_are_readable_by_their_owner_only(
    tmp_path: Path,
    umask: int,
    store_at: Callable[..., SqliteStore],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    linked: list[int] = []
    real_link = os.link

    def link(src: Any, dst: Any, **kwargs: Any) -> None:
        linked.append(stat.S_IMODE(os.stat(src).st_mode))  # the temporary file, complete
        real_link(src, dst, **kwargs)

    monkeypatch.setattr(os, "link", link)
    store = store_at(tmp_path / "p.db")
    store.write(loaded(Catalog(), "r1", "q1"))

    files = {"p.db": 0o600, "p.db-commits": 0o600, "p.db-shm": 0o600, "p.db-wal": 0o600}
    files["p.db.lock"] = 0o600  # (held while it is open: `files.claim`)
    assert ([0o600], files) == (
        linked,
        modes(tmp_path),
    )


# -- 7. a backup deleted while its registrar runs is written again, whole ----------------------


def delete_all(path: Path) -> None:
    for suffix in ("", "-wal", "-shm"):
        Path(f"{path}{suffix}").unlink()


def delete_file(path: Path) -> None:
    path.unlink()


def delete_wal(path: Path) -> None:
    Path(f"{path}-wal").unlink()


def replace_file(path: Path) -> None:
    other = path.with_name("other.db")
    other.write_bytes(b"another program's file")
    other.replace(path)


@pytest.mark.parametrize(
    "lose", [delete_all, delete_file, delete_wal, replace_file], ids=lambda f: f.__name__
)
@pytest.mark.parametrize("background", [False, True], ids=["own-checkpoints", "checkpointer"])
def test_a_backup_deleted_under_a_running_store_is_written_again_whole_at_the_next_commit(
    tmp_path: Path,
    store_at: Callable[..., SqliteStore],
    caplog: pytest.LogCaptureFixture,
    lose: Callable[[Path], None],
    background: bool,
) -> None:
    caplog.set_level(logging.WARNING, logger="rr_actors")
    path = tmp_path / "p.db"
    store = store_at(path, background_checkpoints=background)
    catalog = Catalog()
    store.write(loaded(catalog, "r1", "q1"))
    store.write(loaded(catalog, "r2", "q2"))
    lose(path)

    catalog.add_consumer("r1", "q3", "C")
    store.write(catalog.drain_changes())
    after_the_commit = consumers_on_disk(path)
    catalog.add_consumer("r2", "q4", "C")
    store.write(catalog.drain_changes())  # and it keeps writing there

    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert {"r1": ["q1", "q3"], "r2": ["q2"]} == after_the_commit
    assert {"r1": ["q1", "q3"], "r2": ["q2", "q4"]} == consumers_on_disk(path)
    assert (1, True) == (len(warnings), str(path) in warnings[0].getMessage())
    assert 0o600 == stat.S_IMODE(path.stat().st_mode)


def test_a_backup_deleted_after_the_last_commit_is_written_again_when_the_store_closes(
    tmp_path: Path,
) -> None:
    path = tmp_path / "p.db"
    store = SqliteStore.open(path)
    store.load()
    store.write(loaded(Catalog(), "r1", "q1"))
    delete_all(path)

    store.close(erase=False)

    assert {"r1": ["q1"]} == consumers_on_disk(path)


def test_a_lazily_restored_backup_deleted_mid_run_keeps_the_rows_not_read_yet(
    tmp_path: Path, store_at: Callable[..., SqliteStore]
) -> None:
    path = tmp_path / "p.db"
    writer = SqliteStore.open(path)
    writer.load()
    writer.write(loaded(Catalog(), "r1", "q1"))
    writer.write(loaded(Catalog(), "r2", "q2"))
    writer.close(erase=False)
    store = SqliteStore.open(path)
    restored = store.restore()
    assert restored is not None
    catalog = Catalog.restore(restored.resources, restored.clients, restored.unread)
    delete_all(path)

    catalog.add_consumer(catalog.resource_of("q1").id, "q3", "C")  # reads r1, not r2
    store.write(catalog.drain_changes())
    r2 = catalog.resource_of("q2")  # read now, from the new file
    store.close(erase=False)

    assert ("r2", {"r1": ["q1", "q3"], "r2": ["q2"]}) == (r2.id, consumers_on_disk(path))


def leaf_load(request: Any) -> Any:
    return {"leaf": request}


def serve_leaf(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("leaf", load=leaf_load, unload=noop_unload)


@pytest.mark.usefixtures("process_helpers")  # the forkserver, started before the leak check
def test_a_manager_whose_backup_was_deleted_mid_run_restores_every_acknowledged_id_after_sigkill(
    tmp_path: Path,
) -> None:
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    path = tmp_path / "p.db"
    config = rr.RegistrarConfig(name=unique("P"), backup_path=path, save_on_modify=True)
    system = System.create()
    consumer = rr.ResourceRegistrar.start(unique("C"))
    provider = restarted = None
    try:
        provider = RemoteRegistrar.start(config, system, setup=serve_leaf)
        before = [consumer.call(config.name, "leaf", n).id for n in range(3)]
        delete_all(path)
        after = [consumer.call(config.name, "leaf", n).id for n in range(3, 6)]
        provider.kill()  # SIGKILL
        restarted = RemoteRegistrar.start(config, system, setup=serve_leaf)

        held = {q.id for q in restarted.server_queries("leaf")}
    finally:
        consumer.stop()
        for registrar in (restarted, provider):
            if registrar is not None:
                registrar.stop()
        system.close()
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])

    assert set(before + after) == held


def test_a_copy_that_could_not_be_moved_into_place_is_moved_by_the_next_write(
    tmp_path: Path, store_at: Callable[..., SqliteStore], monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "p.db"
    store = store_at(path)
    catalog = Catalog()
    store.write(loaded(catalog, "r1", "q1"))
    delete_all(path)
    real_replace = os.replace

    def replace_fails_once(src: Any, dst: Any) -> None:
        monkeypatch.setattr(os, "replace", real_replace)
        raise OSError(errno.EIO, "Input/output error (injected)")

    monkeypatch.setattr(os, "replace", replace_fails_once)
    catalog.add_consumer("r1", "q2", "C")
    changes = catalog.drain_changes()
    with pytest.raises(rr.CatalogWriteError, match="EIO"):
        store.write(changes)
    copies = [p.name for p in tmp_path.iterdir() if p.name.endswith(".rewriting")]

    store.write(changes)

    assert (1, {"r1": ["q1", "q2"]}) == (len(copies), consumers_on_disk(path))
    assert [] == [p.name for p in tmp_path.iterdir() if p.name.endswith(".rewriting")]


@pytest.mark.skipif(PLATFORM.name != "linux", reason="inotify tells; elsewhere it stats")
def test_a_store_whose_names_did_not_change_stats_nothing_before_its_commits(
    tmp_path: Path, store_at: Callable[..., SqliteStore], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The check that the path still names the file costs a `poll` a commit, not two
    `stat` calls (the kernel tells when a name changes); the tests above show it told. In
    a process of several stores (the supervisor's, a pool's): a process manager's one stats."""
    path = tmp_path / "p.db"
    store_at(tmp_path / "another.db")
    store = store_at(path)
    catalog = Catalog()
    store.write(loaded(catalog, "r1", "q1"))  # (the first write checks, and arms the watch)
    stats: list[str] = []
    real_stat = os.stat

    def counted(name: Any, *args: Any, **options: Any) -> os.stat_result:
        stats.append(os.fspath(name))
        return real_stat(name, *args, **options)

    monkeypatch.setattr(os, "stat", counted)
    for n in range(20):
        catalog.add_consumer("r1", f"q{n + 2}", "C")
        store.write(catalog.drain_changes())
    monkeypatch.undo()

    assert [] == [name for name in stats if name.startswith(str(path))]
    assert 21 == len(consumers_on_disk(path)["r1"])


@pytest.mark.skipif(PLATFORM.name != "linux", reason="inotify tells; elsewhere it stats")
def test_a_store_whose_watch_cannot_watch_yet_stats_without_asking_it(
    tmp_path: Path, store_at: Callable[..., SqliteStore], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A process manager's one store: its watch cannot watch until a second store makes the
    process's inotify instance (`armable`); each commit stats, asking the watch nothing
    (issue 71 item 5: two calls a commit, each answering `False`), and still finds its file
    deleted."""
    path = tmp_path / "p.db"
    store = store_at(path)
    watch = store._file._watch
    assert watch is not None
    asked: list[str] = []
    monkeypatch.setattr(watch, "armable", False)
    monkeypatch.setattr(watch, "quiet", lambda: asked.append("quiet") or False)
    monkeypatch.setattr(watch, "arm", lambda paths: asked.append("arm") or False)
    catalog = Catalog()
    store.write(loaded(catalog, "r1", "q1"))
    delete_file(path)

    catalog.add_consumer("r1", "q2", "C")
    store.write(catalog.drain_changes())

    assert ([], {"r1": ["q1", "q2"]}) == (asked, consumers_on_disk(path))


# -- 8. a full disk: CatalogWriteError, and nothing is lost ------------------------------------


def test_a_write_to_a_full_disk_raises_catalog_write_error_naming_the_file_and_enospc(
    disk: Path, store_at: Callable[..., SqliteStore]
) -> None:
    path = disk / "p.db"
    store = store_at(path)
    catalog = Catalog()
    store.write(loaded(catalog, "r1", "q1"))
    fill(disk)

    with pytest.raises(rr.CatalogWriteError) as raised:
        store.write(loaded(catalog, "r2", "q2", size=200_000))

    error = raised.value
    assert (str(path), errno.ENOSPC, True, True) == (
        error.path,
        error.errno,
        "ENOSPC" in str(error),
        str(path) in str(error),
    )
    assert {"r1": ["q1"]} == consumers_on_disk(path)  # what was written stays readable


def test_a_write_a_full_disk_refused_is_written_by_a_retry_once_there_is_room(
    disk: Path, store_at: Callable[..., SqliteStore]
) -> None:
    path = disk / "p.db"
    store = store_at(path)
    saver = Saver(store, rr.RegistrarConfig(name="P", backup_path=path, save_on_modify=True))
    catalog = Catalog()
    saver.changed(loaded(catalog, "r1", "q1"))
    filler = fill(disk)
    with pytest.raises(rr.CatalogWriteError, match="ENOSPC"):
        saver.changed(loaded(catalog, "r2", "q2", size=200_000))
    failed = (saver.failure is not None, saver.pending, saver.retry())

    filler.unlink()
    retried = saver.retry()

    assert ((True, True, False), True) == (failed, retried)
    assert (None, False) == (saver.failure, saver.pending)
    assert {"r1": ["q1"], "r2": ["q2"]} == consumers_on_disk(path)


def test_changes_made_while_the_disk_is_full_are_written_with_the_next_change_that_fits(
    disk: Path, store_at: Callable[..., SqliteStore]
) -> None:
    path = disk / "p.db"
    store = store_at(path)
    saver = Saver(store, rr.RegistrarConfig(name="P", backup_path=path, save_on_modify=True))
    catalog = Catalog()
    saver.changed(loaded(catalog, "r1", "q1"))
    filler = fill(disk)
    with pytest.raises(rr.CatalogWriteError):
        saver.changed(loaded(catalog, "r2", "q2", size=200_000))
    filler.unlink()

    catalog.release("q1")
    saver.changed(catalog.drain_changes())

    assert (None, {"r1": [], "r2": ["q2"]}) == (saver.failure, consumers_on_disk(path))


def test_an_interval_flush_on_a_full_disk_keeps_its_changes_for_the_next_flush(
    disk: Path, store_at: Callable[..., SqliteStore]
) -> None:
    path = disk / "p.db"
    store = store_at(path)
    saver = Saver(store, rr.RegistrarConfig(name="P", backup_path=path, save_interval=60.0))
    catalog = Catalog()
    saver.changed(loaded(catalog, "r1", "q1", size=200_000))
    filler = fill(disk)
    with pytest.raises(rr.CatalogWriteError, match="ENOSPC"):
        saver.flush()
    filler.unlink()

    saver.flush()

    assert (None, {"r1": ["q1"]}) == (saver.failure, consumers_on_disk(path))


def test_a_deleted_backup_that_a_full_disk_keeps_from_being_written_again_is_kept_for_later(
    disk: Path, store_at: Callable[..., SqliteStore]
) -> None:
    path = disk / "p.db"
    store = store_at(path)
    catalog = Catalog()
    store.write(loaded(catalog, "r1", "q1", size=200_000))
    delete_all(path)  # (its pages stay allocated while the store has it open)
    filler = fill(disk)
    catalog.add_consumer("r1", "q2", "C")
    changes = catalog.drain_changes()
    with pytest.raises(rr.CatalogWriteError, match="ENOSPC"):
        store.write(changes)
    filler.unlink()

    store.write(changes)

    assert {"r1": ["q1", "q2"]} == consumers_on_disk(path)


def test_catalog_write_error_pickles_with_its_attributes() -> None:
    error = rr.CatalogWriteError("state/p.db", "ENOSPC (No space left on device)", errno.ENOSPC)

    copy = pickle.loads(pickle.dumps(error))

    assert (type(error), error.args, error.path, error.cause, error.errno) == (
        type(copy),
        copy.args,
        copy.path,
        copy.cause,
        copy.errno,
    )


# -- one registrar a backup, whatever name it is given (issue 51, finding 3) ---------------------


def symlink(target: Path, name: Path) -> str:
    """Make `name` a symbolic link to `target`; the refusal names the file it resolves to."""
    name.symlink_to(target)
    return f"(the file {str(target)!r})"


def hard_link(target: Path, name: Path) -> str:
    """Make `name` a hard link to `target`; the refusal says the file is open by another
    name (which name, the kernel does not say)."""
    os.link(target, name)
    return "under another name"


other_names = pytest.mark.parametrize("make_name", [symlink, hard_link], ids=lambda f: f.__name__)
"""Another name of a running registrar's backup: a symbolic link, or a hard link."""

HOLDER = textwrap.dedent(
    """
    import sys
    import rr_actors as rr

    config = rr.RegistrarConfig(name=sys.argv[2], backup_path=sys.argv[1])
    registrar = rr.ResourceRegistrar.start(config)
    print("ready", flush=True)
    sys.stdin.read()  # (until the test closes it)
    registrar.stop()
    """
)
"""Another program: a registrar on the given backup, until its stdin closes."""


@contextlib.contextmanager
def holder(path: Path) -> Iterator[subprocess.Popen[str]]:
    """Run `HOLDER` on `path` in its own process until its registrar serves; end it after."""
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(path), unique("holder")],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        readable, _, _ = selecting.select([proc.stdout], [], [], 60.0)
        assert [proc.stdout] == readable
        assert "ready" == proc.stdout.readline().strip()
        yield proc
    finally:
        proc.kill()
        proc.communicate(timeout=10.0)


def refusal(path: Path) -> str:
    """The `ConfigError` a registrar started on `path` gets (the test fails without one)."""
    config = rr.RegistrarConfig(name=unique("second"), backup_path=path)
    with pytest.raises(rr.ConfigError) as refused:
        rr.ResourceRegistrar.start(config).stop()
    return str(refused.value)


@other_names
def test_a_registrar_on_another_name_of_a_running_registrars_backup_is_refused(
    tmp_path: Path, make_name: Callable[[Path, Path], str]
) -> None:
    """In one process: the second registrar is refused (`ConfigError` naming the name it was
    given, the file that is, and this pid) and the first goes on writing its own rows."""
    path, other = tmp_path / "p.db", tmp_path / "other.db"
    with rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=unique("first"), backup_path=path)
    ) as first:
        first.register_server("leaf", load=lambda r: r, unload=noop_unload)
        held = first.call(first.name, "leaf", "before")
        names_it = make_name(path, other)

        message = refusal(other)

        first.unload(held.id)
        first.call(first.name, "leaf", "after")  # (its file is still its alone)

    assert (True, True, True) == (
        repr(str(other)) in message,
        names_it in message,
        f"(pid {os.getpid()})" in message,
    )


@other_names
def test_a_registrar_on_another_name_of_a_backup_another_process_runs_is_refused(
    tmp_path: Path, make_name: Callable[[Path, Path], str]
) -> None:
    """Across processes: the refusal names the process that has the backup open."""
    path, other = tmp_path / "p.db", tmp_path / "other.db"
    with holder(path) as running:
        names_it = make_name(path, other)

        message = refusal(other)

    assert (True, True, True) == (
        repr(str(other)) in message,
        names_it in message,
        f"(pid {running.pid})" in message,
    )


@other_names
def test_another_name_of_a_backup_is_free_once_its_registrar_stopped(
    tmp_path: Path, make_name: Callable[[Path, Path], str]
) -> None:
    path, other = tmp_path / "p.db", tmp_path / "other.db"
    first = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=unique("first"), backup_path=path))
    first.stop()
    make_name(path, other)

    second = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=unique("b"), backup_path=other))
    second.stop()


# -- durability="power": a file made or put in place is synced, then its name ---------------


@pytest.fixture
def file_syncs(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, str]]:
    """Every `fdatasync`, `fsync` (the name of the file synced), `link` and `replace` (the
    new name) Python makes during the test, in order (SQLite's own are not seen)."""
    done: list[tuple[str, str]] = []
    for call in ("fdatasync", "fsync"):
        real = getattr(os, call)

        def synced(fd: int, real: Callable[[int], None] = real, call: str = call) -> None:
            done.append((call, os.readlink(f"/proc/self/fd/{fd}")))
            real(fd)

        monkeypatch.setattr(os, call, synced)
    for call in ("link", "replace"):
        real_move = getattr(os, call)

        def moved(src: Any, dst: Any, real: Any = real_move, call: str = call) -> None:
            real(src, dst)
            done.append((call, os.fspath(dst)))

        monkeypatch.setattr(os, call, moved)
    return done


@pytest.mark.parametrize("durability", ["process", "power"])
def test_a_new_backup_is_synced_then_linked_then_its_directory_synced_only_with_power(
    tmp_path: Path, file_syncs: list[tuple[str, str]], durability: Any
) -> None:
    path = tmp_path / "p.db"
    SqliteStore.open(path, durability=durability).close(erase=False)

    made = [(call, Path(name).name.split(".")[-1]) for call, name in file_syncs]
    expected = [("fdatasync", "creating"), ("link", "db"), ("fsync", tmp_path.name)]
    assert (expected if durability == "power" else [("link", "db")]) == made


def test_a_backup_deleted_under_a_power_registrar_is_put_back_synced_then_named(
    tmp_path: Path, file_syncs: list[tuple[str, str]]
) -> None:
    path = tmp_path / "p.db"
    store = SqliteStore.open(path, durability="power")
    catalog = Catalog()
    try:
        store.load()
        for rid in ("r1", "r2"):
            catalog.begin_load(rid, "leaf", {"k": rid})
            if rid == "r2":  # (the file gone since the last commit)
                path.unlink()
                file_syncs.clear()
            store.write(catalog.drain_changes())
    finally:
        store.close(erase=False)

    at = [call for call, _ in file_syncs].index("replace")
    assert (("fdatasync", "rewriting"), ("replace", str(path)), ("fsync", str(tmp_path))) == (
        (file_syncs[at - 1][0], file_syncs[at - 1][1].split(".")[-1]),
        file_syncs[at],
        file_syncs[at + 1],
    )


# -- a fresh backup: made whole or not at all, at what SQLite costs ---------------------------


def test_a_new_backup_is_the_empty_image_written_with_no_sqlite_connection_of_its_own(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A fresh backup's file is `schema.empty_image()` written once under its temporary
    name (SQLite builds nothing per file): opening it makes one connection, the store's."""
    opened: list[str] = []
    real = sqlite3.connect

    def connect(name: Any, *args: Any, **kwargs: Any) -> sqlite3.Connection:
        opened.append(Path(name).name)
        return real(name, *args, **kwargs)

    monkeypatch.setattr(sqlite3, "connect", connect)
    path = tmp_path / "p.db"
    store = SqliteStore.open(path)
    try:
        written = path.read_bytes()
    finally:
        store.close(erase=False)
    assert (["p.db"], True) == (opened, written == schema.empty_image())


KILLED_AT = textwrap.dedent(
    """
    import os, signal, sys
    from pathlib import Path
    from rr_actors._store import files
    from rr_actors._store.saver import SqliteStore

    path, durability, point = Path(sys.argv[1]), sys.argv[2], sys.argv[3]

    def die():
        os.kill(os.getpid(), signal.SIGKILL)

    class HalfWritten:  # the new file, killed half way through its one write
        def __init__(self, fd, mode):
            self.fd = fd
        def __enter__(self):
            return self
        def __exit__(self, *exc):
            os.close(self.fd)
        def write(self, data):
            os.write(self.fd, data[: len(data) // 2])
            die()

    real_fchmod, real_link, real_sync = os.fchmod, os.link, files.sync
    def fchmod(fd, mode):
        real_fchmod(fd, mode)
        if point == "created":
            die()

    def link(source, target):
        if point == "before link":
            die()
        real_link(source, target)
        if point == "after link":
            die()

    def sync(name, directory=False):
        real_sync(name, directory=directory)
        if point == "after sync" and directory:
            die()

    os.fchmod, os.link, files.sync = fchmod, link, sync
    if point == "half written":
        files.open = HalfWritten
    SqliteStore.open(path, durability=durability).close(erase=False)
    """
)


@pytest.mark.timeout(600)
@pytest.mark.parametrize("durability", ["process", "power"])
def test_a_process_killed_at_any_point_of_making_a_backup_leaves_none_or_a_whole_empty_one(
    tmp_path: Path, durability: str
) -> None:
    """SIGKILLed once the new file exists, half way through writing it, before and after
    its name is made, after its directory is synced: the path then holds no file, or a
    catalog that opens empty, and the next start makes or opens it."""

    def killed_at(path: Path, point: str) -> subprocess.CompletedProcess[str]:
        command = [sys.executable, "-c", KILLED_AT, str(path), durability, point]
        return subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)

    points = ["created", "half written", "before link", "after link"]
    points += ["after sync"] if durability == "power" else []
    found = {}
    for number, point in enumerate(points):
        path = tmp_path / f"p{number}.db"
        run = killed_at(path, point)
        existed = path.exists()
        store = SqliteStore.open(path, durability=durability)  # (raises if not whole)
        try:
            restored = store.restore()
        finally:
            store.close(erase=False)
        rows = None if restored is None else (len(restored.resources), len(restored.clients))
        found[point] = (run.returncode, existed, rows)

    made = ("after link", "after sync")  # (the name made: the file is whole)
    expected = {
        point: (-9, True, (0, 0)) if point in made else (-9, False, None) for point in points
    }
    assert expected == found


needs_root = pytest.mark.skipif(
    os.geteuid() != 0, reason="a power cut is replayed on a loop device and mounts (root)"
)


@needs_root
@pytest.mark.timeout(600)
@pytest.mark.parametrize("durability", ["process", "power"])
def test_a_power_cut_while_a_backup_is_made_and_first_written_leaves_none_or_a_whole_one(
    tmp_path: Path, durability: str
) -> None:
    """A backup made, written once (its log begins: SQLite syncs its header) and closed,
    on ext4 over a logged disk; replayed to each flush from the start: the path holds no
    file, or one that reads (never an empty or half-written one), and the last holds it."""
    with logged_disk(tmp_path) as disk:
        state = disk.mounted / "state"
        state.mkdir()
        disk.mark("start")
        store = SqliteStore.open(state / "p.db", durability=durability)  # type: ignore[arg-type]
        try:
            store.restore()
            catalog = Catalog()
            catalog.begin_load("r1", "leaf", {"k": 1})
            store.write(catalog.drain_changes())
        finally:
            store.close(erase=False)
        os.sync()
        log = disk.dump(tmp_path / "log.pickle")
    states = []
    for at, image, _ in flush_points(log, disk.size, "start"):
        with mounted_image(image) as mounted:
            backup = mounted / "state" / "p.db"
            try:
                states.append((at, "whole" if read_backup(backup) else "?"))
            except rr.ConfigError:  # (no file there)
                states.append((at, "none"))
            except rr.CatalogCorruptError as exc:
                states.append((at, exc.cause))

    assert (True, "whole") == (
        all(what in ("none", "whole") for _, what in states),
        states[-1][1],
    ), states


# -- the commits counted beside the WAL ------------------------------------------------------------
# Commits counted outside the WAL (`CommitCount`, `lost_commits`): a WAL cut short loses
# its newest commits, and the restore says so (issue 21).
#
# Real manager processes killed with SIGKILL, their real `-wal` files cut at a frame
# boundary right after a commit (the cut SQLite cannot see: it replays what is left and
# drops the rest without a word).
#
# - The restarted registrar logs a WARNING naming the file and how many commits are lost.
# - A consumer whose ids were all in the lost commits is told `FATAL` for each (rule 20).
pytestmark = [
    pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals"),
    pytest.mark.usefixtures("by_value"),  # (tests/conftest.py)
]


def serve_echo(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("leaf", load=lambda r: {"for": r}, unload=lambda _r, _s: None)


def durable(prefix: str, tmp_path: Path) -> rr.RegistrarConfig:
    name = f"{prefix}-{uuid.uuid4().hex[:8]}"
    return rr.RegistrarConfig(name, backup_path=tmp_path / f"{name}.db", save_on_modify=True)


def commit_ends(wal: Path) -> tuple[bytes, list[int]]:
    """The salts of `wal`'s current generation and the end offset of each commit frame."""
    data = wal.read_bytes()
    page_size = struct.unpack(">I", data[8:12])[0]
    salts = data[16:24]
    ends, offset = [], 32
    while offset + 24 + page_size <= len(data) and data[offset + 8 : offset + 16] == salts:
        committed = struct.unpack(">I", data[offset + 4 : offset + 8])[0]  # db size, or 0
        offset += 24 + page_size
        if committed:
            ends.append(offset)
    return salts, ends


def cut(wal: Path, at: int) -> None:
    with open(wal, "r+b") as file:
        file.truncate(at)
        os.fsync(file.fileno())


@pytest.mark.parametrize(
    "replayed",
    [
        pytest.param(False, id="a wal cut short"),
        pytest.param(True, id="a cut after a restart that replayed the log is still seen"),
    ],
)
def test_a_wal_cut_short_is_reported_at_restore_naming_the_file_and_the_commits_lost(
    managers: Callable[..., RemoteRegistrar],
    tmp_path: Path,
    started: list[rr.ResourceRegistrar],
    caplog: pytest.LogCaptureFixture,
    replayed: bool,
) -> None:
    config = durable("provider", tmp_path)
    provider = managers(config, serve_echo)
    for n in range(50):
        provider.call(config.name, "leaf", n, timeout=10)
    provider.kill()
    wal = Path(f"{config.backup_path}-wal")
    _, ends = commit_ends(wal)
    assert len(ends) > 60
    at, lost = ends[-61], 60  # the last 60 commits are gone
    if replayed:
        again = managers(config, serve_echo)  # replays the log, appends to it
        for n in range(50, 55):
            again.call(config.name, "leaf", n, timeout=10)
        again.kill()
        at, lost = ends[-1], len(commit_ends(wal)[1]) - len(ends)  # the second run's
    cut(wal, at)

    caplog.set_level(logging.WARNING, logger="rr_actors")
    started.append(rr.ResourceRegistrar.start(config, setup=serve_echo))

    warnings = [r.getMessage() for r in caplog.records if "commits are lost" in r.getMessage()]
    assert 1 == len(warnings)
    assert str(config.backup_path) in warnings[0]
    assert f": {lost} acknowledged commits are lost (" in warnings[0]


def test_a_consumer_whose_every_id_was_in_the_lost_commits_is_told_fatal(
    managers: Callable[..., RemoteRegistrar],
    tmp_path: Path,
    process_helpers: SharedObjects,
    eventually: Callable[..., bool],
) -> None:
    heard = process_helpers.list()
    config = durable("provider", tmp_path)
    provider = managers(config, serve_echo)
    for n in range(5):
        provider.call(config.name, "leaf", n, timeout=10)  # ids of the provider itself
    wal = Path(f"{config.backup_path}-wal")
    salts, before = commit_ends(wal)
    consumer = managers(durable("consumer", tmp_path), None)

    def note(query: rr.Query, update: rr.StatusUpdate) -> None:
        heard.append((query.id, update.status))

    held = [
        consumer.call(config.name, "leaf", f"device-{n}", on_status=note, timeout=10).id
        for n in range(3)
    ]
    provider.kill()
    assert salts == commit_ends(wal)[0]  # (no checkpoint restarted the log meanwhile)
    cut(wal, before[-1])  # every commit since the consumer's first call is gone
    restarted = managers(config, serve_echo)

    assert eventually(lambda: len(heard) == 3, timeout=10)
    assert sorted((q, rr.Status.FATAL) for q in held) == sorted(heard)
    assert [] == consumer.client_queries()
    assert 5 == len(restarted.server_queries("leaf"))


def test_a_wal_left_whole_by_a_kill_or_a_clean_stop_reports_nothing(
    managers: Callable[..., RemoteRegistrar],
    tmp_path: Path,
    started: list[rr.ResourceRegistrar],
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, logger="rr_actors")
    config = durable("provider", tmp_path)
    provider = managers(config, serve_echo)
    for n in range(20):
        provider.call(config.name, "leaf", n, timeout=10)
    provider.kill()
    again = managers(config, serve_echo)  # replays the log, appends to it
    for n in range(20, 30):
        again.call(config.name, "leaf", n, timeout=10)
    again.kill()
    restarted = rr.ResourceRegistrar.start(config, setup=serve_echo)
    assert 30 == len(restarted.server_queries("leaf"))
    restarted.stop()  # (it releases what it held of itself)
    started.append(rr.ResourceRegistrar.start(config, setup=serve_echo))

    assert [] == [r.getMessage() for r in caplog.records if "commits" in r.getMessage()]


def test_a_log_another_program_checkpointed_and_removed_is_not_reported(
    managers: Callable[..., RemoteRegistrar],
    tmp_path: Path,
    started: list[rr.ResourceRegistrar],
    caplog: pytest.LogCaptureFixture,
) -> None:
    config = durable("provider", tmp_path)
    provider = managers(config, serve_echo)
    for n in range(20):
        provider.call(config.name, "leaf", n, timeout=10)
    provider.kill()
    with contextlib.closing(sqlite3.connect(str(config.backup_path))) as db:
        db.execute("SELECT count(*) FROM resources").fetchone()  # closing checkpoints
    assert not Path(f"{config.backup_path}-wal").exists()

    caplog.set_level(logging.WARNING, logger="rr_actors")
    restarted = rr.ResourceRegistrar.start(config, setup=serve_echo)
    started.append(restarted)

    assert [] == [r.getMessage() for r in caplog.records if "commits" in r.getMessage()]
    assert 20 == len(restarted.server_queries("leaf"))


def test_a_commit_count_dropped_without_close_closes_its_files(tmp_path: Path) -> None:
    """A registrar killed in a simulation drops its backup's commit count without `close`
    (a killed process's files are closed by its kernel, a simulated process's are not):
    the count closes what it opened once it is dropped. (A sweep of `simchain` kept some
    12 descriptors a seed open for good: past the usual limit of 1,024 within 100 seeds.)"""
    file = tmp_path / "b.db"
    db = sqlite3.connect(file, isolation_level=None)
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("CREATE TABLE t (x)")

    def opened(suffix: str) -> int:
        links = []
        for fd in os.listdir("/proc/self/fd"):
            with contextlib.suppress(OSError):  # (the listing's own descriptor, closed)
                links.append(os.readlink(f"/proc/self/fd/{fd}"))
        return links.count(f"{file}{suffix}")

    count = CommitCount(file)
    db.execute("INSERT INTO t VALUES (1)")
    count.committed()
    assert (1, 2) == (opened("-commits"), opened("-wal"))  # (the count's, and SQLite's own)

    del count
    gc.collect()

    assert (0, 1) == (opened("-commits"), opened("-wal"))
    db.close()


def test_the_count_follows_the_log_through_its_restarts_reading_its_salts_from_memory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The salts come from SQLite's shared memory (`-shm`, mapped): a commit reads nothing
    from the log but at a new generation, and the count is still each generation's."""
    file = tmp_path / "b.db"
    db = sqlite3.connect(file, isolation_level=None)
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("CREATE TABLE t (x)")
    count = CommitCount(file)
    reads = []
    real_pread = os.pread

    def pread(fd: int, size: int, offset: int) -> bytes:
        reads.append(offset)
        return real_pread(fd, size, offset)

    monkeypatch.setattr(os, "pread", pread)
    for n in range(300):
        db.execute("INSERT INTO t VALUES (?)", (b"x" * 2000,))
        count.committed()
        if n % 50 == 49:  # (all of it copied into the file: the next commit restarts the log)
            db.execute("PRAGMA wal_checkpoint(PASSIVE)")
    monkeypatch.undo()
    salts, ends = commit_ends(Path(f"{file}-wal"))
    record = struct.unpack(">8sQ", Path(f"{file}-commits").read_bytes()[:16])
    count.close()
    db.close()

    assert 50 == len(ends)  # (the commits since the last restart)
    assert (salts, 50) == record
    assert len([offset for offset in reads if offset == 0]) == 6  # one a generation


@pytest.mark.parametrize("synced", [False, True])
def test_a_synced_count_is_on_the_disk_with_its_name_when_committed_returns(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, synced: bool
) -> None:
    """`durability="power"`: each count is `fdatasync`ed, and the directory is synced once
    the count's file is made; without, nothing is synced."""
    file = tmp_path / "b.db"
    db = sqlite3.connect(file, isolation_level=None)
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("CREATE TABLE t (x)")
    count = CommitCount(file, synced=synced)
    done = []
    for call in ("fdatasync", "fsync"):
        real = getattr(os, call)

        def recorded(fd: int, real: Callable[[int], None] = real, call: str = call) -> None:
            done.append((call, os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))))
            real(fd)

        monkeypatch.setattr(os, call, recorded)
    for n in range(3):
        db.execute("INSERT INTO t VALUES (?)", (n,))
        count.committed()
    monkeypatch.undo()
    count.close()
    db.close()

    made = [("fdatasync", "b.db-commits"), ("fsync", tmp_path.name)]
    expected = [*made, ("fdatasync", "b.db-commits"), ("fdatasync", "b.db-commits")]
    assert (expected if synced else []) == done
