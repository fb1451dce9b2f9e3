"""The backup at real limits: names too long, a file deleted under a running registrar, a
full disk, who may read the files (issue 16: 6, 7, 8 and the file modes).

Full disks are real: a small tmpfs mounted for the test (`small_disk`; CI runs as root),
filled with a file until `ENOSPC`. Crashes are real too: a manager process is SIGKILLed
and its registrar restarted on the same backup.
"""

from __future__ import annotations

import errno
import logging
import os
import pickle
import stat
import sys
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr
from rr_actors._catalog import Catalog, Changes
from rr_actors._store import Saver, SqliteStore, quarantine_backup, read_backup
from rr_actors.testing import RemoteRegistrar, System
from tests.support.small_disk import fill, mounted


def unique(prefix: str) -> str:
    return f"{prefix}-{uuid.uuid4().hex[:8]}"


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


def noop_unload(_request: Any, _response: Any) -> None:
    return None


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
