"""Where a backup lives: the path's checks, the lock, creating, validating, opening and
replacing the file, and the count of its commits kept beside it.

```
 backup_path --check_location--> --claim: <real path>.lock and the file, one registrar a file-->
   (no file) --create: temporary name, linked into place-->
   --validate: header, read-only connection, schema--> --prepare: WAL, durability, migrate-->
   a writable connection (`SqliteStore`); for inspection, a read-only one (`inspected`)
 file deleted or replaced under the store (`moved`) --copy_aside, then put_in_place-->
   a new file at the path, the whole catalog in it
 quarantine_backup: claim, then rename the file and its companions aside (the one way
   to give one up; refused while a registrar has it open)
 each commit --> the log's salts, as SQLite's shared memory (`-shm`) holds them, mapped
   --> `<file>-commits` := (salts, commits of that generation)        (`CommitCount`)
 open after a crash --> count the -wal's complete commit frames of those salts: fewer?
   --> WARNING naming the file and how many commits are gone           (`lost_commits`)
```

A new file is linked into place complete; an existing one is validated read-only before
anything writes to it; every file is its owner's only (`FILE_MODE`). Why: "What the backup
survives" and "Who may see a backup", docs/explanation/failure-semantics.md, and
docs/how-to/persistence.md.

The commit count (synced after the log with `durability="power"`; else not: a count lost
only hides a loss, never invents one) restarts with each generation of the log (new
salts). The check reads frame headers only: it detects a log cut short ("A truncated WAL
loses its newest commits", failure-semantics.md), not one damaged in its middle; a
database file written after the last count reports nothing.
"""

from __future__ import annotations

import contextlib
import datetime
import errno as errno_names
import logging
import mmap
import os
import sqlite3
import struct
import weakref
from collections.abc import Callable, Iterator
from pathlib import Path

from rr_actors._core import runtime
from rr_actors._platform import PLATFORM, lockfile
from rr_actors._store import schema
from rr_actors._store.schema import as_corrupt
from rr_actors.errors import CatalogCorruptError, CatalogWriteError, ConfigError

logger = logging.getLogger("rr_actors")

_HEADER = b"SQLite format 3\x00"

SIDE_FILES = ("-wal", "-shm", "-journal")
LOCK_SUFFIX = ".lock"
SYNCHRONOUS = {"process": "NORMAL", "power": "FULL"}  # by `RegistrarConfig.durability`


_LONGEST_SIDE = max(len(suffix) for suffix in SIDE_FILES)

SQLITE_MAX_PATH = 512  # bytes, side files' suffixes included (its unix VFS's MAX_PATHNAME)


def check_location(path: Path) -> None:
    """Raise `ConfigError`, naming `path`, if it cannot hold a backup."""
    name = str(path)
    parent = path.parent
    try:
        parent_is_dir = parent.is_dir()
    except OSError as exc:  # a component too long, a loop of links, ...
        raise ConfigError(f"backup_path {name!r}: {exc.strerror}") from exc
    if not parent_is_dir:
        what = "is a file, not a directory" if parent.exists() else "does not exist"
        raise ConfigError(f"backup_path {name!r}: directory {str(parent)!r} {what}")
    problem = _length_problem(path)
    if problem is not None:
        raise ConfigError(f"backup_path {name!r}: {problem}")
    try:
        is_dir, exists = path.is_dir(), path.exists()
    except OSError as exc:
        raise ConfigError(f"backup_path {name!r}: {exc.strerror}") from exc
    if is_dir:
        raise ConfigError(f"backup_path {name!r} is a directory, not a file")
    if not exists and path.is_symlink():  # (nothing could be created at it, nor read)
        raise ConfigError(f"backup_path {name!r} is a symbolic link to nothing")
    if exists and not os.access(path, os.R_OK | os.W_OK):
        raise ConfigError(f"backup_path {name!r} is not readable and writable")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(
            f"backup_path {name!r}: directory {str(parent)!r} is not writable "
            f"(SQLite needs to create its -wal and -shm files there)"
        )


