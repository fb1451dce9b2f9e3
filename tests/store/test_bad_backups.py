"""Bad backups: files that are not ours, damaged, unreadable, read-only, or with rows that
cannot be right, each a clear error naming the file (rule 15; `_store/files.py`, `restore.py`).
"""

from __future__ import annotations

import os
import sqlite3
from collections.abc import Callable
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors._store.files import quarantine_backup, read_backup
from rr_actors._store.sqlite import SqliteStore
from tests.support.durable_pair import noop_unload, start
from tests.support.persisting import (
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
from tests.support.small_disk import mounted, remount_read_only


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
