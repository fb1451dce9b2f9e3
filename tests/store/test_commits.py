"""Commits counted outside the WAL (`rr_actors._store.commits`): a WAL cut short loses its
newest commits, and the restore says so (issue 21).

Real manager processes killed with SIGKILL, their real `-wal` files cut at a frame
boundary right after a commit (the cut SQLite cannot see: it replays what is left and
drops the rest without a word).

- The restarted registrar logs a WARNING naming the file and how many commits are lost.
- A consumer whose ids were all in the lost commits is told `FATAL` for each (rule 20).
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import sqlite3
import struct
import sys
import uuid
from collections.abc import Callable
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors._store.commits import CommitCount
from rr_actors.testing import RemoteRegistrar, SharedObjects

pytestmark = [
    pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals"),
    pytest.mark.usefixtures("by_value"),  # (tests/conftest.py)
]


def serve_leaf(registrar: rr.ResourceRegistrar) -> None:
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


def test_a_wal_cut_short_is_reported_at_restore_naming_the_file_and_the_commits_lost(
    managers: Callable[..., RemoteRegistrar],
    tmp_path: Path,
    started: list[rr.ResourceRegistrar],
    caplog: pytest.LogCaptureFixture,
) -> None:
    config = durable("provider", tmp_path)
    provider = managers(config, serve_leaf)
    for n in range(50):
        provider.call(config.name, "leaf", n, timeout=10)
    provider.kill()
    wal = Path(f"{config.backup_path}-wal")
    _, ends = commit_ends(wal)
    assert len(ends) > 60
    cut(wal, ends[-61])  # the last 60 commits are gone

    caplog.set_level(logging.WARNING, logger="rr_actors")
    restarted = rr.ResourceRegistrar.start(config, setup=serve_leaf)
    started.append(restarted)

    warnings = [r.getMessage() for r in caplog.records if "commits are lost" in r.getMessage()]
    assert 1 == len(warnings)
    assert str(config.backup_path) in warnings[0]
    assert ": 60 acknowledged commits are lost" in warnings[0]


def test_a_consumer_whose_every_id_was_in_the_lost_commits_is_told_fatal(
    managers: Callable[..., RemoteRegistrar],
    tmp_path: Path,
    process_helpers: SharedObjects,
    eventually: Callable[..., bool],
) -> None:
    heard = process_helpers.list()
    config = durable("provider", tmp_path)
    provider = managers(config, serve_leaf)
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
    restarted = managers(config, serve_leaf)

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
    provider = managers(config, serve_leaf)
    for n in range(20):
        provider.call(config.name, "leaf", n, timeout=10)
    provider.kill()
    again = managers(config, serve_leaf)  # replays the log, appends to it
    for n in range(20, 30):
        again.call(config.name, "leaf", n, timeout=10)
    again.kill()
    restarted = rr.ResourceRegistrar.start(config, setup=serve_leaf)
    assert 30 == len(restarted.server_queries("leaf"))
    restarted.stop()  # (it releases what it held of itself)
    started.append(rr.ResourceRegistrar.start(config, setup=serve_leaf))

    assert [] == [r.getMessage() for r in caplog.records if "commits" in r.getMessage()]


def test_a_cut_after_a_restart_that_replayed_the_log_is_still_seen(
    managers: Callable[..., RemoteRegistrar],
    tmp_path: Path,
    started: list[rr.ResourceRegistrar],
    caplog: pytest.LogCaptureFixture,
) -> None:
    config = durable("provider", tmp_path)
    provider = managers(config, serve_leaf)
    for n in range(20):
        provider.call(config.name, "leaf", n, timeout=10)
    provider.kill()
    wal = Path(f"{config.backup_path}-wal")
    _, replayed = commit_ends(wal)
    again = managers(config, serve_leaf)
    for n in range(20, 25):
        again.call(config.name, "leaf", n, timeout=10)
    again.kill()
    _, ends = commit_ends(wal)
    cut(wal, replayed[-1])  # what the second run committed is gone

    caplog.set_level(logging.WARNING, logger="rr_actors")
    started.append(rr.ResourceRegistrar.start(config, setup=serve_leaf))

    lost = len(ends) - len(replayed)
    assert [f"{lost} acknowledged commits are lost"] == [
        m[m.index(f"{lost} ack") :].split(" (")[0]
        for m in (r.getMessage() for r in caplog.records)
        if "commits are lost" in m
    ]


def test_a_log_another_program_checkpointed_and_removed_is_not_reported(
    managers: Callable[..., RemoteRegistrar],
    tmp_path: Path,
    started: list[rr.ResourceRegistrar],
    caplog: pytest.LogCaptureFixture,
) -> None:
    config = durable("provider", tmp_path)
    provider = managers(config, serve_leaf)
    for n in range(20):
        provider.call(config.name, "leaf", n, timeout=10)
    provider.kill()
    with contextlib.closing(sqlite3.connect(str(config.backup_path))) as db:
        db.execute("SELECT count(*) FROM resources").fetchone()  # closing checkpoints
    assert not Path(f"{config.backup_path}-wal").exists()

    caplog.set_level(logging.WARNING, logger="rr_actors")
    restarted = rr.ResourceRegistrar.start(config, setup=serve_leaf)
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