def _length_problem(path: Path) -> str | None:
    try:
        name_max = os.pathconf(path.parent, "PC_NAME_MAX")
    except (OSError, ValueError):
        name_max = 255
    length = len(os.fsencode(path.name))
    if length + _LONGEST_SIDE > name_max:
        return (
            f"the file name is {length} bytes long; this file system takes at most "
            f"{name_max - _LONGEST_SIDE} (SQLite adds '-journal', '-wal', '-shm')"
        )
    full = len(os.fsencode(os.path.abspath(path)))
    if full + _LONGEST_SIDE > SQLITE_MAX_PATH:
        return (
            f"the absolute path is {full} bytes long; SQLite opens at most "
            f"{SQLITE_MAX_PATH - _LONGEST_SIDE}"
        )
    return None


def connect(path: Path, *, read_only: bool) -> sqlite3.Connection:
    if read_only:
        uri = f"{path.resolve().as_uri()}?mode=ro"
        db = sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=False)
    else:
        db = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
    return runtime.hold(db)  # (a simulated process's death closes it: `runtime.hold`)


def _file_problem(path: Path) -> str | None:
    size = path.stat().st_size
    if size == 0:
        return "the file is empty (an rr_actors catalog is never empty)"
    with path.open("rb") as file:
        header = file.read(100)
    if not header.startswith(_HEADER):
        return f"not an SQLite database (starts with {header[:16]!r})"
    if len(header) < 100:
        return f"truncated: {size} bytes, shorter than an SQLite header"
    page_size = int.from_bytes(header[16:18], "big")
    page_size = 65536 if page_size == 1 else page_size
    pages = int.from_bytes(header[28:32], "big")
    change_counter, valid_for = header[24:28], header[92:96]
    if change_counter == valid_for and pages and pages * page_size > size and not _has_log(path):
        return f"truncated: {size} bytes, its header says {pages} pages of {page_size} bytes"
    return None


def _has_log(path: Path) -> bool:
    """Whether a non-empty WAL lies next to `path` (a checkpoint killed while it grew the
    file leaves it shorter than its header says, and the log completes it)."""
    try:
        return Path(f"{path}-wal").stat().st_size > 0
    except OSError:
        return False


FILE_MODE = 0o600  # every file the store creates (SQLite gives its side files the same)


def temporary_path(path: Path, purpose: str) -> Path:
    """A new name next to `path` for a file built before it is moved into place."""
    token = runtime.urandom(4).hex()
    named = path.with_name(f".{path.name}.{token}.{purpose}")
    if _length_problem(named) is None:
        return named
    return path.with_name(f".{token}.{purpose}")


