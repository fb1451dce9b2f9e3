"""Commits counted outside the WAL, so that a restore can tell when the WAL lost some.

```
 each commit --> the log's salts (which generation of the log this is), as SQLite's
                 shared memory (`-shm`) holds them, mapped: no system call
             --> `<file>-commits` := (salts, commits of that generation)    (8 + 8 bytes)
 open after a crash --> count the -wal's complete commit frames of those salts: fewer?
             --> WARNING naming the file and how many commits are gone
```

Why ("A truncated WAL loses its newest commits"): docs/explanation/failure-semantics.md.
The count (synced after the log with `durability="power"`; else not: a count lost only
hides a loss, never invents one) restarts with
each generation of the log (new salts), read from the `-shm` SQLite maps (a memory read,
else the log's header). The check reads frame headers only: it detects a log cut short,
not one damaged in its middle; a database file written after the last count reports
nothing.
"""

from __future__ import annotations

import contextlib
import logging
import mmap
import os
import struct
import weakref
from pathlib import Path

from rr_actors._store.files import sync

logger = logging.getLogger("rr_actors")

SUFFIX = "-commits"  # the count's file, beside the backup (`erm.db-commits`)

_RECORD = struct.Struct(">8sQ")  # the log's salts, the commits of that generation
_WAL_HEADER = 32
_FRAME_HEADER = 24
_SHM_MAPPED = 4096  # (SQLite makes its -shm 32 KiB at least)
_SHM_SALTS = slice(32, 40)  # the salts in the shared memory's first header (`WalIndexHdr`)


class CommitCount:
    """Counts the commits of the current WAL generation of backup `file` (the writer's
    thread; never raises; not `kept`: a simulation's, counts nothing; `synced`: on the
    disk, with its name, when `committed` returns)."""

    def __init__(self, file: Path, *, kept: bool = True, synced: bool = False) -> None:
        self.kept = kept
        self.synced = synced
        self.path = f"{file}{SUFFIX}"
        self._wal = f"{file}-wal"
        self._shm_name = f"{file}-shm"
        self._salts = b""
        self._count = 0
        self._fds: dict[str, int] = {}  # "count", "wal": the files it keeps open
        self._shm: mmap.mmap | None = None  # the -shm's first page, read-only
        self._shm_tried = False
        weakref.finalize(self, _close_fds, self._fds)

    def committed(self) -> None:
        if not self.kept:
            return
        shm, count = self._shm, self._fds.get("count")
        if shm is not None and count is not None and shm[_SHM_SALTS] == self._salts:
            self._count += 1  # (most commits: the same generation of the log)
            try:
                os.pwrite(count, self._count.to_bytes(8, "big"), 8)
                self._sync(count)
            except OSError as exc:
                logger.debug("the commit count %s cannot be kept: %s", self.path, exc)
            return
        try:
            shm = shm if self._shm_tried else self._map_shm()
            if shm is not None and shm[_SHM_SALTS] == self._salts:
                self._count += 1
            else:
                wal = self._fds.get("wal")
                if wal is None:
                    wal = self._fds["wal"] = os.open(self._wal, os.O_RDONLY | os.O_CLOEXEC)
                header = os.pread(wal, _WAL_HEADER, 0)
                if len(header) < _WAL_HEADER:
                    return
                salts = header[16:24]
                if salts == self._salts:
                    self._count += 1
                else:  # the first commit of this store, or the log restarted: count them
                    self._salts, self._count = salts, _commit_frames(wal, header)
            created = "count" not in self._fds
            count = self._fds.get("count")
            if count is None:
                count = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
                self._fds["count"] = count
                os.fchmod(count, 0o600)  # (whatever the umask: like SQLite's side files)
            os.pwrite(count, _RECORD.pack(self._salts, self._count), 0)
            self._sync(count, created=created)
        except OSError as exc:
            logger.debug("the commit count %s cannot be kept: %s", self.path, exc)

    def _sync(self, count: int, *, created: bool = False) -> None:
        if self.synced:  # (after SQLite's commit, which synced the log first)
            os.fdatasync(count)
            if created:
                sync(self.path, directory=True)

    def _map_shm(self) -> mmap.mmap | None:
        self._shm_tried = True
        try:
            fd = os.open(self._shm_name, os.O_RDONLY | os.O_CLOEXEC)
        except OSError:
            return None
        try:
            if os.fstat(fd).st_size >= _SHM_MAPPED:  # (a page past its end: SIGBUS)
                self._shm = mmap.mmap(fd, _SHM_MAPPED, mmap.MAP_SHARED, mmap.PROT_READ)
        except (OSError, ValueError):
            self._shm = None
        finally:
            os.close(fd)  # (the mapping stays)
        return self._shm

    def _unmap_shm(self) -> None:
        shm, self._shm, self._shm_tried = self._shm, None, False
        if shm is not None:
            shm.close()

    def reopen(self) -> None:
        _close_fds(self._fds)
        self._unmap_shm()
        self._salts, self._count = b"", 0

    def close(self) -> None:
        _close_fds(self._fds)
        self._unmap_shm()
        with contextlib.suppress(OSError):
            os.unlink(self.path)


def _close_fds(fds: dict[str, int]) -> None:
    while fds:
        with contextlib.suppress(OSError):
            os.close(fds.popitem()[1])


def lost_commits(file: Path) -> tuple[int, str] | None:
    """How many counted commits the WAL of `file` no longer holds, and why; else `None`
    (before anything opens the file)."""
    try:
        record = Path(f"{file}{SUFFIX}").read_bytes()[: _RECORD.size]
        checkpointed = os.stat(file).st_mtime_ns > os.stat(f"{file}{SUFFIX}").st_mtime_ns
    except OSError:
        return None
    # (a checkpoint that wrote the file after the last count left it holding them)
    salts, counted = _RECORD.unpack(record) if len(record) == _RECORD.size else (b"", 0)
    if checkpointed or counted == 0:
        return None
    try:
        with open(f"{file}-wal", "rb") as wal:
            return _compare(wal.fileno(), salts, counted)
    except FileNotFoundError:
        return counted, f"its -wal file is missing; it held the last {counted} commits"
    except OSError as exc:
        logger.debug("the WAL of %s cannot be read: %s", file, exc)
        return None


def _compare(fd: int, salts: bytes, counted: int) -> tuple[int, str] | None:
    header = os.pread(fd, _WAL_HEADER, 0)
    if len(header) < _WAL_HEADER:
        return counted, f"its -wal file is cut short ({len(header)} bytes)"
    if header[16:24] != salts:
        return None  # another generation of the log than the one counted: cannot tell
    found = _commit_frames(fd, header, counted)
    if found >= counted:
        return None
    return counted - found, f"its -wal file holds {found} of the last {counted} commits"


def _commit_frames(fd: int, header: bytes, limit: int | None = None) -> int:
    salts = header[16:24]
    page_size = struct.unpack(">I", header[8:12])[0]
    size = os.fstat(fd).st_size
    frame = _FRAME_HEADER + page_size
    found = 0
    offset = _WAL_HEADER
    while offset + frame <= size and (limit is None or found < limit):
        head = os.pread(fd, _FRAME_HEADER, offset)
        if head[8:16] != salts:  # a frame of an earlier generation: the log ends here
            break
        if struct.unpack(">I", head[4:8])[0] != 0:  # a commit frame
            found += 1
        offset += frame
    return found