def _private_file(path: Path) -> None:
    """Create an empty file at `path` that only its owner may read and write (`fchmod`:
    whatever the umask)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, FILE_MODE)
    try:
        os.fchmod(fd, FILE_MODE)
    finally:
        os.close(fd)


class BackupLock:
    """The locks that make one store the one registrar of a backup: `<real path>.lock`
    (one for every symbolic link) and the file itself (one for every hard link)."""

    def __init__(self, path: Path, real: Path, name_fd: int) -> None:
        self._path = path
        self._real = real
        self._name_fd: int | None = name_fd
        self._file_fd: int | None = None

    def hold_file(self) -> None:
        """Lock the file itself (it exists now); `ConfigError` if another registrar has it
        open under another name."""
        if self._file_fd is not None:
            return
        try:
            self._file_fd = lockfile.claim_file(self._real)
        except lockfile.HeldError as held:
            raise _in_use(self._path, self._real, held.holder, " (under another name)") from None
        except OSError as exc:
            raise ConfigError(f"backup_path {str(self._path)!r} cannot be locked: {exc}") from exc

    def file_replaced(self) -> None:
        """Lock the new file at the path instead (`SqliteStore._keep_in_place`)."""
        file_fd, self._file_fd = self._file_fd, None
        if file_fd is not None:
            lockfile.release_file(file_fd)
        with contextlib.suppress(ConfigError):  # (a file just made: nobody else has it)
            self.hold_file()

    def release(self) -> None:
        file_fd, self._file_fd = self._file_fd, None
        name_fd, self._name_fd = self._name_fd, None
        if file_fd is not None:
            lockfile.release_file(file_fd)
        if name_fd is not None:
            lockfile.release(name_fd)


def _in_use(path: Path, real: Path, holder: str, how: str = "") -> ConfigError:
    resolved = "" if str(real) == str(path) else f" (the file {str(real)!r})"
    return ConfigError(
        f"backup_path {str(path)!r}{resolved} is in use by another registrar{how} (pid "
        f"{holder}); give each registrar its own backup file"
    )


def claim(path: Path) -> BackupLock | None:
    """Make the caller the one registrar of the backup at `path`, until `release()` (why:
    docs/how-to/persistence.md); `None` in a simulation, whose files are its own.

    Raises:
        ConfigError: another registrar has it open (naming its pid), or the lock file
            cannot be made.
    """
    if not runtime.guards_files():
        return None
    real = Path(os.path.realpath(path))
    lock_name = f"{real}{LOCK_SUFFIX}"
    try:
        fd = lockfile.claim(lock_name)
    except lockfile.HeldError as held:
        raise _in_use(path, real, held.holder) from None
    except OSError as exc:
        raise ConfigError(
            f"backup_path {str(path)!r}: its lock file {lock_name} cannot be created: "
            f"{exc.strerror}"
        ) from exc
    lock = BackupLock(path, real, fd)
    try:
        if real.exists():
            lock.hold_file()
    except BaseException:
        lock.release()
        raise
    return lock


def remove_files(path: Path, suffixes: tuple[str, ...] = ("", *SIDE_FILES)) -> None:
    for suffix in suffixes:
        with contextlib.suppress(FileNotFoundError):
            Path(f"{path}{suffix}").unlink()


def create(path: Path, *, synced: bool = False) -> bool:
    """Write an empty catalog (`schema.empty_image`: no SQLite connection) under a
    temporary name, then link it into place (a file another process created first wins);
    whether this one was. `ConfigError` if it cannot be. `synced` (`durability="power"`):
    the file, then its name, on the disk (two syncs); else its pages are written back, not
    synced, before it is named (`write_back`)."""
    tmp = temporary_path(path, "creating")
    linked = False
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, FILE_MODE)
        with open(fd, "wb") as file:
            os.fchmod(fd, FILE_MODE)  # (whatever the umask)
            file.write(schema.empty_image())
            file.flush()
            os.fdatasync(fd) if synced else write_back(fd)
        with contextlib.suppress(FileExistsError):
            os.link(tmp, path)
            linked = True
        if synced:
            sync(path, directory=True)
    except OSError as exc:
        raise ConfigError(f"backup_path {str(path)!r} cannot be created: {exc}") from exc
    finally:
        with contextlib.suppress(FileNotFoundError):  # (a random name: not another's)
            tmp.unlink()
    return linked


def copy_aside(db: sqlite3.Connection, path: Path) -> Path:
    """Copy the database `db` has open (even deleted) into a new file next to `path`;
    its name. Raises `sqlite3.Error` or `OSError`, leaving nothing behind."""
    tmp = temporary_path(path, "rewriting")
    try:
        _private_file(tmp)
        copy = sqlite3.connect(tmp, isolation_level=None)
        try:
            db.backup(copy)
            copy.execute("PRAGMA journal_mode = WAL")
        finally:
            copy.close()
    except BaseException:
        remove_files(tmp)
        raise
    return tmp


def put_in_place(tmp: Path, path: Path, *, synced: bool = False) -> None:
    """Move the complete file `tmp` to `path`, its stale side files removed first (every
    connection to the old file closed; `synced`: the file, then its new name, reach the
    disk first). `OSError`: `tmp` is kept, maybe the only copy."""
    if synced:
        sync(tmp)
    remove_files(path, SIDE_FILES)
    os.replace(tmp, path)
    if synced:
        sync(path, directory=True)
    remove_files(tmp, SIDE_FILES)


def sync(path: str | os.PathLike[str], *, directory: bool = False) -> None:
    """`fdatasync` the file at `path`, or `fsync` its `directory` (`OSError`)."""
    name = os.path.dirname(os.path.abspath(path)) if directory else path
    fd = os.open(name, os.O_RDONLY | os.O_CLOEXEC)
    try:
        (os.fsync if directory else os.fdatasync)(fd)
    finally:
        os.close(fd)


def write_back(fd: int) -> None:
    """Start writing the open file's pages out, not waiting nor syncing (Linux: ext4 then
    writes them before it commits a name given to the file later, so a power cut leaves no
    name or the whole file, never an empty one); never raises."""
    with contextlib.suppress(OSError, AttributeError):  # (no `posix_fadvise`: macOS)
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)


@contextlib.contextmanager
def read_only(path: Path, *, tidy: bool) -> Iterator[sqlite3.Connection]:
    """A read-only connection; with `tidy`, remove the empty `-wal`/`-shm` it created."""
    existed = {suffix: Path(f"{path}{suffix}").exists() for suffix in ("-wal", "-shm")}
    db = connect(path, read_only=True)
    try:
        yield db
    finally:
        db.close()
        wal = Path(f"{path}-wal")
        if tidy and not existed["-wal"] and wal.exists() and wal.stat().st_size == 0:
            for suffix in ("-wal", "-shm"):
                if not existed[suffix]:
                    with contextlib.suppress(FileNotFoundError):
                        Path(f"{path}{suffix}").unlink()


def validate(path: Path, *, tidy: bool) -> int:
    name = str(path)
    problem = _file_problem(path)
    if problem is not None:
        raise CatalogCorruptError(name, problem)
    with as_corrupt(name), read_only(path, tidy=tidy) as db:
        return schema.schema_version(db, name)


@contextlib.contextmanager
def inspected(path: Path, *, unpickle: bool) -> Iterator[tuple[sqlite3.Connection, int]]:
    """The backup at `path` for inspection (`read_backup`), never changed: validated, read
    only, its pages checked, an older schema migrated in a copy in memory; with its schema
    version. What the body raises of SQLite, unpickling or a row check: `as_corrupt`.

    Raises:
        ConfigError: no file at `path`; with `unpickle`, it belongs to another user.
        CatalogCorruptError: the file is not a readable rr_actors catalog.
    """
    if not is_file(path):
        raise ConfigError(f"no catalog backup at {str(path)!r}")
    foreign = foreign_owner(path) if unpickle else None
    if foreign is not None:
        raise ConfigError(
            f"catalog backup {foreign}: reading its values would run code from it "
            "(unpickling); `rr-actors observe --state` and `graph --state` show it "
            "without unpickling anything"
        )
    version, name = validate(path, tidy=True), str(path)
    with as_corrupt(name), read_only(path, tidy=True) as db:
        check_pages(db, name)
        if version == schema.SCHEMA_VERSION:
            yield db, version
            return
        copy = sqlite3.connect(":memory:", isolation_level=None)
        try:
            db.backup(copy)
            schema.migrate(copy, version)
            yield copy, version
        finally:
            copy.close()


def prepare(db: sqlite3.Connection, name: str, durability: str, version: int) -> None:
    try:
        db.execute("BEGIN IMMEDIATE")  # can we write here at all?
        db.execute("ROLLBACK")
    except sqlite3.OperationalError as exc:
        raise ConfigError(f"backup_path {name!r} is not writable: {exc}") from exc
    with as_corrupt(name):
        mode = db.execute("PRAGMA journal_mode = WAL").fetchone()[0]
    if mode != "wal":  # before anything is written: an older file stays as it was
        raise ConfigError(f"backup_path {name!r}: SQLite cannot use WAL mode there ({mode})")
    with as_corrupt(name):
        db.execute(f"PRAGMA synchronous = {SYNCHRONOUS[durability]}")
        schema.migrate(db, version)
    schema.refresh_digests(db, name)


def is_file(path: Path) -> bool:
    try:
        return path.is_file()
    except OSError:
        return False


def foreign_owner(path: Path) -> str | None:
    """Why `path` (or its `-wal`) is not the current user's to unpickle, or `None`."""
    me = os.geteuid()
    for name in (str(path), f"{path}-wal"):
        try:
            owner = os.stat(name).st_uid
        except OSError:
            continue
        if owner != me:
            return f"{name!r} belongs to uid {owner}, not to this user (uid {me})"
    return None


def check_pages(db: sqlite3.Connection, name: str) -> None:
    """Check every page of the file (`PRAGMA quick_check`; `CatalogCorruptError`)."""
    with as_corrupt(name):
        found = db.execute("PRAGMA quick_check").fetchall()
    if found != [("ok",)]:
        lines = [line for (row,) in found for line in str(row).splitlines()]
        listed = "; ".join([line for line in lines if not line.startswith("***")][:3])
        raise CatalogCorruptError(name, f"damaged pages: {listed}")


def quarantine_backup(path: str | os.PathLike[str]) -> Path:
    """Move a catalog backup that cannot be used out of the way, keeping it for analysis.

    The file and its companions are renamed to `<path>.corrupt-<UTC timestamp>`; a
    registrar started on `path` afterwards starts empty. rr_actors never does this on its
    own.

    Args:
        path: the backup file, as in `RegistrarConfig.backup_path`.

    Returns:
        The new path of the quarantined file.

    Raises:
        ConfigError: there is no file at `path`, or a registrar has it open (naming its
            pid).
    """
    file = Path(os.fspath(path))
    if not is_file(file):
        raise ConfigError(f"no catalog backup to quarantine at {str(file)!r}")
    stamp = datetime.datetime.fromtimestamp(runtime.wall(), datetime.UTC).strftime(
        "%Y%m%dT%H%M%S.%fZ"
    )
    target = file.with_name(f"{file.name}.corrupt-{stamp}")
    lock = claim(file)  # (a registrar that has it open keeps it)
    try:
        for suffix in SIDE_FILES:  # companions first: the main file's name is the anchor
            side = Path(f"{file}{suffix}")
            if side.exists():
                side.rename(f"{target}{suffix}")
        file.rename(target)
    finally:
        if lock is not None:
            lock.release()
    return target


FileId = tuple[int, int]  # (st_dev, st_ino)


def file_ids(path: Path | str) -> tuple[FileId | None, FileId | None]:
    ids: list[FileId | None] = []
    for name in (os.fspath(path), f"{path}-wal"):
        try:
            st = os.stat(name)
        except OSError:
            ids.append(None)
        else:
            ids.append((st.st_dev, st.st_ino))
    return ids[0], ids[1]


def moved(path: Path | str, known: tuple[FileId | None, FileId | None]) -> str | None:
    """Why `path` (or its `-wal`) no longer names the file a connection opened (`known`:
    `file_ids` then), or `None`."""
    now = file_ids(path)
    for what, was, is_now in (("the file", known[0], now[0]), ("its -wal", known[1], now[1])):
        if was is None or was == is_now:
            continue
        return f"{what} was deleted" if is_now is None else f"{what} was replaced"
    return None


def write_error(path: str, exc: BaseException) -> CatalogWriteError:
    if isinstance(exc, OSError) and exc.errno is not None:
        name = errno_names.errorcode.get(exc.errno, str(exc.errno))
        return CatalogWriteError(path, f"{name} ({exc.strerror})", exc.errno)
    if isinstance(exc, sqlite3.Error):
        code = getattr(exc, "sqlite_errorname", None) or type(exc).__name__
        if code == "SQLITE_FULL":  # SQLite's unix VFS says so for ENOSPC (or a short write)
            return CatalogWriteError(
                path,
                f"ENOSPC ({os.strerror(errno_names.ENOSPC)}): {exc} ({code})",
                errno_names.ENOSPC,
            )
        return CatalogWriteError(path, f"{exc} ({code})")
    return CatalogWriteError(path, f"{type(exc).__name__}: {exc}")


# -- the file a store writes ---------------------------------------------------------------------


def open_backup(path: Path, durability: str) -> tuple[BackupFile, sqlite3.Connection, bool, bool]:
    """Claim, create if missing, validate and prepare the backup at `path` for writing
    (`SqliteStore.open`): the file, its writable connection, whether it was created, and
    whether its pages were checked. A commit count the log no longer holds is logged
    (WARNING) and kept in `BackupFile.lost_commits`.

    Raises:
        ConfigError: the path cannot hold a backup, the file belongs to another user,
            or another registrar has it open.
        CatalogCorruptError: the file is not a usable rr_actors catalog.
    """
    check_location(path)
    lock = claim(path)  # before anything reads it: one registrar a file
    try:
        return _open(path, lock, durability)
    except BaseException:
        if lock is not None:
            lock.release()
        raise


def _open(
    file: Path, lock: BackupLock | None, durability: str
) -> tuple[BackupFile, sqlite3.Connection, bool, bool]:
    created = made = False
    lost = None
    if not file.exists():
        made = create(file, synced=durability == "power")
        created = True
    if lock is not None:
        lock.hold_file()
    foreign = foreign_owner(file)
    if foreign is not None:
        raise ConfigError(
            f"backup_path {foreign}: restoring it would run code from it (unpickling)"
        )
    if not created:
        lost = lost_commits(file)  # before SQLite replays (and may remove) the log
    version = schema.SCHEMA_VERSION if made else validate(file, tidy=True)  # (known)
    name = str(file)
    try:
        db = connect(file, read_only=False)
    except sqlite3.Error as exc:
        raise ConfigError(f"backup_path {name!r} cannot be opened: {exc}") from exc
    checked = created or not runtime.guards_files()
    try:
        if not checked and _open_writes(db, name, version):
            check_pages(db, name)  # (before anything is written to it: rule 15)
            checked = True
        if made:  # (empty, current, WAL, written there already)
            db.execute(f"PRAGMA synchronous = {SYNCHRONOUS[durability]}")
        else:
            prepare(db, name, durability, version)
            with as_corrupt(name):  # the outbox: read at the last run's exit, if anyone listened
                if db.execute("SELECT EXISTS (SELECT 1 FROM outbox)").fetchone()[0]:
                    db.execute("DELETE FROM outbox")
    except BaseException:
        db.close()
        raise
    backup = BackupFile(file, lock, durability)
    if lost is not None:
        backup.lost_commits, why = lost
        logger.warning(
            "catalog backup %s: %s: %d acknowledged commits are lost (their loads, "
            "releases and unloads are not restored; consumers holding ids it lost are "
            "told FATAL when they reconcile)",
            name,
            why,
            backup.lost_commits,
        )
        backup.commits.close()  # reported once: the next commit counts the log afresh
    return backup, db, created, checked


def _open_writes(db: sqlite3.Connection, name: str, version: int) -> bool:
    """Whether opening the file writes to it (a migration, or last run's outbox to clear)."""
    if version != schema.SCHEMA_VERSION:
        return True
    with as_corrupt(name):
        return bool(db.execute("SELECT EXISTS (SELECT 1 FROM outbox)").fetchone()[0])


class BackupFile:
    """The file a store writes, kept at its path: the lock that makes its store the one
    registrar of it, whether the path still names it (`keep_in_place`), and the count of
    its commits (`CommitCount`). The writer's thread; in a simulation (`guarded` false) its
    files are its own: nothing is watched nor counted."""

    def __init__(self, path: Path, lock: BackupLock | None, durability: str) -> None:
        self.path = str(path)  # as given: what messages name
        self.file = path.absolute()  # the same file after a chdir
        self._name = str(self.file)
        self._names = (self._name, f"{self._name}-wal")
        self._lock = lock
        self.synchronous = SYNCHRONOUS[durability]
        self.synced = durability == "power"
        self.guarded = runtime.guards_files()
        self._ids = file_ids(self._name) if self.guarded else (None, None)
        self._watch = PLATFORM.watch_names() if self.guarded else None
        self.aside: Path | None = None  # a whole copy not moved into place yet
        self.commits = CommitCount(self.file, kept=self.guarded, synced=self.synced)
        self.lost_commits = 0  # of the last run, that its WAL no longer held

    def quiet(self) -> bool:
        """Whether the path surely still names the file: the platform's watch saw no change
        of its names, and no copy waits to be put in place."""
        watch = self._watch
        return watch is not None and watch.armable and self.aside is None and watch.quiet()

    def keep_in_place(
        self, db: sqlite3.Connection, close: Callable[[], None]
    ) -> sqlite3.Connection | None:
        """Write the whole catalog `db` has open to a new file if the path lost this one
        ("A deleted backup", failure-semantics.md): two `stat`s, only once the platform's
        watch (`Platform.watch_names`) told of a change. `close` closes every connection to
        the old file before the copy is put in place. Returns the new file's connection,
        or `None` if the path still names the file.

        Raises:
            CatalogWriteError: the copy failed (kept in `aside`, retried next time).
        """
        if not self.guarded:
            return None
        if self.aside is None:  # (a watch that cannot watch yet: `stat`s, not asked)
            watch = self._watch if self._watch is not None and self._watch.armable else None
            if watch is not None and watch.quiet():  # nothing happened to the names
                return None
            if self._ids[1] is None:  # the -wal appears with the first transaction
                self._ids = (self._ids[0], file_ids(self._name)[1])
            if watch is not None and self._ids[1] is not None:
                watch.arm(self._names)  # (first: a change made during the check is told)
            why = moved(self._name, self._ids)
            if why is None:
                return None
            logger.warning(
                "catalog backup %s: %s while its registrar runs; writing the whole catalog "
                "to a new file there",
                self.path,
                why,
            )
            try:
                self.aside = copy_aside(db, self.file)
            except (sqlite3.Error, OSError) as exc:
                raise write_error(self.path, exc) from exc
            close()
        try:  # no connection is open on the old file now: SQLite would remove the new -wal
            put_in_place(self.aside, self.file, synced=self.synced)
            self.aside = None
            if self._lock is not None:  # (before SQLite locks the new file: see `lockfile`)
                self._lock.file_replaced()
            db = connect(self.file, read_only=False)
            db.execute(f"PRAGMA synchronous = {self.synchronous}")
        except (sqlite3.Error, OSError) as exc:
            raise write_error(self.path, exc) from exc
        if self._watch is not None:
            self._watch.close()  # (armed at the next commit, once the new -wal exists)
        self._ids = file_ids(self.file)
        self.commits.reopen()
        return db

    def closing(self) -> None:
        """Stop counting and watching, before the connections close (SQLite removes the
        log as it closes)."""
        self.commits.close()
        if self._watch is not None:
            self._watch.close()

    def erase(self) -> None:
        """Delete the file, its companions and any copy set aside."""
        remove_files(self.file)
        if self.aside is not None:
            remove_files(self.aside)

    def release(self) -> None:
        """Give the file up: another registrar may open it now (never raises)."""
        lock, self._lock = self._lock, None
        if lock is not None:
            lock.release()


# -- the commits counted beside the WAL --------------------------------------------------

COUNT_SUFFIX = "-commits"  # the count's file, beside the backup (`erm.db-commits`)

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
        self.path = f"{file}{COUNT_SUFFIX}"
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
        record = Path(f"{file}{COUNT_SUFFIX}").read_bytes()[: _RECORD.size]
        checkpointed = os.stat(file).st_mtime_ns > os.stat(f"{file}{COUNT_SUFFIX}").st_mtime_ns
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
